"""The bake issue's target: the glass sphere (TT) at 1024² against a photon reference.

    .venv/bin/python bench/glass_target.py [--resolution 1024] [--photons 50000000] [--modes flux,seeded]
                                           [--no-write]

Bakes sample_blends/glass_sphere.blend's TT chain (light -> into the sphere -> out -> floor,
Fresnel at both interfaces) with the two-bounce modes of the default method, and twice with
photon tracing (independent seeds) for the reference.  relMSE as rel_mse in
tests/fixtures/checks.py (mean over texels lit in either image of (a - b)² / (b² + eps), eps = 1e-2 x mean² of the
lit reference).  The reference is noisy: with two independent photon textures A, B of
per-texel relative variance s², relMSE(A, B) ~ 2 s², and the reference R = (A + B) / 2 adds
~ s² / 2 = relMSE(A, B) / 4 to any relMSE measured against it; the table prints the raw value
and the value less that noise.  Target (issue): relMSE <= 1e-3 in less time than Cycles'
shadow caustics need for 256 samples of one 256² view of the floor (128 s on this machine,
with 52 % of the caustic energy still missing).  Rewrites the "glass_target" section of
BENCHMARKS.md.
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

CYCLES_SECONDS = 128.0


def rel_mse(img, ref):
    lit = (ref > 0) | (img > 0)
    eps = 1e-2 * ref[lit].mean() ** 2
    return float(np.mean((img[lit] - ref[lit]) ** 2 / (ref[lit] ** 2 + eps)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=1024)
    ap.add_argument("--photons", type=int, default=50_000_000, help="photons per reference texture (two are traced)")
    ap.add_argument("--modes", default="flux", help="two-bounce modes to bake (flux, seeded)")
    ap.add_argument("--samples", type=int, default=4, help="supersamples per texel (seeded mode; flux uses them for coverage)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)

    from addon.bake.pipeline import BakeSettings, bake
    from addon.bake.extract import extract_scene, open_blend

    open_blend(os.path.join(ROOT, "sample_blends", "glass_sphere.blend"))
    scene = extract_scene(resolution=args.resolution)
    rec = scene.receivers[0].name
    base = dict(resolution=args.resolution, samples=args.samples, bounces=2, chains=("TT",), margin=0)
    rows = []
    for mode in args.modes.split(","):
        t0 = time.perf_counter()
        cold = bake(scene, BakeSettings(**base, two_bounce=mode))
        t1 = time.perf_counter()
        warm = bake(scene, BakeSettings(**base, two_bounce=mode))
        t2 = time.perf_counter()
        rows.append(dict(mode=mode, cold=t1 - t0, warm=t2 - t1, img=warm.raw[rec][:, :, 0], report=warm.report))
        print(f"{mode}: cold {t1 - t0:.1f} s, warm {t2 - t1:.1f} s", flush=True)
    refs = []
    for seed in (1, 2):
        t0 = time.perf_counter()
        r = bake(scene, BakeSettings(**base, method="photon", photons=args.photons, seed=seed))
        refs.append((time.perf_counter() - t0, r.raw[rec][:, :, 0]))
        print(f"photon reference seed {seed}: {refs[-1][0]:.1f} s", flush=True)
    ref = 0.5 * (refs[0][1] + refs[1][1])
    noise = rel_mse(refs[0][1], refs[1][1]) / 4.0
    lines = ["| estimator | seconds (warm) | seconds (cold) | relMSE vs reference | less the reference's noise | "
             "energy / reference | under target (1e-3 and < 128 s) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        e = rel_mse(r["img"], ref)
        ok = e - noise <= 1e-3 and r["warm"] < CYCLES_SECONDS
        lines.append(f"| spoly two_bounce={r['mode']} | {r['warm']:.1f} | {r['cold']:.1f} | {e:.2e} | {e - noise:.2e} | "
                     f"{r['img'].sum() / ref.sum():.4f} | {'yes' if ok else 'no'} |")
    for k, (sec, img) in enumerate(refs):
        e = rel_mse(img, refs[1 - k][1])
        lines.append(f"| photon {args.photons:,} (seed {k + 1}) | {sec:.1f} | — | {e:.2e} (vs the other seed) | "
                     f"{e / 2:.2e} (its own noise) | {img.sum() / refs[1 - k][1].sum():.4f} | — |")
    rep = rows[0]["report"] if rows else {}
    estimators = rep.get("estimators", {})
    img_rep = estimators.get("forward-flux") or estimators.get("path-seeded") or {}
    text = (f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
            f"{args.resolution}² texels, chain TT only, date {time.strftime('%Y-%m-%d')}; load average "
            f"{os.getloadavg()[0]:.1f} at the end.  Cold: the first bake in this process (it includes Numba "
            f"compiling any kernel not in the on-disk cache).  Reference: mean of the two photon textures (its noise "
            f"~{noise:.1e} relMSE, subtracted in the fifth column).\n\n" + "\n".join(lines) + "\n\n"
            f"Sub-triangles (first mode): {img_rep.get('passes', [{}])[0].get('sub_triangles', 0):,}, points traced "
            f"{img_rep.get('passes', [{}])[0].get('points_traced', 0):,}; timings of the warm bake (s): "
            + ", ".join(f"{k} {v:.2f}" for k, v in rep.get("timings", {}).items()) + ".\n")
    print(text)
    if not args.no_write:
        path = os.path.join(ROOT, "BENCHMARKS.md")
        md = open(path).read()
        begin, end = "<!-- glass_target:begin -->", "<!-- glass_target:end -->"
        section = f"{begin}\n## Bake target: glass sphere TT (`bench/glass_target.py`)\n\n{text}{end}"
        if begin in md:
            md = md[:md.index(begin)] + section + md[md.index(end) + len(end):]
        else:
            md = md.rstrip("\n") + "\n\n" + section + "\n"
        open(path, "w").write(md)


if __name__ == "__main__":
    main()
