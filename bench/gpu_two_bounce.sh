#!/usr/bin/env bash
# The two-bounce OpenCL check, for one call of the device tool on a lent NVIDIA machine
# (see ../shared/GPU.md): the environment of bench/gpu_env.sh, the Numba two-bounce kernels
# compiled (the one-kernel solver: the baseline, and the host's path for the tuples a device
# leaves), then bench/opencl_profile.py for RR, RT, TR, TT, random and planted tuples: every
# stage of the staged pipeline on the GPU (stage A included: the default on GPUs), with its
# kernels' device times, against Numba on every core.  Tables, logs and the results page go to
# $OUT.  About 6 minutes: give the call timeout_s=560.
#
#   bash bench/gpu_two_bounce.sh        (from the repository root; carry .whl)
# N2 (two-bounce tuples a row, default 2000); CHAINS (default RR,RT,TR,TT).
set -u
N2=${N2:-2000}
CHAINS=${CHAINS:-RR,RT,TR,TT}
cd "$(dirname "$0")/.."
. bench/gpu_env.sh  # OUT, log, DEV, WARM_UP_PY, the environment

log "Numba two-bounce compile (warm_up(2))"
timeout 240 python3 -c "$WARM_UP_PY" 2 \
  > "$OUT/warm.txt" 2>&1
log "warm-up exit $?: $(tail -1 "$OUT/warm.txt")"

log "opencl_profile $CHAINS, $N2 tuples"
timeout 280 python3 bench/opencl_profile.py --device "$DEV" --chains "$CHAINS" --two-bounce-tuples "$N2" \
  --repeats 2 > "$OUT/opencl_profile_two.txt" 2>&1
log "opencl_profile exit $?"
cp bench/results/opencl_profile_gpu.md "$OUT/" 2>/dev/null
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
log "done"
