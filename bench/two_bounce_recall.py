"""Two-bounce recall harness: the tuples of tests/solver/test_solver_two_bounce.py's acceptance run,
brute-force truth cached once, the solver's misses listed with diagnostics.

    .venv/bin/python bench/two_bounce_recall.py --chain RT --tuples 10000 [--pieces 100] [--diag]
        [--cache /tmp/two_bounce_truth] [--only 1,2,3]

The tuples are ``make_dataset(chain, n=tuples)`` of the test (same SEED, same generator), so
``--tuples 10000`` is the acceptance set.  The brute force (tests/reference/bruteforce.py,
~15-120 ms per tuple) runs once per (chain, tuples) in chunks of ``--chunk`` tuples, each
chunk saved as an .npz under ``--cache`` (resumable); later runs only solve.

Printed: recall of the required paths (the test's margins), false paths, duplicates (the
test's rules), µs/tuple, and per missed path (``--diag``): the tuple, its (u1, v1, u2, v2),
sigma_min, cos_i, inside margin, TIR margin, the nearest other brute-force path of the tuple
(in the forward v1 and in the reversed v2, the hidden variables of the two orientations)
and what the solver found there.  ``--diag`` also evaluates the resultant of the systems
of both orientations around the missed root (``diagnose_system``).
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
TESTS = os.path.join(ROOT, "tests")
for p in (ROOT, TESTS):
    if p not in sys.path:
        sys.path.insert(0, p)

from reference import bruteforce as bf  # noqa: E402
from reference import truth_two_bounce as T  # noqa: E402


def truth(chain, n, cache, chunk):
    """The dataset of the test with its brute-force truth (cached per chunk)."""
    d = T.make_dataset(chain, n=n)
    folder = os.path.join(cache, f"{chain}_{n}_{T.SEED}")
    os.makedirs(folder, exist_ok=True)
    merged = os.path.join(folder, "truth.npz")
    if not os.path.exists(merged):
        for s in range(0, n, chunk):
            f = os.path.join(folder, f"chunk_{s:06d}.npz")
            if os.path.exists(f):
                continue
            e = min(n, s + chunk)
            t0 = time.time()
            ti, uv, chk = bf.solve_bruteforce(chain, d["x0"][s:e], d["x3"][s:e], d["P"][s:e], d["N"][s:e], d["eta"][s:e],
                                              return_all=True)
            ti = ti + s
            sig = bf.root_sigma_min(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv) \
                if len(ti) else np.zeros(0)
            np.savez(f, ti=ti, uv=uv, sigma=sig, inside_margin=chk.inside_margin, cos_i=chk.cos_i, k_min=chk.k_min)
            print(f"  truth {chain} [{s}, {e}): {len(ti)} paths, {time.time() - t0:.0f} s", flush=True)
        parts = [dict(np.load(f)) for f in sorted(glob.glob(os.path.join(folder, "chunk_*.npz")))]
        np.savez(merged, **{k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
    z = dict(np.load(merged))
    d.update(bf_t=z["ti"], bf_uv=z["uv"], bf_sigma=z["sigma"], inside_margin=z["inside_margin"], cos_i=z["cos_i"],
             k_min=z["k_min"])
    return d


def required_mask(d):
    return ((d["inside_margin"] >= T.RECALL_MARGIN) & (d["cos_i"] >= T.GRAZE_MARGIN) & (d["k_min"] >= T.TIR_MARGIN)
            & (d["bf_sigma"] >= T.SIGMA_MARGIN))


def duplicates(chain, d, ti, uv):
    pol = bf.polish(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv) if len(ti) else uv
    dup = []
    bounds = np.flatnonzero(np.diff(ti)) + 1
    for s_, e_ in zip(np.r_[0, bounds], np.r_[bounds, len(ti)]):
        for a in range(s_, e_):
            for b in range(a + 1, e_):
                if np.abs(pol[a] - pol[b]).max() < T.DUP_TOL:
                    dup.append((a, b))
    return dup


def evaluate(chain, d, ti, uv):
    chk = bf.check_path(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv, tol=T.FALSE_TOL)
    false = np.flatnonzero(~chk.valid)
    dup = duplicates(chain, d, ti, uv)
    req = required_mask(d)
    m = T.match_paths(d["bf_t"], d["bf_uv"], ti, uv)
    miss = np.flatnonzero(req & (m < 0))
    return dict(false=false, dup=dup, req=req, match=m, miss=miss, recall=1.0 - len(miss) / max(1, int(req.sum())))


def solve(chain, d, pieces, idx=None):
    from addon.solver.spoly.api import SpecularPolynomialSolver

    s = SpecularPolynomialSolver()
    sel = slice(None) if idx is None else idx
    t0 = time.perf_counter()
    res = s.solve(chain, d["x0"][sel], d["x3"][sel], d["P"][sel], d["N"][sel], d["eta"][sel], pieces=pieces)
    dt = time.perf_counter() - t0
    ti = res.tuple_index if idx is None else np.asarray(idx)[res.tuple_index]
    return ti, res.uv, dt, res.report


def describe_miss(chain, d, b, ti, uv):
    t = int(d["bf_t"][b])
    same = np.flatnonzero(d["bf_t"] == t)
    mine = d["bf_uv"][b]
    others = [int(o) for o in same if o != b]
    lines = [f"tuple {t} ({d['cat'][t]}) eta={d['eta'][t]:.4g}: missed uv={np.array2string(mine, precision=9)} "
             f"sigma={d['bf_sigma'][b]:.3g} cos_i={d['cos_i'][b]:.3g} inside={d['inside_margin'][b]:.3g} "
             f"k_min={d['k_min'][b]:.3g}; brute-force paths in tuple: {len(same)}"]
    for o in others:
        ou = d["bf_uv"][o]
        lines.append(f"    other bf path uv={np.array2string(ou, precision=9)} |dv1|={abs(ou[1] - mine[1]):.3g} "
                     f"|dv2|={abs(ou[3] - mine[3]):.3g} |du1|={abs(ou[0] - mine[0]):.3g} |du2|={abs(ou[2] - mine[2]):.3g} "
                     f"max={np.abs(ou - mine).max():.3g}")
    sol = uv[ti == t]
    for s in sol:
        lines.append(f"    solver path uv={np.array2string(s, precision=9)} dist to missed {np.abs(s - mine).max():.3g}")
    return t, "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chain", default="RT")
    ap.add_argument("--tuples", type=int, default=10000)
    ap.add_argument("--pieces", type=int, default=None)
    ap.add_argument("--cache", default="/tmp/two_bounce_truth")
    ap.add_argument("--chunk", type=int, default=500)
    ap.add_argument("--truth-only", action="store_true")
    ap.add_argument("--diag", action="store_true", help="resultant diagnostics around each missed root")
    ap.add_argument("--only", default="", help="comma-separated tuple indices to solve (default: all)")
    ap.add_argument("--range", default="", help="a:b, solve tuples a .. b-1 only")
    ap.add_argument("--save", default="", help="save the solver's paths to this .npz")
    ap.add_argument("--exact", default="", help="comma-separated tuples: det_bezout and the padded Bézout matrix "
                    "against exact arithmetic around each tuple's first brute-force path (both orientations)")
    args = ap.parse_args()
    d = truth(args.chain, args.tuples, args.cache, args.chunk)
    if args.truth_only:
        return
    if args.exact:
        from two_bounce_diag import exact_check

        agg = {}
        for t in (int(x) for x in args.exact.split(",")):
            uv0 = d["bf_uv"][d["bf_t"] == t]
            if not len(uv0):
                continue
            for rev in (False, True):
                res = exact_check(args.chain, d, t, uv0[0], rev)
                for name, rows in res.items():
                    agg.setdefault((rev, name), []).extend(rows)
                print(f"  tuple {t} {'reversed' if rev else 'forward'}: " + "; ".join(
                    f"{k} sign ok {sum(r[0] for r in v)}/{len(v)} max log err {max(r[1] for r in v):.2g}" for k, v in res.items()),
                    flush=True)
        for (rev, name), rows in sorted(agg.items()):
            e = np.array([r[1] for r in rows])
            print(f"{'reversed' if rev else 'forward'} {name}: sign wrong at {sum(not r[0] for r in rows)}/{len(rows)} "
                  f"samples; log error median {np.median(e):.2g}, max {e.max():.2g}")
        return
    idx = [int(x) for x in args.only.split(",")] if args.only else None
    if args.range:
        a_, b_ = (int(x) for x in args.range.split(":"))
        idx = list(range(a_, b_))
    ti, uv, dt, rep = solve(args.chain, d, args.pieces, idx)
    n = len(d["x0"]) if idx is None else len(idx)
    if args.save:
        np.savez(args.save, ti=ti, uv=uv)
    if idx is not None:
        keep = np.isin(d["bf_t"], idx)
        for k in ("bf_t", "bf_uv", "bf_sigma", "inside_margin", "cos_i", "k_min"):
            d[k] = d[k][keep]
    ev = evaluate(args.chain, d, ti, uv)
    print(f"[{args.chain}] {n} tuples, pieces {args.pieces or 'default'}: solve {dt:.1f} s ({1e6 * dt / n:.0f} µs/tuple), "
          f"determinants {rep.determinants}; paths {len(ti)}, brute force {len(d['bf_t'])} (required "
          f"{int(ev['req'].sum())}); recall {100 * ev['recall']:.3f} % ({len(ev['miss'])} missed); false "
          f"{len(ev['false'])}; duplicates {len(ev['dup'])}", flush=True)
    for r in ev["false"][:10]:
        print(f"  FALSE tuple {ti[r]} uv={uv[r]}")
    for a, b in ev["dup"][:10]:
        print(f"  DUPLICATE tuple {ti[a]} {uv[a]} / {uv[b]}")
    missed_tuples = []
    for b in ev["miss"]:
        t, text = describe_miss(args.chain, d, b, ti, uv)
        missed_tuples.append(t)
        print(text)
        if args.diag:
            from two_bounce_diag import diagnose_path

            print(diagnose_path(args.chain, d, t, d["bf_uv"][b], args.pieces))
    print("missed tuples:", ",".join(str(t) for t in sorted(set(missed_tuples))))


if __name__ == "__main__":
    main()
