# Sourced by the bench/gpu_*.sh scripts on a lent NVIDIA machine (see ../shared/GPU.md), from the
# repository root: $OUT (default /tmp/out) made, log() (seconds since the start, appended to
# $OUT/steps.txt), pyopencl from the carried wheels (.whl/) into /tmp/site, NVIDIA's OpenCL library
# as the only ICD (left as it is where the library is missing: PoCL here), the Numba cache in
# /tmp/nc, OPENCL_DEVICE (and DEV) = the first NVIDIA device with double precision (0 when there
# is none), logged with nvidia-smi's list, and WARM_UP_PY: `python3 -c "$WARM_UP_PY" B` compiles
# the Numba solver up to B bounces (addon.solver.warm_up).  Problems are appended to $GPU_LOG
# (default $OUT/steps.txt).
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
T0=$(date +%s)
log() { echo "[$(( $(date +%s) - T0 )) s] $*" | tee -a "$OUT/steps.txt"; }
GPU_LOG=${GPU_LOG:-$OUT/steps.txt}
log "environment (bench/gpu_env.sh)"
NVLIB=/usr/local/nvidia/lib64/libnvidia-opencl.so
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl > /tmp/pip.txt 2>&1 \
    || { echo "pip install failed:" >> "$GPU_LOG"; tail -5 /tmp/pip.txt >> "$GPU_LOG"; }
  export PYTHONPATH=/tmp/site
fi
if [ -e "$NVLIB" ]; then
  mkdir -p /tmp/icd
  echo "$NVLIB" > /tmp/icd/nvidia.icd
  export OCL_ICD_VENDORS=/tmp/icd
else
  echo "no $NVLIB: OCL_ICD_VENDORS=${OCL_ICD_VENDORS:-unset}" >> "$GPU_LOG"
fi
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/nc}
export PYTHONUNBUFFERED=1
OPENCL_DEVICE=$(python3 - <<'PY'
import pyopencl as cl
i = 0
for p in cl.get_platforms():
    for d in p.get_devices():
        if "NVIDIA" in p.name and "cl_khr_fp64" in d.extensions:
            print(i)
            raise SystemExit
        i += 1
print(0)
PY
)
export OPENCL_DEVICE
DEV=$OPENCL_DEVICE
nvidia-smi -L 2>&1 | tee -a "$OUT/steps.txt"
log "OpenCL device $DEV"
WARM_UP_PY='import sys; sys.path.insert(0, "."); from addon.solver import warm_up; print("warm-up s", warm_up(int(sys.argv[1])))'
