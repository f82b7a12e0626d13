"""The one-bounce OpenCL kernel's launch shapes on one device: one stage or the split pipeline
(filter, prefix sums, solve over the survivors, gather), at several work-group sizes.

    OCL_ICD_VENDORS=... python bench/opencl_shapes.py [--device N] [--tuples 1000000,4000000]
        [--planted-tuples 1000000] [--groups 32,64,128,256] [--repeats 2] [--no-write]

Workloads: R and T tuples as (emitter, point) int32 index pairs over tables kept on the device
(``spoly.api.TupleTable``, as a bake sends them): "random pairs" over 65,536 random emitters
and points, "planted pairs" one planted path per emitter.  Each row: best wall of --repeats
solves, and the device time of the solve's kernels (profiling events) in one more.  The last
line names the fastest shape on the random pairs (summed over R and T): ``best: stages=S
group=G``, which ``bench/gpu_check.sh`` hands on to the benchmarks that follow.  Writes
bench/results/opencl_shapes_{cpu,gpu}.md unless --no-write.
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

from workloads import planted_pairs, random_pairs  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", type=int, default=None)
    parser.add_argument("--tuples", default="1000000,4000000", help="random pairs per row (comma list)")
    parser.add_argument("--planted-tuples", type=int, default=1_000_000)
    parser.add_argument("--groups", default="32,64,128,256")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()

    from addon.solver.opencl import backend
    from addon.solver.spoly.api import TupleTable

    devices = [d for d in backend.list_devices() if d[3]]
    index = args.device if args.device is not None else int(os.environ.get("OPENCL_DEVICE", devices[0][0]))
    d = backend._context(index)
    limit = d.kernel_info(d.kernel_one)[0]
    groups = [g for g in (int(x) for x in args.groups.split(",")) if g <= limit]
    print(f"device {index}: {d.label}; kernel limit {limit}", flush=True)

    rng = np.random.default_rng(3)  # one stream: each size's pairs follow the previous size's
    workloads = [("random pairs", random_pairs(int(n), rng)) for n in args.tuples.split(",")]
    rows, totals = [], {}
    for chain in ("R", "T"):
        cases = workloads + [("planted pairs", planted_pairs(args.planted_tuples, chain))]
        for name, (x0, P, N, x2, e, s) in cases:
            table = TupleTable(chain, x0, P, N, 1.5, x2, device=f"opencl:{index}")
            reference = None
            for stages in ("1", "2"):
                os.environ["CAUSTIC_OPENCL_STAGES"] = stages
                for g in groups:
                    d.local_one = g
                    table.solve(e[:256], s[:256])
                    best = float("inf")
                    for _ in range(args.repeats):
                        t0 = time.perf_counter()
                        result = table.solve(e, s)
                        best = min(best, time.perf_counter() - t0)
                    if reference is None:
                        reference = result
                    same = np.array_equal(result.tuple_index, reference.tuple_index) and \
                        np.array_equal(result.uv, reference.uv)
                    prof = backend.Profiler()
                    backend.set_profiling(index, prof)
                    try:
                        table.solve(e, s)
                    finally:
                        backend.set_profiling(index, None)
                    dev = prof.device_seconds()
                    kernels = sum(v for k, v in dev.items() if k.startswith("kernel"))
                    row = dict(chain=chain, workload=name, tuples=e.size, paths=result.report.paths, stages=stages,
                               group=g, wall=best, kernels=kernels, same="yes" if same else "NO")
                    rows.append(row)
                    print(line(row), flush=True)
                    if name == "random pairs" and e.size == int(args.tuples.split(",")[0]):
                        totals[(stages, g)] = totals.get((stages, g), 0.0) + best
    os.environ.pop("CAUSTIC_OPENCL_STAGES", None)
    stages, g = min(totals, key=totals.get)
    kind = "cpu" if d.is_cpu else "gpu"
    lines = [f"# One-bounce OpenCL launch shapes (`bench/opencl_shapes.py`)", "",
             f"Device {index}: **{d.label}** ({'CPU' if d.is_cpu else 'GPU/accelerator'}, {d.dev.max_compute_units} "
             f"compute units); host {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
             f"best of {args.repeats}; date {time.strftime('%Y-%m-%d')}.", "",
             "Tuples as index pairs over tables kept on the device; stages 1 = one kernel, paths sorted on the host; "
             "2 = filter, prefix sums, solve over the survivors, gather (canonical order on the device). "
             "\"same\": the paths equal the first shape's, bit for bit.", "",
             "| chain | workload | tuples | paths | stages | work-group | wall (ms) | µs / tuple | kernels (ms) | same |",
             "|---|---|---|---|---|---|---|---|---|---|"] + [line(r) for r in rows] + ["",
             f"Fastest on the random pairs (R + T at {int(args.tuples.split(',')[0]):,}): stages {stages}, work-group {g}."]
    if not args.no_write:
        os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
        with open(os.path.join(HERE, "results", f"opencl_shapes_{kind}.md"), "w") as f:
            f.write("\n".join(lines) + "\n")
    print(f"best: stages={stages} group={g}")


def line(r):
    return (f"| {r['chain']} | {r['workload']} | {r['tuples']:,} | {r['paths']:,} | {r['stages']} | {r['group']} | "
            f"{r['wall'] * 1e3:.1f} | {r['wall'] / r['tuples'] * 1e6:.4f} | {r['kernels'] * 1e3:.1f} | {r['same']} |")


if __name__ == "__main__":
    main()
