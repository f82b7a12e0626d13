#!/usr/bin/env bash
# The forward-flux device check, for one call of the device tool on a lent NVIDIA machine (see
# ../shared/GPU.md and bench/gpu_check.sh): the environment of bench/gpu_env.sh, then
# bench/flux_device.py (the wavy sheet baked by Numba on every core and with its refinement,
# tracing and splat on the GPU).  The first bake compiles the Numba pipeline (minutes there);
# RESOLUTIONS (default 512,1024) and FRAMES (default 1) size it.  Logs and BENCHMARKS.md go to $OUT.
set -u
cd "$(dirname "$0")/.."
. bench/gpu_env.sh  # OUT, log, DEV, the environment
timeout "${LIMIT:-230}" python3 bench/flux_device.py --device "$DEV" --resolutions "${RESOLUTIONS:-512,1024}" \
  --frames "${FRAMES:-1}" 2>&1 | tee "$OUT/flux_device.txt"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
