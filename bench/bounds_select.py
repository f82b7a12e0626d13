"""Path-points tuple selection: the cone cull against the Bernstein bounds (addon/bake/bounds_select.py).

    .venv/bin/python bench/bounds_select.py [--scenes glass_sphere,glass_slab] [--resolution 128]
                                            [--samples 1] [--chains R,T,RR,RT,TR,TT] [--cone-solve 20000]

Per sample scene (sample_blends/*.blend, extracted with the bpy module) and chain, one light
sample per light, path-points estimator ("points" for R/T, two_bounce="exact" for RR..TT),
the spoly solver:

* bounds: a full bake of that chain with ``cull="bounds"``: (tuple, sample) pairs solved, paths,
  seconds in the cull (emitters, bounds, selection) and in the solver, the bake's total;
* cone: the cone cull's pairs over every band (counted, not solved) and its solve time; for
  one-bounce chains a full bake with ``cull="cone"`` (same paths), for two-bounce chains the
  cone's pairs of one band of rows through the texture's middle are solved on a random subset
  of ``--cone-solve`` pairs and the µs per pair times the total count is the estimate ("est.").

Prints a markdown table; ``--write`` also rewrites the "bounds-select" section of BENCHMARKS.md.
Each scene runs in its own interpreter.
"""

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = ("mirror_plane", "metal_ring", "water_pool", "glass_sphere", "glass_slab")

ONE = r"""
import json, sys, time
sys.path.insert(0, {root!r})
import numpy as np
from addon.bake.context import with_resolution
from addon.bake.estimators.path_points import chain_emitters
from addon.bake.pipeline import BakeSettings, bake, make_context
from addon.bake.plan import make_plan
from addon.bake.cull import TupleCull, _emit_count
from addon.bake.extract import extract_scene, open_blend
from addon.bake.lights import sample_light
from addon.bake.raster import bands, rasterise
from addon.solver import solve_tuples
open_blend({blend!r})
scene = extract_scene(resolution={res})
res, samples, seed = {res}, {samples}, 1
out = []
for chain in {chains!r}:
    k = len(chain)
    base = dict(resolution=res, samples=samples, seed=seed, bounces=k, chains=(chain,), margin=0, one_bounce="points",
                two_bounce="exact")
    plan = [it for it in make_plan(make_context(scene, BakeSettings(**base))).items if it.baked and it.light == 0]
    if not plan:
        continue
    row = dict(chain=chain, casters=[int(v.size) for v in plan[0].vertices],
               lights=[l.type for l in scene.lights])
    if k == 1:  # load the kernels first (one-bounce bakes take about a second)
        bake(scene, BakeSettings(**base, cull="bounds"))
    b = bake(scene, BakeSettings(**base, cull="bounds"))
    c, tm = b.report["counts"], b.report["timings"]
    print(chain, "bounds bake", c["tuples"], tm, file=sys.stderr, flush=True)
    row["bounds"] = dict(tuples=c["tuples"], paths=c["paths_visible"], cull=tm.get("cull", 0.0), solve=tm.get("solve", 0.0),
                         total=tm["bake_total"])
    # the cone cull's pairs, every light sample and band (counted only)
    st = BakeSettings(**base, cull="cone")
    receivers = [with_resolution(r, res) for r in scene.receivers]
    total, t_cull = 0, 0.0
    emitters = []
    for li, light in enumerate(scene.lights):
        ls = sample_light(light, 1, seed)
        t = time.perf_counter()
        em = chain_emitters(make_context(scene, st), plan[0], ls, 0)
        t_cull += time.perf_counter() - t
        emitters.append((ls, em))
        if em is None or em[0].size == 0:
            continue
        for rec in receivers:
            for j0, j1 in bands(rec, samples, st.band_samples):
                band = rasterise(scene, rec, samples, seed, True, rows=(j0, j1))
                if band.size == 0:
                    continue
                t = time.perf_counter()
                tc = TupleCull(em[0], band.position, band.geo_normal, band.texel, res)
                cnt = np.zeros(tc.pair_tri.shape[0], dtype=np.int64)
                if cnt.size:
                    _emit_count(tc.pair_tri, tc.pair_tile, tc.tile_start, tc.order, *tc.arrays, tc.pos, tc.rec_ng, cnt)
                total += int(cnt.sum())
                t_cull += time.perf_counter() - t
    row["cone"] = dict(tuples=total, cull=t_cull)
    if k == 1:
        cb = bake(scene, st)
        cc, ct = cb.report["counts"], cb.report["timings"]
        row["cone"].update(tuples=cc["tuples"], paths=cc["paths_visible"], cull=ct.get("cull", 0.0), solve=ct.get("solve", 0.0),
                           total=ct["bake_total"], estimated=False)
    else:  # solve a random subset of one band's cone pairs; extrapolate
        rng = np.random.default_rng(0)
        per, n_done = 0.0, 0
        for ls, em in emitters:
            if em is None or em[0].size == 0:
                continue
            rec = receivers[0]
            mid = rec.resolution[1] // 2
            band = rasterise(scene, rec, samples, seed, True, rows=(mid - 2, mid + 2))
            es, ss = [], []
            for bt in TupleCull(em[0], band.position, band.geo_normal, band.texel, res).batches(1 << 22):
                es.append(bt[0]); ss.append(bt[1])
            if not es:
                continue
            e, s = np.concatenate(es), np.concatenate(ss)
            pick = rng.choice(e.size, min({cone_solve}, e.size), replace=False)
            e, s = e[pick], s[pick]
            tri = em[1][e]
            t = time.perf_counter()
            solve_tuples(chain, em[2][e], band.position[s], scene.tri_p[tri], scene.tri_n[tri], scene.tri_ior[tri[:, 0]])
            per += time.perf_counter() - t
            n_done += e.size
        us = per / max(1, n_done)
        row["cone"].update(solve=us * total, total=row["cone"]["cull"] + us * total, estimated=True, solve_us=us * 1e6,
                           solved_sample=n_done)
    out.append(row)
    print("ROW" + json.dumps(row), flush=True)
"""


