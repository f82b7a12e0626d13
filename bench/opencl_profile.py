"""Where the OpenCL back end's time goes, stage by stage, against Numba on the same tuples.

    OCL_ICD_VENDORS=/etc/OpenCL/vendors .venv/bin/python bench/opencl_profile.py
        [--tuples 1000000] [--planted-tuples 200000] [--two-bounce-tuples 200] [--repeats 2]
        [--device N] [--chains R,T,RR,RT,TR,TT] [--no-write]

One bounce (R, T; random and planted workloads of bench/workloads.py, the tuples of
bench/solver.py): host checks and packing, host→device writes, the accumulator fill, the
kernel, device→host read-back (OpenCL profiling events), the host sort into canonical order,
and the rest of the wall time.  Two bounces (RR, RT, TR, TT): inside the device call (stages
A-E of ``two_bounce.staged``) the writes, each kernel and the read-backs, the one-kernel path
on Numba for the tuples left to the host, the numpy glue, with the
number of launches and of host waits.  Every row gives the OpenCL wall time (profiling off)
and the Numba wall time on the same tuples (all threads), the two called in turn, each the
best of at least --repeats calls and 0.25 s (``solver.best_times``), their ratio, and whether
the paths are the same.

The device is the first with double precision, or ``--device N`` / ``OPENCL_DEVICE=N``.
Prints the tables and writes them to bench/results/opencl_profile_{cpu,gpu}.md (by the device's
type), and the index of those pages into BENCHMARKS.md between ``<!-- opencl-profile:begin -->``
and ``<!-- opencl-profile:end -->`` (unless --no-write).
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

from solver import PAIR_SECONDS, best_times, write_section  # noqa: E402
from workloads import planted_tuples, planted_two_bounce, random_pairs, random_tuples, random_two_bounce  # noqa: E402

ONE = ("R", "T")
TWO = ("RR", "RT", "TR", "TT")


class HostTimer:
    """Seconds spent in wrapped functions, by label (module attributes swapped while active)."""

    def __init__(self):
        self.seconds = {}
        self._swapped = []

    def wrap(self, module, name, label):
        fn = getattr(module, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - t0

        setattr(module, name, timed)
        self._swapped.append((module, name, fn))

    def restore(self):
        for module, name, fn in reversed(self._swapped):
            setattr(module, name, fn)
        self._swapped = []


def wanted(args, chain, workload):
    return chain in args.rows or f"{chain}:{workload}" in args.rows


def same_paths(a, b):
    """"yes" when both results hold the same paths (uv within 1e-9); else what differs."""
    if not np.array_equal(a.tuple_index, b.tuple_index):
        return f"NO: path counts differ in {np.count_nonzero(np.bincount(a.tuple_index, minlength=a.report.tuples) != np.bincount(b.tuple_index, minlength=b.report.tuples))} tuples"
    far = np.abs(a.uv - b.uv).max(axis=1) > 1e-9 if a.uv.size else np.zeros(0, dtype=bool)
    if far.any():
        return f"NO: {np.count_nonzero(far)} of {far.size:,} paths differ (by up to {np.abs(a.uv - b.uv).max():.0e})"
    return "yes"


def profiled_run(index, solve, chain):
    """One OpenCL solve with profiling events and host timers on: (wall, {stage: s}, profiler)."""
    from addon.solver.spoly import api
    from addon.solver.spoly.two_bounce import staged as two_bounce_staged
    from addon.solver.opencl import backend as opencl_backend

    prof = opencl_backend.Profiler()
    timer = HostTimer()
    timer.wrap(api, "validate_inputs", "validate")
    if chain in ONE:
        timer.wrap(api, "canonical_order", "sort")
    else:
        timer.wrap(api, "compact_paths", "compact")
        for name, label in (("stage_a_on_host", "A"), ("solve_on_host", "host"), ("_solve_batch", "batch")):
            timer.wrap(two_bounce_staged, name, label)
        timer.wrap(opencl_backend.OpenCLSystemSolver, "solve_batch", "device calls")
    opencl_backend.set_profiling(index, prof)
    try:
        t0 = time.perf_counter()
        solve()
        wall = time.perf_counter() - t0
        device = prof.device_seconds()
    finally:
        opencl_backend.set_profiling(index, None)
        timer.restore()
    stages = dict(timer.seconds)
    for key, value in prof.host.items():
        stages[key] = stages.get(key, 0.0) + value
    for key, value in device.items():
        stages[key] = stages.get(key, 0.0) + value
    return wall, stages, prof


def one_bounce_rows(solver, index, args):
    device = f"opencl:{index}"
    rows = []
    for chain in ONE:
        x0p, x2p, Pp, Np, _ = planted_tuples(int(args.planted_tuples * 1.6) + 16, chain, seed=1)
        k = args.planted_tuples
        workloads = {"random": random_tuples(args.tuples, seed=2), "planted": (x0p[:k], x2p[:k], Pp[:k], Np[:k])}
        for name, (x0, x2, P, N) in workloads.items():
            if not wanted(args, chain, name):
                continue
            n = x0.shape[0]
            solver.solve(chain, x0[:64], x2[:64], P[:64], N[:64], 1.5)
            solver.solve(chain, x0[:64], x2[:64], P[:64], N[:64], 1.5, device=device)
            (t_numba, a), (t_ocl, b) = best_times(lambda: solver.solve(chain, x0, x2, P, N, 1.5),
                                                  lambda: solver.solve(chain, x0, x2, P, N, 1.5, device=device), args.repeats)
            wall, st, prof = profiled_run(index, lambda: solver.solve(chain, x0, x2, P, N, 1.5, device=device), chain)
            rows.append(dict(chain=chain, workload=name, tuples=n, paths=b.report.paths, numba=t_numba, opencl=t_ocl,
                             profiled=wall, stages=st, launches=prof.launches, syncs=prof.syncs, same=same_paths(a, b)))
            print(one_bounce_line(rows[-1]), flush=True)
        if wanted(args, chain, "random pairs"):
            rows.append(pair_row(solver, index, chain, args))
            print(one_bounce_line(rows[-1]), flush=True)
    return rows


def pair_row(solver, index, chain, args):
    """--tuples random (emitter, point) pairs over 65,536 random emitters and 65,536 random
    points kept on the device (``spoly.api.TupleTable``, as a bake sends them); the table's
    upload is made before the timing; Numba solves the gathered tuples (gathering not timed)."""
    from addon.solver.spoly.api import TupleTable

    x0, P, N, x2, e, s = random_pairs(args.tuples)
    table = TupleTable(chain, x0, P, N, 1.5, x2, device=f"opencl:{index}", solver=solver)
    table.solve(e[:64], s[:64])
    g0, g2, gP, gN = x0[e], x2[s], P[e], N[e]
    (t_numba, a), (t_ocl, b) = best_times(lambda: solver.solve(chain, g0, g2, gP, gN, 1.5), lambda: table.solve(e, s),
                                          args.repeats)
    wall, st, prof = profiled_run(index, lambda: table.solve(e, s), chain)
    return dict(chain=chain, workload="random pairs", tuples=e.size, paths=b.report.paths, numba=t_numba, opencl=t_ocl,
                profiled=wall, stages=st, launches=prof.launches, syncs=prof.syncs, same=same_paths(a, b))


def two_bounce_rows(solver, index, args):
    device = f"opencl:{index}"
    rows = []
    n2 = args.two_bounce_tuples
    for chain in TWO:
        if not any(wanted(args, chain, name) for name in ("random", "planted")):
            continue
        x0p, x3p, Pp, Np, _ = planted_two_bounce(2 * n2, chain, seed=1)
        workloads = {"random": random_two_bounce(n2, seed=2), "planted": (x0p[:n2], x3p[:n2], Pp[:n2], Np[:n2])}
        for name, (x0, x3, P, N) in workloads.items():
            if not wanted(args, chain, name):
                continue
            n = x0.shape[0]
            solver.solve(chain, x0[:4], x3[:4], P[:4], N[:4], 1.5)
            solver.solve(chain, x0[:4], x3[:4], P[:4], N[:4], 1.5, device=device)
            (t_numba, a), (t_ocl, b) = best_times(lambda: solver.solve(chain, x0, x3, P, N, 1.5),
                                                  lambda: solver.solve(chain, x0, x3, P, N, 1.5, device=device), args.repeats)
            wall, st, prof = profiled_run(index, lambda: solver.solve(chain, x0, x3, P, N, 1.5, device=device), chain)
            rows.append(dict(chain=chain, workload=name, tuples=n, paths=b.report.paths, numba=t_numba, opencl=t_ocl,
                             profiled=wall, stages=st, launches=prof.launches, syncs=prof.syncs, same=same_paths(a, b)))
            print(two_bounce_line(rows[-1]), flush=True)
    return rows


ONE_COLUMNS = (("validate", "check inputs"), ("pack", "pack"), ("host->device", "host→device"), ("zero", "zero acc"),
               ("kernel solve_one_bounce", "kernel, one stage"),
               ("kernel one_bounce filter", "filter kernel"), ("kernel one_bounce solve", "solve kernel"),
               ("kernel compaction", "prefix sums, scatter"), ("kernel gather", "gather kernel"), ("device->host", "device→host"), ("unpack", "unpack"),
               ("sort", "sort paths"))
TWO_DEVICE = (("kernel stage_a", "stage A kernel"), ("kernel gather_systems", "gather kernel"),
              ("kernel scan_samples", "scan samples kernel"), ("kernel scan_degenerate", "degenerate kernel"),
              ("kernel scan_pins", "Illinois pins kernel"), ("kernel scan_roots", "root lists kernel"),
              ("kernel candidates_scan", "candidates kernel (C)"), ("kernel refine_flags", "refine flags kernel"),
              ("kernel refine_samples", "refine sub-samples kernel"), ("kernel refine_assemble", "refine assembly kernel"),
              ("kernel candidates_refined", "candidates kernel (E)"))
TWO_COLUMNS = ((("validate", "check inputs"), ("A", "stage A on Numba (CPU devices)"), ("host->device", "host→device"))
               + TWO_DEVICE + (("device->host", "device→host"), ("host", "one-kernel tuples (Numba)"),
                               ("compact", "compact")))


def ms(seconds):
    return f"{seconds * 1e3:.1f}" if seconds < 10 else f"{seconds * 1e3:.0f}"


def one_bounce_line(r):
    st = r["stages"]
    listed = sum(st.get(k, 0.0) for k, _ in ONE_COLUMNS)
    n = r["tuples"]
    return (f"| {r['chain']} | {r['workload']} | {n:,} | {r['paths']:,} | "
            + " | ".join(ms(st.get(k, 0.0)) for k, _ in ONE_COLUMNS)
            + f" | {ms(r['profiled'] - listed)} | {ms(r['profiled'])} | {ms(r['opencl'])} ({r['opencl'] / n * 1e6:.3f} µs) | "
            f"{ms(r['numba'])} ({r['numba'] / n * 1e6:.3f} µs) | {r['opencl'] / r['numba']:.2f}× | "
            f"{r['launches']} / {r['syncs']} | {r['same']} |")


def two_bounce_line(r):
    st = r["stages"]
    glue = st.get("batch", 0.0) - sum(st.get(k, 0.0) for k in ("host", "device calls"))
    device = ("host->device", "device->host") + tuple(k for k, _ in TWO_DEVICE)
    calls_other = st.get("device calls", 0.0) - sum(st.get(k, 0.0) for k in device + ("A",))
    n = r["tuples"]
    return (f"| {r['chain']} | {r['workload']} | {n:,} | {r['paths']:,} | "
            + " | ".join(ms(st.get(k, 0.0)) for k, _ in TWO_COLUMNS)
            + f" | {ms(calls_other)} | {ms(glue)} | {ms(r['profiled'])} | {ms(r['opencl'])} ({r['opencl'] / n * 1e6:.0f} µs) | "
            f"{ms(r['numba'])} ({r['numba'] / n * 1e6:.0f} µs) | {r['opencl'] / r['numba']:.2f}× | "
            f"{r['launches']} / {r['syncs']} | {r['same']} |")


def one_bounce_header():
    return ["| chain | workload | tuples | paths | " + " | ".join(label + " (ms)" for _, label in ONE_COLUMNS)
            + " | other (ms) | profiled wall (ms) | OpenCL wall (ms) | Numba wall (ms) | OpenCL / Numba | launches / waits | same paths |",
            "|---" * (4 + len(ONE_COLUMNS) + 7) + "|"]


def two_bounce_header():
    return ["| chain | workload | tuples | paths | " + " | ".join(label + " (ms)" for _, label in TWO_COLUMNS)
            + " | device calls, rest (ms) | numpy glue (ms) | profiled wall (ms) | OpenCL wall (ms) | Numba wall (ms) "
              "| OpenCL / Numba | launches / waits | same paths |",
            "|---" * (4 + len(TWO_COLUMNS) + 8) + "|"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tuples", type=int, default=1_000_000, help="random R / T tuples per row")
    parser.add_argument("--planted-tuples", type=int, default=200_000, help="planted R / T tuples per row")
    parser.add_argument("--two-bounce-tuples", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", type=int, default=None, help="OpenCL device index (default: OPENCL_DEVICE or the first with fp64)")
    parser.add_argument("--chains", default="R,T,RR,RT,TR,TT", help="rows to run: chains, or chain:workload")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    args.rows = set(args.chains.split(","))

    from addon.solver.runtime import jit
    from addon.solver.opencl import backend as opencl_backend
    from addon.solver.spoly.api import SpecularPolynomialSolver

    devices = [d for d in opencl_backend.list_devices() if d[3]]
    if args.device is None:
        args.device = int(os.environ.get("OPENCL_DEVICE", devices[0][0] if devices else 0))
    index = args.device
    solver = SpecularPolynomialSolver()
    threads = jit.get_num_threads()
    print(f"device {index}: {opencl_backend.device_name(index)}", flush=True)
    one = one_bounce_rows(solver, index, args)
    two = two_bounce_rows(solver, index, args)
    info = opencl_backend.device_info(index)

    lines = [f"Device {index}: **{info['name']}** ({info['type']}, {info['compute_units']} compute units); "
             f"host {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
             f"Numba {threads} threads; the two back ends called in turn, the best of at least {args.repeats} calls and "
             f"{PAIR_SECONDS} s each; date {time.strftime('%Y-%m-%d')}.", ""]
    lines.append("Kernels: " + "; ".join(
        f"`{name}` work-group {k['local']} (kernel maximum {k['max_local']}, private memory "
        f"{'%s bytes' % format(k['private_bytes'], ',') if k['private_bytes'] is not None else 'not reported'} per work-item)"
        for name, k in info["kernels"].items()) + ".")
    lines.append("")
    if one:
        lines.append("One bounce: times in ms for the whole batch (device columns from OpenCL profiling events; "
                     "\"other\" = profiled wall minus the listed columns: Python, waits, and any overlap counted twice). "
                     "OpenCL and Numba walls are best-of runs without profiling; µs per tuple in brackets.")
        lines.append("")
        lines += one_bounce_header()
        lines += [one_bounce_line(r) for r in one]
        lines.append("")
    if two:
        lines.append("Two bounces (staged, `two_bounce/staged.py`: the systems (stage A: on Numba beside a CPU "
                     "device, on the device otherwise), the resultant scan, the candidates' polish and the refinement "
                     "on the device): times in ms for the batch. \"device calls, rest\" = host time inside "
                     "the device calls beyond their commands' device time (Python, waits); \"numpy glue\" = the "
                     "staging's array work between stages.")
        lines.append("")
        lines += two_bounce_header()
        lines += [two_bounce_line(r) for r in two]
        lines.append("")
    section = "\n".join(lines).rstrip("\n")
    print()
    print(section)
    if not args.no_write:
        kind = "gpu" if "GPU" in info["type"] else "cpu"
        with open(os.path.join(ROOT, "bench", "results", f"opencl_profile_{kind}.md"), "w") as fh:
            fh.write(f"# OpenCL back end, stage by stage (`bench/opencl_profile.py`)\n\n{section}\n")
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "opencl-profile",
                      "OpenCL back end, stage by stage (`bench/opencl_profile.py`)", profile_index())


def profile_index():
    """The BENCHMARKS.md section: where the stage-by-stage pages are, one line each."""
    lines = ["Where the time of an OpenCL solve goes (host checks, transfers, each kernel by profiling events, "
             "the two-bounce kernels stage by stage), next to Numba on the same tuples; one page per kind of "
             "device, each written by the last run on it:", ""]
    for kind, label in (("cpu", "CPU (PoCL)"), ("gpu", "GPU")):
        page = os.path.join(ROOT, "bench", "results", f"opencl_profile_{kind}.md")
        if os.path.exists(page):
            first = next((l for l in open(page) if l.startswith("Device ")), "").strip()
            lines.append(f"- [{label}](bench/results/opencl_profile_{kind}.md): {first}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
