"""Bake benchmark: every sample scene at 512² and 1024², cold and warm.

    .venv/bin/python bench/bake.py [--scenes mirror_plane,metal_ring] [--resolutions 512,1024]
                                   [--samples 4] [--no-write]

Each (scene, resolution) runs in a fresh interpreter (the Numba kernel cache on disk is warm,
as for a user's second session): *cold* is the first ``bake()`` call there (loading the kernels
included), *warm* the same bake repeated in that process.  texels/s = covered texels / warm
seconds.  Prints a table and rewrites the "bake" section of BENCHMARKS.md.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = ("mirror_plane", "metal_ring", "water_pool", "glass_sphere", "glass_slab")

ONE = """
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, {root!r})
from addon.bake.pipeline import BakeSettings, bake
from addon.bake.extract import extract_scene, open_blend
open_blend({blend!r})
t1 = time.perf_counter()
scene = extract_scene(resolution={res})
t2 = time.perf_counter()
settings = BakeSettings(resolution={res}, samples={samples}, bounces={bounces!r})
from addon.bake.estimate import estimate_bake
estimate = estimate_bake(scene, settings).seconds
t2 = time.perf_counter()
cold = bake(scene, settings)
t3 = time.perf_counter()
warm = bake(scene, settings)
t4 = time.perf_counter()
print("RESULT" + json.dumps(dict(start=t1 - t0, extract=t2 - t1, cold=t3 - t2, warm=t4 - t3, estimate=estimate,
                                report=warm.report)))
"""


def run_one(scene, res, samples, bounces):
    code = ONE.format(root=ROOT, blend=os.path.join(ROOT, "sample_blends", scene + ".blend"), res=res, samples=samples, bounces=bounces)
    return run_script(code, f"{scene} {res}")


def run_script(code, what):
    """Run ``code`` in a fresh interpreter; returns the JSON it printed after "RESULT"."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")), None)
    if out.returncode != 0 or line is None:
        raise RuntimeError(f"{what}: {out.stderr.strip().splitlines()[-1] if out.stderr.strip() else 'no result'}")
    return json.loads(line[len("RESULT"):])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--resolutions", default="512,1024")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--bounces", default="auto", choices=("auto", "1", "2"),
                    help="auto (default: the planner's chains), or force 1 or 2")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch BENCHMARKS.md")
    args = ap.parse_args(argv)
    args.bounces = args.bounces if args.bounces == "auto" else int(args.bounces)
    rows = []
    for scene in args.scenes.split(","):
        for res in (int(r) for r in args.resolutions.split(",")):
            t = time.perf_counter()
            r = run_one(scene, res, args.samples, args.bounces)
            rep = r["report"]
            c = rep["counts"]
            chains = ", ".join(f"{ch['chain']}" + ("" if ch["status"] == "baked" else " (skipped)") for ch in rep["chains"]) or "-"
            passes = [p for e in rep.get("estimators", {}).values() for p in e.get("passes", [])]
            reach = [p["reach"] for p in passes if "reach" in p]
            row = dict(scene=scene, res=res, chains=chains, cold=r["cold"], warm=r["warm"], extract=r["extract"],
                       estimate=r["estimate"],
                       texels_per_s=c["texels_covered"] / r["warm"], tuples=c["tuples"], naive=c["tuples_naive"],
                       paths=c["paths_visible"], lit=c["texels_touched"], stages=rep["timings"], estimator=rep["estimator"],
                       summary=" / ".join(rep["plan"]["summary"]) if isinstance(rep["plan"]["summary"], list) else rep["plan"]["summary"],
                       sub_triangles=sum(p["sub_triangles"] for p in passes),
                       casters=(sum(x["reaching"] for x in reach), sum(x["lit"] for x in reach)),
                       reach_s=sum(x["seconds"] for x in reach))
            rows.append(row)
            print(f"{scene:13s} {res:5d}²  cold {r['cold']:7.2f} s  warm {r['warm']:7.2f} s  {row['texels_per_s']:10,.0f} texels/s  "
                  f"{c['tuples']:>12,} tuples ({c['tuples_naive']:,} uncull'd)  {c['paths_visible']:>10,} paths  [{chains}]"
                  f"  ({time.perf_counter() - t:.0f} s)", flush=True)
    section = _table(rows, args.samples, args.bounces)
    print(section)
    if not args.no_write:
        from solver import write_section  # bench/solver.py's, shared by the bench scripts

        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "bake", "Bake: sample scenes (`bench/bake.py`)", section)


def _table(rows, samples, bounces):
    import numba

    lines = [f"Machine: {platform.machine()}, {os.cpu_count()} cores ({numba.config.NUMBA_NUM_THREADS} Numba threads), "
             f"Python {platform.python_version()}; {samples} supersamples per texel, one light sample; "
             f"bounces = {bounces}; date {time.strftime('%Y-%m-%d')}.",
             "Cold: the first bake in a fresh interpreter (Numba cache on disk warm); warm: the same bake again. "
             "Casters traced: first-vertex caster triangles whose scattered light can reach the chain's next targets, of those "
             "the light reaches (summed over chains; the rest are skipped by the cone test of `cull.first_casters_reaching`, "
             "which costs the seconds given). Estimate: the up-front lower bound the CLI and the operator show before a "
             "bake (`addon/bake/estimate.py`; two-bounce chains left out), for a first (cold) bake: the warm one keeps "
             "the receiver's coverage and texel areas.", "",
             "| scene | estimator | plan | texels | estimate (s) | cold (s) | warm (s) | texels/s (warm) | sub-triangles | "
             "casters traced | reach test (s) | paths | texels lit |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        traced, lit = r["casters"]
        lines.append(f"| {r['scene']} | {r['estimator']} | {r['summary']} | {r['res']}² | {r['estimate']:.2f} | {r['cold']:.2f} | "
                     f"{r['warm']:.2f} | "
                     f"{r['texels_per_s']:,.0f} | {r['sub_triangles']:,} | {traced:,} / {lit:,} | {r['reach_s']:.2f} | "
                     f"{r['paths']:,} | {r['lit']:,} |")
    keys = sorted({k for r in rows for k in r["stages"]})
    lines += ["", "Warm time per stage (s):", "", "| scene | texels | " + " | ".join(keys) + " |",
              "|---|---|" + "---|" * len(keys)]
    for r in rows:
        s = r["stages"]
        lines.append(f"| {r['scene']} | {r['res']}² | " + " | ".join(f"{s.get(k, 0.0):.2f}" for k in keys) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
