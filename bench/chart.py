"""Speed against accuracy: every estimator (and path-points solver) on every sample scene,
error against time.

    .venv/bin/python bench/chart.py [--quick] [--scenes metal_ring,water_pool] [--limit 60] [--no-write]

Each sample scene (sample_blends/*.blend, read with addon/bake/extract.py) is baked with each
estimator over a sweep of its speed knob (the names as ``--estimator`` / ``--solver`` take them):

- path-points/spoly, path-points/newton, path-points/curve: supersamples per texel (the tuple
  loop's cost is linear in them); the one-bounce chains' exact paths at every supersample, the
  two-bounce chains by forward-flux (the samples only set coverage);
- forward-flux: the default estimator for every chain, knob = the sub-triangles' deepest
  subdivision level (image_depth, default 6);
- path-points/sms: random Newton seeds per tuple (at 4 supersamples);
- photon: photons traced;
- cycles: Cycles' own shadow caustics (MNEE) baked by bpy (bench/cycles_bake.py: two Cycles
  bakes per knob, casters on and off, the difference x pi in W/m²; x IOR² under an open water
  surface), knob = Cycles samples.  MNEE refracts only: it renders the T / TT chains, the
  reflection scenes get a row saying so and no numbers.  Its bake cannot be cancelled: one
  that takes longer than the limit is measured to the end and marked too slow.

Every bake forces the scene's bounces (1, or 2 for the glass scenes), so that each row bakes
the chains of the reference.

Error: relMSE against a high-count photon reference of the same scene and settings (the
texel-averaged irradiance, every chain the scene has), all receivers and RGB channels, with
the definition of rel_mse in tests/fixtures/checks.py: mean over texels lit in either image of
(b - r)² / (r² + eps), eps = 1e-2 (mean lit r)².  The reference is the mean of two halves with
different seeds; relMSE(half1, half2) / 4 estimates its own noise, the floor under every
error measured against it (given per scene).  References are cached under
bench/results/ref_<scene>_<key>.npz, the key a hash of the .blend file and the settings.

Time: wall seconds of ``bake()`` in this process after a warm-up bake (kernels loaded);
cycles: of all its ``bpy.ops.object.bake`` calls (scene sync included) after a 1-sample one.
A bake longer than ``--limit`` seconds is cancelled (through the progress callback; tuple
batches are kept small so that it is seen) and reported as too slow; the method's larger
knobs are then skipped.  Chains a method cannot solve are skipped by the bake (newton / sms:
R, T; curve: T only) and listed; their light is missing, which the error shows.

Writes bench/results/chart.csv (scene,method,knob,seconds,relmse; empty seconds / relmse:
too slow or unavailable), bench/results/chart.json (the run, for ``--rewrite``),
bench/results/chart_<scene>.png (log-log error against time), bench/results/chart.md (every
sweep) and the "chart" section of BENCHMARKS.md (each estimator's most accurate point).  ``--quick``: 48² textures, 3 knob values, a 40 M photon
reference, bounces 2 only where the scene needs them (glass: TT), 15 s limit.
"""

import argparse
import csv
import hashlib
import json
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE]
RESULTS = os.path.join(HERE, "results")
SCENES = ("mirror_plane", "metal_ring", "water_pool", "glass_sphere", "glass_slab")
TWO_BOUNCE_SCENES = ("glass_sphere", "glass_slab")  # their main caustic is TT
METHODS = ("path-points/spoly", "forward-flux", "path-points/newton", "path-points/sms", "path-points/curve", "photon", "cycles")


def rel_mse(b, r):
    """relMSE (rel_mse of tests/fixtures/checks.py) over every texel and channel lit in either."""
    b = np.asarray(b, dtype=np.float64).ravel()
    r = np.asarray(r, dtype=np.float64).ravel()
    lit = (r > 0) | (b > 0)
    if not lit.any():
        return 0.0
    eps = 1e-2 * r[lit].mean() ** 2
    return float(np.mean((b[lit] - r[lit]) ** 2 / (r[lit] ** 2 + eps)))


def stack(result):
    """All receivers' raw images, concatenated in name order."""
    return np.concatenate([result.raw[k].ravel() for k in sorted(result.raw)])


def load_scene(name, res):
    from addon.bake.extract import extract_scene, open_blend

    path = os.path.join(ROOT, "sample_blends", name + ".blend")
    open_blend(path)
    with open(path, "rb") as fh:
        digest = hashlib.sha1(fh.read()).hexdigest()[:12]
    return extract_scene(resolution=res), digest


