"""Record the results a refactoring must not change, and compare two records bit for bit.

    .venv/bin/python bench/fingerprint.py record OUT.npz [--no-scenes] [--resolution 64]
    .venv/bin/python bench/fingerprint.py compare BEFORE.npz AFTER.npz

*record* stores, in one ``.npz``:

* the 24 result arrays of the solver benchmark workloads (``bench/workloads.py``): per chain
  R, T, RR, RT, TR, TT and workload random / planted, the solver's ``tuple_index`` and ``uv``
  (the Specular Polynomial solver of ``addon.solver.spoly.api``, IOR 1.5; one-bounce sets of
  20,000 tuples, two-bounce sets of 60);
* with the bpy module, the default bake (forward-flux, bounces auto, 4 supersamples) of every
  sample scene in ``sample_blends/`` at ``--resolution``: each receiver's raw texture.

*compare* prints one line per array and exits 1 when any array differs (shape, dtype or one
bit), or when one record has an array the other lacks.
"""

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

ONE_BOUNCE_TUPLES = 20_000
TWO_BOUNCE_TUPLES = 60
SCENES = ("mirror_plane", "metal_ring", "water_pool", "glass_sphere", "glass_slab")


def solver_arrays():
    """{"<chain>/<workload>/tuple_index" | ".../uv": array} for the 24 workload results."""
    from workloads import planted_tuples, planted_two_bounce, random_tuples, random_two_bounce

    from addon.solver.spoly.api import SpecularPolynomialSolver

    solver = SpecularPolynomialSolver()
    out = {}
    for chain in ("R", "T", "RR", "RT", "TR", "TT"):
        n = ONE_BOUNCE_TUPLES if len(chain) == 1 else TWO_BOUNCE_TUPLES
        if len(chain) == 1:
            planted = planted_tuples(int(n * 1.6), chain, seed=1)[:4]
            random = random_tuples(n, seed=2)
        else:
            planted = planted_two_bounce(n * 2, chain, seed=1)[:4]
            random = random_two_bounce(n, seed=2)
        for name, (x0, x2, P, N) in (("random", random), ("planted", planted)):
            res = solver.solve(chain, x0[:n], x2[:n], P[:n], N[:n], 1.5)
            out[f"{chain}/{name}/tuple_index"] = np.asarray(res.tuple_index)
            out[f"{chain}/{name}/uv"] = np.asarray(res.uv)
            print(f"{chain:2s} {name:7s}: {np.asarray(res.tuple_index).size:,} paths", flush=True)
    return out


def scene_arrays(resolution):
    """{"scene/<name>/<receiver>": raw texture} of the default bake of every sample scene."""
    from addon.bake.extract import extract_scene, open_blend
    from addon.bake.pipeline import BakeSettings, bake

    out = {}
    for name in SCENES:
        open_blend(os.path.join(ROOT, "sample_blends", name + ".blend"))
        result = bake(extract_scene(resolution=resolution), BakeSettings(resolution=resolution, samples=4))
        for rec, tex in result.raw.items():
            out[f"scene/{name}/{rec}"] = np.asarray(tex)
        print(f"{name}: {', '.join(result.raw)}", flush=True)
    return out


def compare(a_path, b_path):
    a, b = np.load(a_path), np.load(b_path)
    bad = 0
    for key in sorted(set(a.files) | set(b.files)):
        if key not in a.files or key not in b.files:
            print(f"MISSING  {key} ({'after' if key in a.files else 'before'} lacks it)")
            bad += 1
            continue
        x, y = a[key], b[key]
        same = x.shape == y.shape and x.dtype == y.dtype and np.array_equal(x.view(np.uint8), y.view(np.uint8))
        print(f"{'same    ' if same else 'DIFFERS '} {key} {x.shape}")
        bad += not same
    print(f"{len(set(a.files) | set(b.files)) - bad} identical, {bad} different")
    return 1 if bad else 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("out")
    rec.add_argument("--no-scenes", action="store_true", help="only the solver workloads (no bpy needed)")
    rec.add_argument("--resolution", type=int, default=64)
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("before")
    cmp_.add_argument("after")
    args = ap.parse_args(argv)
    if args.cmd == "compare":
        return compare(args.before, args.after)
    arrays = solver_arrays()
    if not args.no_scenes:
        arrays.update(scene_arrays(args.resolution))
    np.savez(args.out, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    print(f"wrote {len(arrays)} arrays to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
