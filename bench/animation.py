"""Animation: seconds per frame of the default estimator (``forward-flux``).

    .venv/bin/python bench/animation.py [--cases pool512,sheet512,sheet1024] [--frames 3] [--no-write]

Cases:

- ``pool512``: ``sample_blends/water_pool.blend`` (4.6k-triangle displaced water surface, a
  point light and a sun, chain T) at 512², frames 1, 2, ... (the waves move; each frame is
  extracted from Blender, extraction not counted);
- ``sheet512`` / ``sheet1024``: :func:`wavy_sheet`, a generated 115,200-triangle water sheet
  (IOR 1.33, analytic normals) 1 m above a 4 x 4 m floor under a point light, at 512² / 1024².

Each case first bakes one frame that is not counted (Numba compile / cache load and first-touch
costs), then bakes ``--frames`` frames and reports the mean seconds per frame of ``bake()``
(the whole bake: BVH, plan, estimator, padding), the sub-triangles per frame, µs per
sub-triangle (estimator seconds / sub-triangles) and the estimator's stages from the bake's
timer: ``image`` (refinement: tracing the corners and midpoints, the split decisions),
``image.trace`` (the part of it inside the tracing kernel), ``flux.*`` (the flux of the final
sub-triangles: centroid trace, light visibility, corner densities, splat).
Prints a table and rewrites the "animation" section of BENCHMARKS.md.
"""

import argparse
import math
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE]

SHEET_WAVES = (  # (amplitude m, wavelength m, direction rad, phase rad): deep-water waves
    (0.012, 0.9, 0.3, 0.0),
    (0.008, 0.55, 1.9, 1.0),
    (0.006, 0.37, -0.8, 2.0),
    (0.004, 0.23, 2.6, 0.5),
)


