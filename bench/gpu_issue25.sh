#!/usr/bin/env bash
# Issue 25's GPU figures in one call of the device tool on a lent NVIDIA machine (see
# ../shared/GPU.md; a session has 15 minutes of device time, starts included, so one call does
# it all): the environment of bench/gpu_env.sh, the Numba solver compiling in the background
# (one and two bounces, cached in $NUMBA_CACHE_DIR for the later steps), then, each with its own
# time limit so that the call ends within ~9 minutes:
#   1. bench/flux_device.py: the 115k wavy sheet, forward-flux on Numba (every core) and on the
#      GPU (refinement, tracing, splat; target 1024² <= 0.5 s a frame);
#   2. bench/solver.py --opencl: R and T at N1 tuples (target >= 20x the 16-core Numba rate);
#   3. bench/opencl_profile.py: two-bounce chains CHAINS at N2 tuples, every stage on the GPU
#      (target TT >= 10x).
# Tables, logs, BENCHMARKS.md and the GPU results page go to $OUT (7 files).
#
#   bash bench/gpu_issue25.sh        (from the repository root; carry .whl; timeout_s 590)
# N1 (default 1000000), N2 (default 2000), CHAINS (default RR,TT), RESOLUTIONS (default 1024)
# shrink or widen it; without NVIDIA's library it runs on the OpenCL device there is (PoCL here).
set -u
N1=${N1:-1000000}
N2=${N2:-2000}
CHAINS=${CHAINS:-RR,TT}
cd "$(dirname "$0")/.."
. bench/gpu_env.sh  # OUT, log, DEV, WARM_UP_PY, the environment

log "Numba one- and two-bounce compile, in the background"
( timeout 300 python3 -c "$WARM_UP_PY" 2 \
  > "$OUT/warm.txt" 2>&1 ) &
WARM=$!

log "1. flux_device.py ${RESOLUTIONS:-1024}"
timeout 170 python3 bench/flux_device.py --device "$DEV" --resolutions "${RESOLUTIONS:-1024}" --frames 2 \
  > "$OUT/flux_device.txt" 2>&1
log "flux_device exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"

wait $WARM
log "warm-up done: $(tail -1 "$OUT/warm.txt")"

log "2. solver.py --opencl, R and T at $N1 tuples"
timeout 110 python3 bench/solver.py --opencl --tuples "$N1" --two-bounce-tuples 0 --repeats 2 \
  > "$OUT/solver_opencl.txt" 2>&1
log "solver.py exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"

LEFT=$(( 540 - ($(date +%s) - T0) ))
log "3. opencl_profile $CHAINS at $N2 tuples (${LEFT} s left)"
if [ "$LEFT" -gt 30 ]; then
  timeout "$LEFT" python3 bench/opencl_profile.py --device "$DEV" --chains "$CHAINS" --two-bounce-tuples "$N2" \
    --repeats 2 > "$OUT/opencl_profile_two.txt" 2>&1
  log "opencl_profile exit $?"
fi
cp bench/results/opencl_profile_gpu.md "$OUT/" 2>/dev/null
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
log "done"
