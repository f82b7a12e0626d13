"""Animation: seconds per frame of the default estimator (``forward-flux``).

    .venv/bin/python bench/animation.py [--cases pool512,sheet512,sheet1024,ocean512,ocean512rough] [--frames 3]
                                        [--forms reference,fast] [--no-write]

Cases:

- ``pool512``: ``sample_blends/water_pool.blend`` (4.6k-triangle displaced water surface, a
  point light and a sun, chain T) at 512², frames 1, 2, ... (the waves move; each frame is
  extracted from Blender, extraction not counted);
- ``sheet512`` / ``sheet1024``: ``tests/fixtures/bake_scenes.wavy_sheet``, a generated 115,200-triangle water sheet
  (IOR 1.33, analytic normals) 1 m above a 4 x 4 m floor under a point light, at 512² / 1024²;
- ``ocean512`` / ``ocean512rough``: ``tests/fixtures/animated_scene.build_ocean_sheet``, a 240 x 240
  grid (115,200 triangles) displaced by Blender's Ocean modifier with its time keyframed, 1 m
  above a 4 x 4 m floor, point light, 512² (waves of about 5 cm, and rough: about 20 cm with
  full choppiness), built and extracted with the bpy module each frame.

Each case first bakes one frame that is not counted (Numba compile / cache load and first-touch
costs), then bakes ``--frames`` frames and reports the mean seconds per frame of ``bake()``
(the whole bake: BVH, plan, estimator, padding; ``extract``: the seconds to extract a frame
from Blender, not in s/frame), the sub-triangles per frame, µs per
sub-triangle (estimator seconds / sub-triangles) and the estimator's stages from the bake's
timer: ``image`` (refinement: tracing the corners and midpoints, the split decisions),
``image.trace`` (the part of it inside the tracing kernels: the point tracer, and the refine
and border kernels whole, which trace as they decide), ``flux.*`` (the flux of the final
sub-triangles: centroid trace, light visibility, corner densities, splat).
Forms: ``fast`` (the default estimator) and ``reference`` (``ForwardFlux.reference``: the
numpy form without coarse levels, every point traced per sub-triangle, texel areas and
supersample counts measured every frame, a receiver's edge cut by bisection (no flat-receiver
extension): the estimator as it was before the fast form), run in
the same process one after the other, so their ratio is measured under the same load; ``rel. diff`` is the relMSE of the fast textures
against the reference ones (last frame, all receivers; ``tests/fixtures/checks.rel_mse``: the
mean over lit texels of (fast - ref)² / (ref² + 1e-2 mean(ref)²)).
Prints a table and rewrites the "animation" section of BENCHMARKS.md.
"""

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE, os.path.join(ROOT, "tests")]

def sheet_frames(resolution):
    """A function frame -> the 115,200-triangle wavy sheet at that frame."""
    from fixtures.bake_scenes import wavy_sheet

    return lambda frame: wavy_sheet(frame, resolution)


def pool_frames(resolution):
    """A function frame -> the water_pool scene model at that frame (extracted from Blender)."""
    import bpy

    from addon.bake.extract import extract_scene, open_blend

    open_blend(os.path.join(ROOT, "sample_blends", "water_pool.blend"))

    def at(frame):
        bpy.context.scene.frame_set(frame)
        return extract_scene(resolution=resolution)
    return at


def ocean_frames(resolution, **waves):
    """A function frame -> the Ocean-modifier sheet's scene model at that frame (bpy)."""
    from fixtures.animated_scene import build_ocean_sheet

    from addon.bake.extract import extract_scene

    build_ocean_sheet(resolution, **waves)
    return lambda frame: extract_scene(resolution=resolution, frame=frame)


CASES = {
    "pool512": ("water_pool", 512, lambda: pool_frames(512)),
    "sheet512": ("wavy sheet 115k", 512, lambda: sheet_frames(512)),
    "sheet1024": ("wavy sheet 115k", 1024, lambda: sheet_frames(1024)),
    "ocean512": ("Ocean modifier 115k", 512, lambda: ocean_frames(512)),
    "ocean512rough": ("Ocean modifier 115k, rough", 512, lambda: ocean_frames(512, wave_scale=0.2, choppiness=1.0)),
}
STAGES = ("bvh", "plan", "image", "image.trace", "flux", "flux.trace", "flux.visibility", "flux.density", "flux.splat", "raster",
          "texel_area", "pad")
TABLE = ("image", "image.trace", "flux", "flux.trace", "flux.visibility", "flux.density", "flux.splat")  # + "other"


