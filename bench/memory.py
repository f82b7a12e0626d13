"""Memory: peak resident memory and time of a default bake of a large glass caster.

    .venv/bin/python bench/memory.py [--triangles 100000,300000,1000000] [--resolution 1024] [--no-write]

Each case is a generated closed glass sphere (``tests/fixtures/bake_scenes.glass_sphere_scene``:
a UV sphere of about ``--triangles`` triangles, IOR 1.5, over a 3.2 x 3.2 m floor under a
point light) baked with the default settings (``forward-flux``, the planner's chains) at
``--resolution``² in a child process of its own, so its peak resident set (``ru_maxrss``) is
the bake's alone: scene arrays, BVH, the plan, the forward images of one chunk of casters at a
time (``addon/bake/estimators/forward_flux.CASTER_CHUNK``) and the textures.  Reported: the
triangle count, the sub-triangles, the bake's seconds (``bake()``, the scene already built;
Numba's cache warm: one small bake first) and the child's peak RSS, with the memory budget the
bake ran under.  Prints a table and rewrites the "memory" section of BENCHMARKS.md.
"""

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE, os.path.join(ROOT, "tests")]


def sphere(segments, rings, radius=0.5, centre=(0.0, 0.0, 1.0)):
    """The triangles of ``tests/fixtures/bake_scenes.uv_sphere`` (a closed UV sphere, outward
    winding, radial corner normals; upper triangles first), built in numpy: a million of them
    without a Python loop."""
    import numpy as np

    th = np.pi * np.arange(rings + 1) / rings
    ph = 2 * np.pi * np.arange(segments) / segments
    n = np.stack([np.sin(th)[:, None] * np.cos(ph)[None, :], np.sin(th)[:, None] * np.sin(ph)[None, :],
                  np.broadcast_to(np.cos(th)[:, None], (rings + 1, segments))], axis=-1)  # (rings + 1, segments, 3)
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a, b, c, d = (i, j), (i + 1, j), (i + 1, (j + 1) % segments), (i, (j + 1) % segments)
    upper = np.stack([n[a], n[b], n[d]], axis=2)[1:].reshape(-1, 3, 3)  # no cap triangle at the pole
    lower = np.stack([n[d], n[b], n[c]], axis=2)[:-1].reshape(-1, 3, 3)
    N = np.concatenate([upper, lower])
    return np.asarray(centre, float) + radius * N, N


def child(triangles, resolution):
    """Bake the sphere of about ``triangles`` triangles; print a JSON line of what was measured."""
    from addon.bake.pipeline import BakeSettings, bake
    from addon.bake.scene import Light, build_scene
    from fixtures.bake_scenes import floor, glass_sphere_scene

    bake(glass_sphere_scene(resolution=16, segments=16, rings=8), BakeSettings(resolution=16))  # load the kernels
    rings = max(4, int(round(math.sqrt(triangles / 4.0))))
    P, N = sphere(2 * rings, rings)
    sc = build_scene([floor(half=1.6, resolution=resolution), dict(name="sphere", tri_p=P, tri_n=N, role="both", ior=1.5)],
                     [Light("Point", "point", (1.0, 1.0, 1.0), 80.0, position=(0.0, 0.0, 3.0))])
    n = int(P.shape[0])
    settings = BakeSettings(resolution=resolution)
    t0 = time.perf_counter()
    res = bake(sc, settings)
    seconds = time.perf_counter() - t0
    est = res.report.get("estimators", {}).get("forward-flux", {})
    print(json.dumps({"triangles": n, "seconds": seconds, "sub_triangles": est.get("sub_triangles"),
                      "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))


def run_case(triangles, resolution):
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(triangles), str(resolution)],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        return {"triangles": triangles, "error": (proc.stderr.strip().splitlines() or ["rc %d" % proc.returncode])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", default="100000,300000,1000000")
    ap.add_argument("--resolution", type=int, default=1024)
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch BENCHMARKS.md")
    ap.add_argument("--child", nargs=2, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    from addon.bake.memory import MEMORY_FRACTION, available_memory

    free = available_memory()
    rows = []
    for t in (int(x) for x in args.triangles.split(",")):
        r = run_case(t, args.resolution)
        rows.append(r)
        print(r, flush=True)
    head = "| glass sphere | texels | sub-triangles | seconds | peak RSS |\n|---|---|---|---|---|\n"
    lines = []
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['triangles']:,} triangles | {args.resolution}² | - | - | failed: {r['error']} |")
        else:
            lines.append(f"| {r['triangles']:,} triangles | {args.resolution}² | {r['sub_triangles'] or 0:,} | "
                         f"{r['seconds']:.1f} | {r['peak_rss'] / 1e9:.2f} GB |")
    budget = "" if free is None else f" (default budget {MEMORY_FRACTION:.0%} of the {free / 1e9:.1f} GB available)"
    body = (f"{os.cpu_count()} cores, {platform.machine()}, shared; {time.strftime('%Y-%m-%d')}. A default bake "
            f"(forward-flux, the planner's chains) of a generated glass sphere in a child process: seconds of `bake()` "
            f"(kernels cached), peak resident memory of the whole process{budget}.\n\n" + head + "\n".join(lines) + "\n")
    print(body)
    if not args.no_write:
        from bake import write_section

        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "memory", "Memory: peak RSS of a large glass caster (`bench/memory.py`)",
                      body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