def run_scene(scene, res, samples, chains, cone_solve):
    code = ONE.format(root=ROOT, blend=os.path.join(ROOT, "sample_blends", scene + ".blend"), res=res, samples=samples,
                      chains=list(chains), cone_solve=cone_solve)
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=f"_bounds_select_{scene}.py", delete=False) as fh:
        fh.write(code)
    proc = subprocess.Popen([sys.executable, fh.name], stdout=subprocess.PIPE, text=True)  # progress on stderr
    rows = []
    for line in proc.stdout:
        if line.startswith("ROW"):
            rows.append(json.loads(line[3:]))
            yield rows[-1]
    proc.wait()
    os.unlink(fh.name)
    if proc.returncode != 0:
        raise RuntimeError(f"{scene}: exit status {proc.returncode} (see stderr)")


def fmt(row, scene, res):
    b, c = row["bounds"], row["cone"]
    est = " est." if c.get("estimated") else ""
    ratio = c["tuples"] / max(1, b["tuples"])
    speed = c["total"] / max(1e-9, b["total"])
    return (f"| {scene} | {row['chain']} | {'/'.join(row['lights'])} | {res}² | {c['tuples']:,} | {b['tuples']:,} | {ratio:,.1f}x | "
            f"{c['cull']:.1f} + {c['solve']:.1f}{est} | {b['cull']:.1f} + {b['solve']:.1f} | {c['total']:.1f}{est} | {b['total']:.1f} | "
            f"{speed:,.1f}x | {b['paths']:,}" + ("" if c.get("paths", b["paths"]) == b["paths"] else f" (cone {c['paths']:,})") + " |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--chains", default="R,T,RR,RT,TR,TT")
    ap.add_argument("--cone-solve", type=int, default=20000, help="cone pairs solved for the two-bounce estimate")
    ap.add_argument("--write", action="store_true", help="rewrite the bounds-select section of BENCHMARKS.md")
    args = ap.parse_args(argv)
    head = ["| scene | chain | lights | texels | cone pairs | bounds pairs | fewer | cone cull + solve (s) | bounds cull + solve (s) "
            "| cone total (s) | bounds total (s) | faster | paths |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines = []
    print("\n".join(head), flush=True)
    for scene in args.scenes.split(","):
        t = time.perf_counter()
        for row in run_scene(scene, args.resolution, args.samples, args.chains.split(","), args.cone_solve):
            lines.append(fmt(row, scene, args.resolution))
            print(lines[-1], flush=True)
        print(f"<!-- {scene}: {time.perf_counter() - t:.0f} s -->", flush=True)
    print("\n" + "\n".join(head + lines))
    if args.write:
        import platform

        import numba

        sys.path.insert(0, HERE)
        from bake import write_section

        intro = [f"Machine: {platform.machine()}, {os.cpu_count()} cores ({numba.config.NUMBA_NUM_THREADS} Numba threads); "
                 f"{args.samples} supersample(s) per texel, one light sample per light, estimator path-points, solver spoly; "
                 f"date {time.strftime('%Y-%m-%d')}.",
                 "Pairs: (tuple, texel sample) pairs handed to the solver. *cone*: the cone cull of `addon/bake/cull.py`; "
                 "*bounds*: the Bernstein position bounds of `addon/bake/bounds_select.py` (the default, `cull=\"bounds\"`). "
                 "One-bounce rows are two full bakes; two-bounce cone rows marked *est.* solve a random subset of the cone's "
                 "pairs of one band and scale its time per pair to all pairs. Same paths: the bounds are conservative.", ""]
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "bounds-select",
                      "Path-points pair selection: cone cull against Bernstein bounds (`bench/bounds_select.py`)",
                      "\n".join(intro + head + lines))


if __name__ == "__main__":
    main()