def run_case(key, frames, form, scene_at):
    from addon.bake.estimators.forward_flux import ForwardFlux
    from addon.bake.pipeline import BakeSettings, bake

    from addon.bake.estimators import forward_images

    name, res, _make = CASES[key]
    ForwardFlux.reference = form == "reference"
    forward_images.EXTEND_FLAT_RECEIVERS = form != "reference"
    settings = BakeSettings(resolution=res, estimator="forward-flux")
    try:
        return _run(key, name, res, frames, form, scene_at, settings, bake)
    finally:
        ForwardFlux.reference = False
        forward_images.EXTEND_FLAT_RECEIVERS = True


def _run(key, name, res, frames, form, scene_at, settings, bake):
    import numpy as np

    from addon.bake import pipeline

    bake(scene_at(1), settings)  # warm-up: compile / cache load, first touch
    total, subs, points, stages, extract = 0.0, 0, 0, {}, 0.0
    for f in range(2, 2 + frames):
        t0 = time.perf_counter()
        scene = scene_at(f)
        extract += time.perf_counter() - t0
        if form == "reference":  # as before: texel areas and supersample counts measured every frame
            pipeline._AREA_CACHE.clear()
            pipeline._COVER_CACHE.clear()
        t0 = time.perf_counter()
        r = bake(scene, settings)
        total += time.perf_counter() - t0
        est = next(iter(r.report["estimators"].values()), {})
        subs += est.get("sub_triangles", 0)
        points += sum(p["points_traced"] for p in est.get("passes", []))
        for k, v in r.report["timings"].items():
            stages[k] = stages.get(k, 0.0) + v
    est_s = stages.get("image", 0.0) + stages.get("flux", 0.0)
    image = np.concatenate([r.raw[k].ravel() for k in sorted(r.raw)])
    return dict(case=key, scene=name, res=res, form=form, spf=total / frames, extract=extract / frames, subs=subs / frames,
                points=points / frames,
                us=1e6 * est_s / max(subs, 1), stages={k: v / frames for k, v in stages.items()}, image=image)


def table(rows):
    import numba

    labels = dict(zip(TABLE, ("image", "trace", "flux", "centre", "vis.", "density", "splat")))
    lines = [f"{os.cpu_count()} cores, {numba.config.NUMBA_NUM_THREADS} Numba threads, shared (compare forms within a case); "
             f"{time.strftime('%Y-%m-%d')}. `bake()` s/frame after a warm-up frame. reference = forward-flux before (numpy "
             "terms, no coarse levels, each point traced per sub-triangle, texel areas / sample counts every frame, receiver "
             "edges bisected); fast = "
             "the default. µs/sub = (image + flux) / sub-triangles; rel. diff = relMSE fast vs reference. trace ⊂ image; "
             "centre, vis., density, splat ⊂ flux; other: BVH, plan, raster, texel areas, pad.", "",
             "| case | texels | form | s/frame | extract | sub-triangles | points traced | µs/sub | rel. diff | "
             + " | ".join(labels[k] for k in TABLE) + " | other |",
             "|---|---|---|---|---|---|---|---|---|" + "---|" * (len(TABLE) + 1)]
    for r in rows:
        diff = f"{r['rel']:.1e}" if "rel" in r else "-"
        lines.append(f"| {r['scene']} | {r['res']}² | {r['form']} | {r['spf']:.2f} | {r['extract']:.2f} | {r['subs']:,.0f} | {r['points']:,.0f} | {r['us']:.1f} | {diff} | "
                     + " | ".join(f"{r['stages'].get(k, 0.0):.2f}" for k in TABLE)
                     + f" | {r['spf'] - r['stages'].get('image', 0.0) - r['stages'].get('flux', 0.0):.2f} |")
    return "\n".join(lines)


def main(argv=None):
    from bake import write_section
    from fixtures.checks import rel_mse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--forms", default="reference,fast")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)
    rows = []
    for key in args.cases.split(","):
        scene_at = CASES[key][2]()
        ref = None
        for form in args.forms.split(","):
            t = time.perf_counter()
            r = run_case(key, args.frames, form, scene_at)
            if form == "reference":
                ref = r["image"]
            elif ref is not None:
                r["rel"] = rel_mse(r["image"], ref)
            rows.append(r)
            print(f"{key:10s} {form:9s} {r['spf']:7.2f} s/frame  {r['subs']:10,.0f} sub-triangles  {r['points']:10,.0f} points  "
                  f"{r['us']:6.1f} µs/sub  "
                  + "  ".join(f"{k} {r['stages'].get(k, 0.0):.2f}" for k in STAGES)
                  + (f"  relMSE {r['rel']:.2e}" if "rel" in r else "") + f"  ({time.perf_counter() - t:.0f} s)", flush=True)
    body = table(rows)
    print(body)
    if not args.no_write:
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "animation", "Animation: seconds per frame (`bench/animation.py`)", body)


if __name__ == "__main__":
    main()
