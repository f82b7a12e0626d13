#!/usr/bin/env bash
# The OpenCL GPU check, for one call of the device tool on a lent NVIDIA machine
# (see ../shared/GPU.md): pyopencl from the carried wheels (.whl/), NVIDIA's OpenCL ICD,
# then bench/opencl_profile.py and bench/solver.py --opencl on the GPU.  Every step has a
# time limit so that the whole script ends within ~6 minutes, the ~1.5 minute cold Numba
# compile included; outputs (tables, logs, BENCHMARKS.md) go to $OUT.
#
#   bash bench/gpu_check.sh        (from the repository root; carry .whl)
# N1 (one-bounce tuples, default 1000000) and N2 (two-bounce tuples, default 200) shrink it
# for a dry run; without NVIDIA's library the ICD setting is left as it is (PoCL here).
set -u
N1=${N1:-1000000}
N2=${N2:-200}
NVLIB=/usr/local/nvidia/lib64/libnvidia-opencl.so
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
cd "$(dirname "$0")/.."
T0=$(date +%s)
log() { echo "[$(( $(date +%s) - T0 )) s] $*" | tee -a "$OUT/steps.txt"; }

log "install carried wheels"
python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl \
  > "$OUT/pip.txt" 2>&1 || log "pip install failed (see pip.txt)"
export PYTHONPATH=/tmp/site
if [ -e "$NVLIB" ]; then
  mkdir -p /tmp/icd
  echo "$NVLIB" > /tmp/icd/nvidia.icd
  export OCL_ICD_VENDORS=/tmp/icd
else
  log "no $NVLIB: OCL_ICD_VENDORS=${OCL_ICD_VENDORS:-unset}"
fi
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/nc}

nvidia-smi -L 2>&1 | tee "$OUT/gpu.txt"
python3 - <<'EOF' | tee -a "$OUT/gpu.txt"
import numba, numpy, platform, pyopencl as cl
print("python", platform.python_version(), "numpy", numpy.__version__,
      "numba", numba.__version__, "pyopencl", cl.VERSION_TEXT)
i = 0
for p in cl.get_platforms():
    for d in p.get_devices():
        print(f"opencl {i}: {p.name} | {d.name} | fp64 {'cl_khr_fp64' in d.extensions}"
              f" | {d.max_compute_units} CUs | driver {d.driver_version}")
        i += 1
EOF

# The first NVIDIA device with double precision.
DEV=$(python3 - <<'EOF'
import pyopencl as cl
i = 0
for p in cl.get_platforms():
    for d in p.get_devices():
        if "NVIDIA" in p.name and "cl_khr_fp64" in d.extensions:
            print(i)
            raise SystemExit
        i += 1
print(0)
EOF
)
export OPENCL_DEVICE=$DEV
log "OpenCL device $DEV"

log "opencl_profile (cold Numba compile first)"
timeout 210 python3 bench/opencl_profile.py --device "$DEV" \
  --tuples "$N1" --planted-tuples "$N1" --two-bounce-tuples "$N2" \
  --repeats 2 > "$OUT/opencl_profile.txt" 2>&1
log "opencl_profile exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"

log "one bounce at work-group 64"
CAUSTIC_OPENCL_WORK_GROUP=64 timeout 40 python3 bench/opencl_profile.py \
  --device "$DEV" --chains R,T --tuples "$N1" --planted-tuples "$N1" \
  --repeats 2 --no-write > "$OUT/opencl_profile_wg64.txt" 2>&1
log "work-group 64 exit $?"

log "solver.py --opencl"
timeout 95 python3 bench/solver.py --opencl --tuples "$N1" \
  --two-bounce-tuples "$N2" --repeats 2 > "$OUT/solver_opencl.txt" 2>&1
log "solver.py exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
log "done"