def reference(scene, name, digest, res, bounces, photons, force=False):
    """(image stack, floor, seconds) of the photon reference, cached on disk."""
    from addon.bake.pipeline import BakeSettings, bake

    key = hashlib.sha1(json.dumps(dict(d=digest, res=res, b=bounces, p=photons, v=1)).encode()).hexdigest()[:12]
    path = os.path.join(RESULTS, f"ref_{name}_{key}.npz")
    if os.path.exists(path) and not force:
        z = np.load(path)
        return z["ref"], float(z["floor"]), float(z["seconds"]), True
    t0 = time.perf_counter()
    halves = [stack(bake(scene, BakeSettings(resolution=res, bounces=bounces, margin=0, estimator="photon",
                                             photons=photons // 2, seed=1000 + k))) for k in range(2)]
    seconds = time.perf_counter() - t0
    ref = 0.5 * (halves[0] + halves[1])
    floor = rel_mse(halves[0], halves[1]) / 4.0
    os.makedirs(RESULTS, exist_ok=True)
    np.savez_compressed(path, ref=ref, floor=floor, seconds=seconds)
    return ref, floor, seconds, False


def settings_for(method, knob, res, bounces):
    """BakeSettings of chart row ``method`` (an estimator, or path-points/SOLVER) at ``knob``."""
    from addon.bake.settings import BakeSettings

    estimator, _, solver = method.partition("/")
    kw = dict(resolution=res, bounces=bounces, margin=0, seed=1, batch_tuples=1 << 14)
    if estimator == "forward-flux":
        kw.update(estimator="forward-flux", samples=1, image_depth=knob)
    elif estimator == "photon":
        kw.update(estimator="photon", photons=knob)
    else:  # exact paths at every supersample (R, T); two bounces: forward-flux
        kw.update(estimator="path-points", solver=solver, one_bounce="points", two_bounce="flux")
        kw.update(dict(samples=4, sms_seeds=knob) if solver == "sms" else dict(samples=knob))
    return BakeSettings(**kw)


class TooSlow(Exception):
    pass


def timed_bake(scene, settings, limit):
    """(result, seconds), or raises TooSlow after ``limit`` seconds."""
    from addon.bake.pipeline import BakeCancelled, bake

    t0 = time.perf_counter()

    def progress(_fraction, _message):
        return time.perf_counter() - t0 < limit

    try:
        out = bake(scene, settings, progress=progress)
    except BakeCancelled:
        raise TooSlow() from None
    return out, time.perf_counter() - t0


def sweep(quick):
    if quick:
        return {"path-points/spoly": [1, 4, 16], "forward-flux": [2, 4, 6], "path-points/newton": [1, 4, 16],
                "path-points/curve": [1, 4, 16], "path-points/sms": [1, 4, 16],
                "photon": [100_000, 400_000, 1_600_000], "cycles": [16, 64, 256]}
    return {"path-points/spoly": [1, 4, 16, 64], "forward-flux": [2, 3, 4, 5, 6, 7], "path-points/newton": [1, 4, 16, 64],
            "path-points/curve": [1, 4, 16, 64], "path-points/sms": [1, 4, 16, 64],
            "photon": [100_000, 1_000_000, 4_000_000, 16_000_000], "cycles": [16, 64, 256, 1024]}


def run_cycles(name, scene, bounces, ref, args, rows, notes):
    """The "cycles" rows of one scene (bench/cycles_bake.py); reopens the .blend afterwards,
    since the Cycles set-up changes the bpy scene (the other methods bake the extracted model
    and never see it)."""
    from addon.bake.extract import open_blend
    from addon.bake.pipeline import BakeSettings, make_context
    from addon.bake.plan import make_plan
    from cycles_bake import CyclesCaustics, CyclesUnavailable

    knobs = sweep(args.quick)["cycles"]
    plan = make_plan(make_context(scene, BakeSettings(resolution=8, bounces=bounces)))
    chains = list(dict.fromkeys(it.chain for it in plan.items if it.baked))
    rendered = [c for c in chains if set(c) == {"T"}]
    missing = [c for c in chains if c not in rendered]
    try:
        try:
            cc = CyclesCaustics(scene, args.res)
        except CyclesUnavailable as ex:
            rows.append(dict(scene=name, method="cycles", knob=knobs[0], seconds=None, relmse=None, note=str(ex)))
            print(f"  cycles  {str(ex)}", flush=True)
            return
        notes[name]["skipped"]["cycles"] = ([",".join(missing) + " not rendered (MNEE refracts only)"] if missing else []) + cc.notes
        cc.bake(1, seed=0)  # warm-up, not timed
        slow = False
        for knob in knobs:
            if slow:
                rows.append(dict(scene=name, method="cycles", knob=knob, seconds=None, relmse=None, note="skipped (smaller knob too slow)"))
                continue
            images, sec, _parts = cc.bake(knob, seed=1)
            if sec > args.limit:
                slow = True
                rows.append(dict(scene=name, method="cycles", knob=knob, seconds=None, relmse=None,
                                 note=f"too slow (> {args.limit:.0f} s; Cycles' bake cannot be cancelled: it took {sec:.1f} s)"))
                print(f"  cycles  {knob:>10,}  too slow ({sec:.1f} s > {args.limit:.0f} s)", flush=True)
                continue
            err = rel_mse(np.concatenate([images[k].ravel() for k in sorted(images)]), ref)
            rows.append(dict(scene=name, method="cycles", knob=knob, seconds=sec, relmse=err, note="chains " + ",".join(rendered)))
            print(f"  cycles  {knob:>10,}  {sec:8.2f} s  relMSE {err:.3e}  [{','.join(rendered)}]", flush=True)
    finally:
        open_blend(os.path.join(ROOT, "sample_blends", name + ".blend"))


def run_scene(name, args, rows, notes):
    res = args.res
    bounces = 2 if name in TWO_BOUNCE_SCENES else 1
    scene, digest = load_scene(name, res)
    ref, floor, ref_s, cached = reference(scene, name, digest, res, bounces, args.ref_photons)
    notes[name] = dict(floor=floor, ref_seconds=ref_s, cached=cached, bounces=bounces, skipped={})
    print(f"{name}: reference {args.ref_photons:,} photons ({'cached' if cached else f'{ref_s:.1f} s'}), noise floor "
          f"relMSE {floor:.2e}", flush=True)
    for method in args.methods:
        if method == "cycles":
            run_cycles(name, scene, bounces, ref, args, rows, notes)
            continue
        knobs = sweep(args.quick)[method]
        # Warm-up: load / compile the method's kernels on a tiny bake (not timed).
        from addon.bake.pipeline import bake

        warm_settings = settings_for(method, sweep(True)[method][0], 8, bounces)
        warm_settings.photons = min(warm_settings.photons, 1000)
        bake(scene, warm_settings, progress=None)
        slow = False
        for knob in knobs:
            if slow:
                rows.append(dict(scene=name, method=method, knob=knob, seconds=None, relmse=None, note="skipped (smaller knob too slow)"))
                continue
            try:
                out, sec = timed_bake(scene, settings_for(method, knob, res, bounces), args.limit)
            except TooSlow:
                slow = True
                rows.append(dict(scene=name, method=method, knob=knob, seconds=None, relmse=None, note=f"too slow (> {args.limit:.0f} s)"))
                print(f"  {method:7s} {knob:>10,}  too slow (> {args.limit:.0f} s)", flush=True)
                continue
            groups = {}
            for c in out.report["chains"]:
                if c["status"] != "baked":
                    groups.setdefault(c["status"], []).append(c["chain"])
            skipped = [",".join(chs) + " " + st for st, chs in groups.items()]
            baked = [c["chain"] for c in out.report["chains"] if c["status"] == "baked"]
            if skipped:
                notes[name]["skipped"][method] = skipped
            if not baked:
                rows.append(dict(scene=name, method=method, knob=knob, seconds=None, relmse=None,
                                 note="no chain baked (see below the table)"))
                print(f"  {method:7s} {knob:>10,}  no chain baked ({'; '.join(skipped)})", flush=True)
                break
            err = rel_mse(stack(out), ref)
            rows.append(dict(scene=name, method=method, knob=knob, seconds=sec, relmse=err, note="chains " + ",".join(baked)))
            print(f"  {method:7s} {knob:>10,}  {sec:8.2f} s  relMSE {err:.3e}  [{','.join(baked)}]", flush=True)


def write_csv(rows, path):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scene", "method", "knob", "seconds", "relmse"])
        for r in rows:
            w.writerow([r["scene"], r["method"], r["knob"], "" if r["seconds"] is None else f"{r['seconds']:.4f}",
                        "" if r["relmse"] is None else f"{r['relmse']:.6e}"])


def plot(rows, notes, scene, path, knob_label):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
    markers = {"path-points/spoly": "o", "path-points/newton": "s", "forward-flux": "P", "path-points/sms": "^",
               "path-points/curve": "D", "photon": "v", "cycles": "x"}
    any_point = False
    for method in METHODS:
        pts = [r for r in rows if r["scene"] == scene and r["method"] == method and r["relmse"] is not None]
        if not pts:
            continue
        x = [max(p["seconds"], 1e-3) for p in pts]
        y = [max(p["relmse"], 1e-8) for p in pts]
        ax.plot(x, y, marker=markers[method], label=method)
        for p, xi, yi in zip(pts, x, y):
            ax.annotate(knob_label(method, p["knob"]), (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7)
        any_point = True
    floor = notes[scene]["floor"]
    if floor > 0:
        ax.axhline(floor, color="grey", ls=":", lw=1, label="reference noise")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("bake time (s)")
    ax.set_ylabel("relMSE vs photon reference")
    ax.set_title(f"{scene}: error against time")
    ax.grid(True, which="both", alpha=0.3)
    if any_point:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def knob_label(method, knob):
    if method == "photon":
        return f"{knob / 1e6:g}M" if knob >= 1e6 else f"{knob / 1e3:g}k"
    if method == "path-points/sms":
        return f"{knob} seeds"
    if method == "forward-flux":
        return f"depth {knob}"
    return f"{knob} spp"


def _preamble(args, date):
    import numba

    return [f"Machine: {platform.machine()}, {os.cpu_count()} cores ({numba.config.NUMBA_NUM_THREADS} Numba threads, shared "
            f"with other jobs: timings are noisy), Python {platform.python_version()}; {args['res']}² textures, one light "
            f"sample, date {date}; {'`--quick`' if args['quick'] else 'full'} sweep.", ""]


def results_page(rows, notes, args, date):
    """bench/results/chart.md: every estimator's sweep per scene (the knobs, times, errors, notes)."""
    lines = ["# Speed against accuracy: every sweep (`bench/chart.py`)", ""] + _preamble(args, date)
    lines += ["Knobs: supersamples per texel (path-points with the spoly, newton, curve solvers: every exact R/T path "
              "the solver finds at every supersample; the two-bounce chains by forward-flux), subdivision depth of "
              "the forward-image sub-triangles (forward-flux, **the default estimator**), "
              "random seeds per tuple at 4 supersamples (path-points/sms), photons (photon), Cycles samples (cycles: "
              "Cycles' MNEE shadow caustics baked by bpy, two bakes per point, see bench/cycles_bake.py; refraction "
              "chains only). Error: relMSE (rel_mse of tests/fixtures/checks.py, all receivers and channels) against a "
              f"{args['ref_photons']:,}-photon reference of every chain the scene has (bounces 2 for the glass scenes: TT); "
              "'floor' is the reference's own noise (relMSE of its two halves / 4), under which no error can be measured. "
              f"Bakes over {args['limit']:.0f} s are cancelled and marked too slow (cycles: cannot be cancelled, measured "
              "to the end and marked).", ""]
    for scene in notes:
        n = notes[scene]
        lines.append(f"**{scene}** (bounces {n['bounces']}; reference floor relMSE {n['floor']:.1e}) "
                     f"![{scene}](chart_{scene}.png)")
        lines.append("")
        lines.append("| estimator | knobs | seconds | relMSE | note |")
        lines.append("|---|---|---|---|---|")
        methods = list(dict.fromkeys(r["method"] for r in rows if r["scene"] == scene))
        for method in methods:  # one row per estimator: its sweep as lists (the chart has the picture)
            rs = [r for r in rows if r["scene"] == scene and r["method"] == method]
            knobs = " / ".join(knob_label(method, r["knob"]) for r in rs)
            sec = " / ".join("–" if r["seconds"] is None else f"{r['seconds']:.2f}" for r in rs)
            err = " / ".join("–" if r["relmse"] is None else f"{r['relmse']:.1e}" for r in rs)
            row_notes = "; ".join(dict.fromkeys(r["note"] for r in rs if r["note"]))
            lines.append(f"| {method} | {knobs} | {sec} | {err} | {row_notes} |")
        for method, sk in n["skipped"].items():
            lines.append(f"\n{method}: " + "; ".join(sorted(set(sk))))
        lines.append("")
    lines.append(READING)
    return "\n".join(lines) + "\n"


READING = ("Reading the chart: path-points and forward-flux are deterministic: their error is the texel average's "
           "supersample error plus the paths a solver misses (newton, sms) or the chains it skips (newton/sms: R, T; "
           "curve: T), which no knob recovers; photon's error is noise (1/photons); cycles (MNEE) is bias: light its "
           "seeding misses, its clamp of the geometry term, and no reflection chains (bench/cycles_bake.py). Too slow: "
           "cut at the limit.")


def section(rows, notes, args, date):
    """The BENCHMARKS.md section: per scene and estimator the most accurate point of its sweep
    (lowest relMSE, then the fastest), as "relMSE · seconds"; the sweeps are on the results page."""
    lines = _preamble(args, date)
    lines += [f"Question: for each estimator, how close to a {args['ref_photons'] / 1e6:g} M-photon reference does it get, "
              "and at what time? Each cell is the estimator's most accurate point of its sweep, *relMSE · seconds* "
              "(– : no chain of the scene baked, or too slow); 'floor' is the reference's own noise. Every sweep, knob "
              "and note: [bench/results/chart.md](bench/results/chart.md); charts: "
              + ", ".join(f"[{sc}](bench/results/chart_{sc}.png)" for sc in notes) + ".", ""]
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    lines.append("| scene (floor) | " + " | ".join(methods) + " |")
    lines.append("|---|" + "---|" * len(methods))
    for scene in notes:
        cells = []
        for method in methods:
            rs = [r for r in rows if r["scene"] == scene and r["method"] == method and r["relmse"] is not None
                  and r["seconds"] is not None]
            if not rs:
                cells.append("–")
                continue
            best = min(rs, key=lambda r: (float(f"{r['relmse']:.1e}"), r["seconds"]))
            cells.append(f"{best['relmse']:.1e} · {best['seconds']:.2f}")
        lines.append(f"| {scene} ({notes[scene]['floor']:.1e}) | " + " | ".join(cells) + " |")
    lines += ["", READING]
    return "\n".join(lines)


def publish(rows, notes, args, date, write):
    """Write the results page and (``write``) the BENCHMARKS.md section; print the section."""
    with open(os.path.join(RESULTS, "chart.md"), "w") as fh:
        fh.write(results_page(rows, notes, args, date))
    body = section(rows, notes, args, date)
    print(body)
    if write:
        from solver import write_section

        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "chart", "Speed against accuracy (`bench/chart.py`)", body)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reduced sweep in a few minutes")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--res", type=int, default=None, help="texels per side (default 48 quick, 128 full)")
    ap.add_argument("--ref-photons", type=int, default=None, help="reference photons (default 5M quick, 64M full)")
    ap.add_argument("--limit", type=float, default=None, help="seconds before a bake counts as too slow (15 quick, 120 full)")
    ap.add_argument("--no-write", action="store_true", help="do not touch BENCHMARKS.md")
    ap.add_argument("--rewrite", action="store_true",
                    help="re-write the results page and the section from bench/results/chart.json (no bakes)")
    args = ap.parse_args(argv)
    saved = os.path.join(RESULTS, "chart.json")
    if args.rewrite:
        with open(saved) as fh:
            run = json.load(fh)
        publish(run["rows"], run["notes"], run["args"], run["date"], not args.no_write)
        return 0
    args.res = args.res or (48 if args.quick else 128)
    args.ref_photons = args.ref_photons or (40_000_000 if args.quick else 64_000_000)
    args.limit = args.limit or (15.0 if args.quick else 120.0)
    args.methods = args.methods.split(",")
    rows, notes = [], {}
    os.makedirs(RESULTS, exist_ok=True)
    for name in args.scenes.split(","):
        run_scene(name, args, rows, notes)
    write_csv(rows, os.path.join(RESULTS, "chart.csv"))
    for scene in notes:
        plot(rows, notes, scene, os.path.join(RESULTS, f"chart_{scene}.png"), knob_label)
    run = {"date": time.strftime("%Y-%m-%d"), "rows": rows, "notes": notes,
           "args": {"res": args.res, "quick": args.quick, "ref_photons": args.ref_photons, "limit": args.limit}}
    with open(saved, "w") as fh:
        json.dump(run, fh, indent=1)
    publish(rows, notes, run["args"], run["date"], not args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