def wavy_sheet(frame=1, resolution=512, n=240, size=4.0, height=1.0, fps=24.0):
    """A deterministic animated water sheet: an n x n grid of quads (2 n² triangles; 240:
    115,200) of side ``size`` at ``height`` over a floor receiver (z = 0, same size, UV the
    unit square, ``resolution``²), displaced by the sum of the deep-water waves
    ``SHEET_WAVES`` at time frame / fps (ω² = g k), corner normals the analytic surface
    normals; water IOR 1.33 (normals up, away from the water), a 150 W point light above."""
    from addon.bake.scene import Light, build_scene

    t = frame / fps
    s = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(s, s, indexing="ij")
    Z = np.full_like(X, height)
    dzx = np.zeros_like(X)
    dzy = np.zeros_like(X)
    for a, lam, ang, ph in SHEET_WAVES:
        k = 2 * math.pi / lam
        w = math.sqrt(9.81 * k)
        kx, ky = k * math.cos(ang), k * math.sin(ang)
        arg = kx * X + ky * Y - w * t + ph
        Z += a * np.sin(arg)
        dzx += a * kx * np.cos(arg)
        dzy += a * ky * np.cos(arg)
    V = np.stack([X, Y, Z], axis=-1)
    N = np.stack([-dzx, -dzy, np.ones_like(X)], axis=-1)
    N /= np.linalg.norm(N, axis=-1, keepdims=True)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()  # quad corners (i, j), (i+1, j), (i+1, j+1), (i, j+1) as flat vertex ids
    q = (a, a + n + 1, a + n + 2, a + 1)
    idx = np.concatenate([np.stack([q[0], q[1], q[2]], axis=1), np.stack([q[0], q[2], q[3]], axis=1)])  # (2n², 3)
    P = V.reshape(-1, 3)[idx]
    Nn = N.reshape(-1, 3)[idx]
    h = size / 2
    floor_p = np.array([[[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0]], [[-h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]])
    floor = dict(name="Floor", tri_p=floor_p, uv=(floor_p[:, :, :2] + h) / size, receiver=True,
                 resolution=(resolution, resolution))
    water = dict(name="Water", tri_p=P, tri_n=Nn, role="refract", ior=1.33)
    light = Light("Point", "point", (1.0, 1.0, 1.0), 150.0 / (4 * math.pi), position=(0.3, -0.2, 3.0))
    return build_scene([floor, water], [light], frame=frame)


def pool_frames(resolution):
    """A function frame -> the water_pool scene model at that frame (extracted from Blender)."""
    import bpy

    from addon.bake.extract import extract_scene, open_blend

    open_blend(os.path.join(ROOT, "sample_blends", "water_pool.blend"))

    def at(frame):
        bpy.context.scene.frame_set(frame)
        return extract_scene(resolution=resolution)
    return at


CASES = {
    "pool512": ("water_pool", 512, lambda: pool_frames(512)),
    "sheet512": ("wavy sheet 115k", 512, lambda: (lambda f: wavy_sheet(f, 512))),
    "sheet1024": ("wavy sheet 115k", 1024, lambda: (lambda f: wavy_sheet(f, 1024))),
}
STAGES = ("bvh", "plan", "image", "image.trace", "flux", "flux.trace", "flux.visibility", "flux.density", "flux.splat", "raster",
          "texel_area", "pad")


def run_case(key, frames, estimator="forward-flux"):
    from addon.bake.pipeline import BakeSettings, bake

    name, res, make = CASES[key]
    scene_at = make()
    settings = BakeSettings(resolution=res, estimator=estimator)
    bake(scene_at(1), settings)  # warm-up: compile / cache load, first touch
    total, subs, stages = 0.0, 0, {}
    for f in range(2, 2 + frames):
        scene = scene_at(f)
        t0 = time.perf_counter()
        r = bake(scene, settings)
        total += time.perf_counter() - t0
        est = next(iter(r.report["estimators"].values()), {})
        subs += est.get("sub_triangles", 0)
        for k, v in r.report["timings"].items():
            stages[k] = stages.get(k, 0.0) + v
    est_s = stages.get("image", 0.0) + stages.get("flux", 0.0)
    return dict(case=key, scene=name, res=res, spf=total / frames, subs=subs / frames,
                us=1e6 * est_s / max(subs, 1), stages={k: v / frames for k, v in stages.items()})


def table(rows):
    import numba

    lines = [f"Machine: {platform.machine()}, {os.cpu_count()} cores ({numba.config.NUMBA_NUM_THREADS} Numba threads), "
             f"Python {platform.python_version()}; date {time.strftime('%Y-%m-%d')}. Seconds per frame of `bake()` "
             "(estimator `forward-flux`; warm: one frame baked first), mean over the frames; µs/sub = (image + flux) "
             "seconds per final sub-triangle. Stages in s per frame (image.trace ⊂ image; flux.* ⊂ flux).", "",
             "| case | texels | s/frame | sub-triangles | µs/sub | " + " | ".join(STAGES) + " |",
             "|---|---|---|---|---|" + "---|" * len(STAGES)]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['res']}² | {r['spf']:.2f} | {r['subs']:,.0f} | {r['us']:.1f} | "
                     + " | ".join(f"{r['stages'].get(k, 0.0):.2f}" for k in STAGES) + " |")
    return "\n".join(lines)


def main(argv=None):
    from bake import write_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)
    rows = []
    for key in args.cases.split(","):
        t = time.perf_counter()
        rows.append(run_case(key, args.frames))
        r = rows[-1]
        print(f"{key:10s} {r['spf']:7.2f} s/frame  {r['subs']:10,.0f} sub-triangles  {r['us']:6.1f} µs/sub  "
              + "  ".join(f"{k} {r['stages'].get(k, 0.0):.2f}" for k in STAGES) + f"  ({time.perf_counter() - t:.0f} s)",
              flush=True)
    body = table(rows)
    print(body)
    if not args.no_write:
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "animation", "Animation: seconds per frame (`bench/animation.py`)", body)


if __name__ == "__main__":
    main()
