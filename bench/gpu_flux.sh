#!/usr/bin/env bash
# The forward-flux device check, for one call of the device tool on a lent NVIDIA machine (see
# ../shared/GPU.md and bench/gpu_check.sh): pyopencl from the carried wheels (.whl/), NVIDIA's
# OpenCL ICD, then bench/flux_device.py (the wavy sheet baked with its points traced by Numba on
# every core and by the GPU).  The first bake compiles the Numba pipeline (minutes there);
# RESOLUTIONS (default 512,1024) and FRAMES (default 1) size it.  Logs and BENCHMARKS.md go to $OUT.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
cd "$(dirname "$0")/.."
NVLIB=/usr/local/nvidia/lib64/libnvidia-opencl.so
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl > /tmp/pip.txt 2>&1 || tail -5 /tmp/pip.txt
  export PYTHONPATH=/tmp/site
fi
if [ -e "$NVLIB" ]; then
  mkdir -p /tmp/icd && echo "$NVLIB" > /tmp/icd/nvidia.icd && export OCL_ICD_VENDORS=/tmp/icd
fi
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/nc} PYTHONUNBUFFERED=1
DEV=$(python3 -c "
import pyopencl as cl
i = 0
for p in cl.get_platforms():
    for d in p.get_devices():
        if 'NVIDIA' in p.name and 'cl_khr_fp64' in d.extensions:
            print(i); raise SystemExit
        i += 1
print(0)")
echo "OpenCL device $DEV"
timeout "${LIMIT:-230}" python3 bench/flux_device.py --device "$DEV" --resolutions "${RESOLUTIONS:-512,1024}" \
  --frames "${FRAMES:-1}" 2>&1 | tee "$OUT/flux_device.txt"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
