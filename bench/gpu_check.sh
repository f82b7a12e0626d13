#!/usr/bin/env bash
# The OpenCL GPU check, for one call of the device tool on a lent NVIDIA machine
# (see ../shared/GPU.md): the environment of bench/gpu_env.sh, then
#   1. bench/opencl_shapes.py: the one-bounce launch shapes (one stage / split pipeline, work-group
#      sizes), while the Numba one-bounce kernels compile in the background;
#   2. with the fastest shape: bench/solver.py --opencl (Numba on every core against OpenCL, R and
#      T, tuples given directly and as index pairs) and bench/opencl_profile.py --chains R,T.
# Every step has a time limit so that the whole script ends within ~5 minutes; tables, logs,
# BENCHMARKS.md and the results pages go to $OUT (7 files: the device tool brings back 8 at most).
#
#   bash bench/gpu_check.sh        (from the repository root; carry .whl)
# N1 (one-bounce tuples, default 1000000) shrinks it for a dry run; N2 > 0 (two-bounce tuples)
# adds the two-bounce rows to solver.py, whose staged pipeline takes ~6 minutes of cold Numba
# compilation there; SHAPE_GROUPS (default 128,256) the work-group sizes of the sweep.  Without NVIDIA's library the ICD setting is left as it is (PoCL here).
set -u
N1=${N1:-1000000}
N2=${N2:-0}
cd "$(dirname "$0")/.."
. bench/gpu_env.sh  # OUT, log, DEV, WARM_UP_PY, the environment

log "Numba one-bounce compile, in the background"
python3 -c "$WARM_UP_PY" 1 \
  > /tmp/warm.txt 2>&1 &
WARM=$!

python3 - <<'EOF' | tee -a "$OUT/steps.txt"
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

log "opencl_shapes"
timeout 170 python3 bench/opencl_shapes.py --device "$DEV" --tuples "$N1,$((4 * N1))" --groups "${SHAPE_GROUPS:-128,256}" \
  --planted-tuples "$N1" --repeats 2 > "$OUT/shapes.txt" 2>&1
log "opencl_shapes exit $?"
cp bench/results/opencl_shapes_gpu.md "$OUT/" 2>/dev/null
BEST=$(grep '^best:' "$OUT/shapes.txt" | tail -1)
if [ -n "$BEST" ]; then
  export CAUSTIC_OPENCL_STAGES=$(echo "$BEST" | sed 's/.*stages=\([0-9]*\).*/\1/')
  export CAUSTIC_OPENCL_WORK_GROUP=$(echo "$BEST" | sed 's/.*group=\([0-9]*\).*/\1/')
fi
log "shape for what follows: stages ${CAUSTIC_OPENCL_STAGES:-default}, group ${CAUSTIC_OPENCL_WORK_GROUP:-default}"

wait $WARM
log "warm-up done: $(tail -1 /tmp/warm.txt)"

log "solver.py --opencl"
timeout 120 python3 bench/solver.py --opencl --tuples "$N1" --two-bounce-tuples "$N2" --repeats 2 \
  > "$OUT/solver_opencl.txt" 2>&1
log "solver.py exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"

log "opencl_profile R,T"
timeout 100 python3 bench/opencl_profile.py --device "$DEV" --chains R,T --tuples "$N1" \
  --planted-tuples "$N1" --repeats 2 > "$OUT/opencl_profile.txt" 2>&1
log "opencl_profile exit $?"
cp BENCHMARKS.md "$OUT/BENCHMARKS.md"
cp bench/results/opencl_profile_gpu.md "$OUT/" 2>/dev/null
log "done"
