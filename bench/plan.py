"""The planner's cost and what it keeps: every sample scene baked with the defaults (bounces
auto) against bakes forced to one and to two bounces.

    .venv/bin/python bench/plan.py [--scenes mirror_plane,metal_ring] [--resolution 256] [--samples 4] [--no-write]

Each scene runs in a fresh interpreter (the Numba kernel cache on disk is warm); every bake is
run once to load its kernels, then timed again (warm).  Per scene: the chains each plan bakes,
the warm seconds of each bake and their ratios (auto / forced one bounce: the planner's price
where one bounce is all a scene needs; auto / forced two bounces: what it saves), the probe's
seconds and points, and the caustic energy each bake holds (sum over texels of irradiance x
texel area) relative to the forced two-bounce bake.  Prints a table and rewrites the "plan"
section of BENCHMARKS.md.
"""

import argparse
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
from bake import run_script, write_section  # noqa: E402
SCENES = ("mirror_plane", "metal_ring", "water_pool", "glass_sphere", "glass_slab")

ONE = """
import json, sys, time
sys.path.insert(0, {root!r})
from addon.bake.pipeline import BakeSettings, bake, texel_areas
from addon.bake.extract import extract_scene, open_blend
open_blend({blend!r})
scene = extract_scene(resolution={res})
areas = {{r.name: texel_areas(scene, r) for r in scene.receivers}}
out = {{}}
for key, bounces in (("one", 1), ("auto", "auto"), ("two", 2)):
    settings = BakeSettings(resolution={res}, samples={samples}, bounces=bounces)
    bake(scene, settings)  # load the kernels
    t0 = time.perf_counter()
    r = bake(scene, settings)
    sec = time.perf_counter() - t0
    energy = sum(float((r.raw[k].reshape(-1, 3).mean(axis=1) * areas[k]).sum()) for k in r.raw)
    out[key] = dict(seconds=sec, energy=energy, plan=r.report["plan"]["summary"], probe=r.report["plan"]["probe"],
                    chains=[c["chain"] for c in r.report["chains"] if c["status"] == "baked"],
                    sub_triangles=r.report["counts"].get("sub_triangles", 0))
print("RESULT" + json.dumps(out))
"""


def run_one(scene, res, samples):
    code = ONE.format(root=ROOT, blend=os.path.join(ROOT, "sample_blends", scene + ".blend"), res=res, samples=samples)
    return run_script(code, scene)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)
    rows = []
    for scene in args.scenes.split(","):
        t = time.perf_counter()
        r = run_one(scene, args.resolution, args.samples)
        rows.append((scene, r))
        print(f"{scene:13s} one {r['one']['seconds']:6.2f} s  auto {r['auto']['seconds']:6.2f} s  two {r['two']['seconds']:6.2f} s  "
              f"probe {r['auto']['probe']['seconds']:.3f} s  energy auto/two {r['auto']['energy'] / r['two']['energy']:.4f}  "
              f"{r['auto']['plan']}  ({time.perf_counter() - t:.0f} s)", flush=True)
    section = _table(rows, args.resolution, args.samples)
    print(section)
    if not args.no_write:
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "plan", "Planner: automatic bounces (`bench/plan.py`)", section)


def _table(rows, res, samples):
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    lines = ["Question: what does the default plan (bounces auto) bake, what does it cost next to a bake forced to one "
             "bounce, and how much of the two-bounce caustic does it keep?", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; commit {commit}, "
             f"{time.strftime('%Y-%m-%d')}; {res}² textures, {samples} supersamples per texel, forward-flux, warm runs.", "",
             "| scene | plan (auto): baked share per chain | forced 1 (s) | auto (s) | forced 2 (s) | auto / forced 1 | "
             "auto / forced 2 | probe (s) | probe points | energy auto / forced 2 | energy forced 1 / forced 2 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene, r in rows:
        one, auto, two = r["one"], r["auto"], r["two"]
        lines.append(f"| {scene} | {'; '.join(auto['plan'])} | {one['seconds']:.2f} | {auto['seconds']:.2f} | {two['seconds']:.2f} | "
                     f"{auto['seconds'] / one['seconds']:.2f} | {auto['seconds'] / two['seconds']:.2f} | "
                     f"{auto['probe']['seconds']:.3f} | {auto['probe']['points']:,} | {auto['energy'] / two['energy']:.4f} | "
                     f"{one['energy'] / two['energy']:.4f} |")
    lines += ["", "Target: auto / forced 1 <= 1.3 where one bounce is all a scene needs (mirror_plane, water_pool); energy "
              "auto / forced 2 >= 0.99 everywhere."]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
