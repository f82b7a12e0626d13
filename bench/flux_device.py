"""Forward-flux bakes on Numba and on an OpenCL device, side by side.

    OCL_ICD_VENDORS=... python bench/flux_device.py [--resolutions 512,1024] [--frames 2] [--device N] [--no-write]

The scene: ``tests/fixtures/bake_scenes.wavy_sheet``, the 115,200-triangle water sheet under a
point light (bench/animation.py's sheet cases; no Blender needed).  Per resolution: one
warm-up bake per back end (Numba compile or cache load, OpenCL program builds), then --frames
frames each, Numba (all threads) and ``device="opencl:N"`` alternating in the same process;
reported: seconds per frame of ``bake()``, the seconds of the stages the device takes over
(``image.trace``: the landed refinement and the tracing; ``flux.splat``: the splat and, on the
device, the textures' read-back: enqueued work is waited for in the next blocking call, so
the device's stage times are approximate) and whether the textures are identical (every
device kernel is its Numba kernel step for step).  Writes the "flux-device" section of
BENCHMARKS.md, one block per kind of device (CPU / GPU), unless --no-write.
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE, os.path.join(ROOT, "tests")]


def bake_frame(scene, res, device):
    from addon.bake.pipeline import BakeSettings, bake

    t0 = time.perf_counter()
    out = bake(scene, BakeSettings(resolution=res, estimator="forward-flux", device=device))
    wall = time.perf_counter() - t0
    timings = out.report["timings"]
    return wall, timings.get("image.trace", 0.0), timings.get("flux.splat", 0.0), out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", default="512,1024")
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--device", type=int, default=None)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()

    from addon.solver.opencl import backend
    from addon.solver.runtime import jit
    from fixtures.bake_scenes import wavy_sheet
    from solver import write_block, write_section

    devices = [d for d in backend.list_devices() if d[3]]
    index = args.device if args.device is not None else int(os.environ.get("OPENCL_DEVICE", devices[0][0]))
    d = backend._context(index)
    device = f"opencl:{index}"
    threads = jit.get_num_threads()
    rows = []
    for res in (int(r) for r in args.resolutions.split(",")):
        bake_frame(wavy_sheet(0, res), res, "numba")
        bake_frame(wavy_sheet(0, res), res, device)
        acc = {"numba": [], device: []}
        same = True
        for f in range(1, args.frames + 1):
            scene = wavy_sheet(f, res)
            a = bake_frame(scene, res, "numba")
            b = bake_frame(scene, res, device)
            acc["numba"].append(a[:3])
            acc[device].append(b[:3])
            same &= all(np.array_equal(a[3].images[k], b[3].images[k]) for k in a[3].images)
        row = dict(res=res, same="yes" if same else "NO")
        for key, vals in acc.items():
            row[key] = tuple(float(np.mean([v[k] for v in vals])) for k in range(3))
        row["profile"] = profiled_frame(index, wavy_sheet(args.frames + 1, res), res, device)
        rows.append(row)
        print(line(row, device), flush=True)
    kind = "cpu" if d.is_cpu else "gpu"
    lines = [f"Device {index}: **{d.label}** ({'CPU' if d.is_cpu else 'GPU/accelerator'}, {d.dev.max_compute_units} compute "
             f"units); host {platform.machine()}, {os.cpu_count()} cores, Numba {threads} threads, Python "
             f"{platform.python_version()}; mean of {args.frames} frames after a warm-up bake each; date {time.strftime('%Y-%m-%d')}.",
             "", "Kernels: " + kernel_line(index), "", "| scene | texels | Numba s/frame | OpenCL s/frame | frame Numba / OpenCL | refine + trace Numba / OpenCL (s) "
             "| splat Numba / OpenCL (s) | same texture |", "|---|---|---|---|---|---|---|---|"]
    lines += [line(r, device) for r in rows]
    lines += [""] + [f"OpenCL device time of one more frame at {r['res']}², by command (profiling events): {r['profile']}."
                     for r in rows]
    print("\n".join(lines))
    if not args.no_write:
        path = os.path.join(ROOT, "BENCHMARKS.md")
        text = open(path).read()
        blocks = {}
        for k in ("cpu", "gpu"):  # the other kind's block stays as its last run wrote it
            b, e = f"<!-- flux-device-{k}:begin -->", f"<!-- flux-device-{k}:end -->"
            blocks[k] = text[text.index(b) + len(b):text.index(e)].strip("\n") if b in text and e in text else ""
        blocks[kind] = "\n".join(lines)
        write_section(path, "flux-device", "Forward-flux on an OpenCL device (`bench/flux_device.py`)", ABOUT + "".join(
            f"\n\n<!-- flux-device-{k}:begin -->\n{blocks[k] or NOT_MEASURED}\n<!-- flux-device-{k}:end -->" for k in ("cpu", "gpu")))


ABOUT = ("The 115,200-triangle wavy sheet (`tests/fixtures/bake_scenes.wavy_sheet`) under a point light, the default "
         "bake with `device=\"numba\"` and `device=\"opencl:N\"`: on the device the landed refinement with its tracing "
         "(`addon/solver/opencl/refine.cl`, `trace.cl`) and the splat into textures kept there for the pass (`splat.cl`); "
         "the per-sub-triangle flux terms, the border cuts and the rest of the bake on Numba in both. The device's "
         "stage times are approximate (its work is waited for in the next blocking call). Target on an H100/H200: "
         "1024² in at most 0.5 s a frame. One block per kind of device, each written by its last run.")
NOT_MEASURED = "Not measured with this code yet: run `bench/gpu_flux.sh` on a lent GPU machine."


def profiled_frame(index, scene, res, device):
    """One OpenCL bake with profiling events: its device seconds by command, launches and waits."""
    from addon.solver.opencl import backend

    profiler = backend.Profiler()
    backend.set_profiling(index, profiler)
    try:
        wall = bake_frame(scene, res, device)[0]
    finally:
        backend.set_profiling(index, None)
    spent = sorted(profiler.device_seconds().items(), key=lambda kv: -kv[1])
    busy = sum(sec for _, sec in spent)
    return (", ".join(f"{stage} {sec:.3f} s" for stage, sec in spent) +
            f"; {profiler.launches} launches, {profiler.syncs} waits, frame {wall:.2f} s with profiling, of which the "
            f"device was idle {wall - busy:.2f} s (the host's share: what a frame would take with an instant device)")


def kernel_line(index):
    """The forward-flux kernels' launch sizes and private memory on device index."""
    from addon.solver.opencl import splatting, tracing

    d, trace = tracing._kernel(index)
    _, splat = splatting._kernel(index)
    refine = tracing._refine_kernel(index, 32)  # the default bake's stack: 1 + 3 (6 + 2 + 1) + 4
    parts = []
    for name, k, local in (("refine_emitters", refine, d.small_work_group(refine)), ("trace_chain_points", trace, d.work_group(trace)),
                           ("splat_bands", splat, d.small_work_group(splat))):
        limit, private = d.kernel_info(k)
        parts.append(f"`{name}` work-group {local} (kernel maximum {limit}, private memory "
                     f"{format(private, ',') + ' bytes' if private is not None else 'not reported'} per work-item)")
    return "; ".join(parts) + "."


def line(r, device):
    n, o = r["numba"], r[device]
    return (f"| wavy sheet 115k | {r['res']}² | {n[0]:.2f} | {o[0]:.2f} | {n[0] / o[0]:.2f}× | {n[1]:.2f} / {o[1]:.2f} | "
            f"{n[2]:.2f} / {o[2]:.2f} | {r['same']} |")


if __name__ == "__main__":
    main()
