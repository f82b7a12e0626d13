"""Randomised check of addon.solver.solve_tuples (one bounce) against an independent brute force.

Ground truth: tests/reference/bruteforce.py (dense-seeded Levenberg-Marquardt on eq. (3) of Fan et
al. 2024 + deflation, validated by an independent implementation of CONTRACT.md's path rules).

Per chain ("R", "T") >= 10,000 tuples from a fixed seed:
  planted_tilt    a path planted at a random (u,v); vertex normals tilted up to 45 deg
  planted_sphere  same on strongly curved (sphere-like, concave/convex) normal fields
  two_path        two planted paths whose outgoing rays really intersect (x2 := intersection)
  random          plain random endpoints around the triangle (mostly no path)
  near_tir        (T only) light from the dense side close to the critical angle, half of them
                  nudged past it (x0 "inside the medium" for eta > 1)
with random shapes, sizes 1e-3..10, offsets up to 500 units, non-unit vertex normals, random
winding vs normal orientation, eta in [0.6, 0.95] u [1.1, 2.5].

Asserts: output dtypes/shapes, no NaN, ascending tuple_index, zero false paths (every solver path
passes check_path with a 1e-6 direction tolerance and lies in the triangle with the contract
epsilon), no duplicate paths, recall >= 99.99 % of brute-force paths that are inside by >= 1e-7 and
not at a grazing / TIR edge (cos_i >= 1e-4, k >= 1e-6 for T) nor ill-conditioned (smallest singular
value of the constraint Jacobian d(h x n)/d(u,v) >= 1e-5; such near-double roots are not located to
1e-6 by any method). Paths outside these margins are reported, not required. Run with -s to see the counts.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from reference import bruteforce as bf
from reference.truth import (COUNTS, DUP_TOL, FALSE_TOL, GRAZE_MARGIN, POLISH_TOL, RECALL_MARGIN,
                             SEED, SIGMA_MARGIN, TIR_MARGIN, dataset_with_truth, make_dataset, match_paths)
from reference.truth import mixed_normals

RECALL_MIN = 0.9999


# ----------------------------------------------------------------------------------------------
# solver runs (module cache: computed once per chain)
# ----------------------------------------------------------------------------------------------
_CACHE: dict = {}


def _solver():
    try:
        from addon.solver import solve_tuples  # noqa: WPS433
    except Exception as exc:  # pragma: no cover - solver not there yet
        pytest.fail(f"addon.solver.solve_tuples not importable: {exc!r}")
    return solve_tuples


def _run_solver(chain, d):
    key = ("solver", chain)
    if key not in _CACHE:
        solve_tuples = _solver()
        t = time.time()
        out = solve_tuples(chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"])
        _CACHE[key] = (out, time.time() - t)
    return _CACHE[key]


def _polished(chain, d, ti, uv):
    """Reference Newton polish of the solver rows: (polished uv, |moved|, sigma_min there)."""
    key = ("polish", chain)
    if key not in _CACHE:
        A = (d["x0"][ti], d["x2"][ti], d["P"][ti], d["N"][ti], d["eta"][ti])
        pol = bf.polish(chain, *A, uv)
        moved = np.abs(pol - uv).max(1) if len(uv) else np.zeros(0)
        sig = bf.root_sigma_min(chain, *A, pol) if len(uv) else np.zeros(0)
        _CACHE[key] = (pol, moved, sig)
    return _CACHE[key]


def _describe(d, t, extra=""):
    np.set_printoptions(precision=17, linewidth=150)
    s = (
        f"--- tuple {t} (category {d['cat'][t]}) {extra}\n"
        f"chain={d['chain']!r}\nx_start=np.array([{d['x0'][t].tolist()!r}])\n"
        f"x_end=np.array([{d['x2'][t].tolist()!r}])\nP=np.array([{d['P'][t].tolist()!r}])\n"
        f"N=np.array([{d['N'][t].tolist()!r}])\neta={float(d['eta'][t])!r}\n"
        f"brute-force uv: {d['bf_uv'][d['bf_t'] == t].tolist()!r}\n"
    )
    return s


# ----------------------------------------------------------------------------------------------
# tests that need no solver: the reference itself
# ----------------------------------------------------------------------------------------------
@pytest.mark.slow  # the 10,000-tuple brute-force truth (reference/truth.py): ~30-60 s per chain here
@pytest.mark.parametrize("chain", ["R", "T"])
def test_bruteforce_recovers_planted(chain):
    d = dataset_with_truth(chain)
    n = len(d["x0"])
    planted_t, planted_uv = [], []
    for key in ("uv1", "uv2"):
        ok = np.isfinite(d[key][:, 0])
        planted_t.append(np.flatnonzero(ok))
        planted_uv.append(d[key][ok])
    pt = np.concatenate(planted_t)
    pu = np.concatenate(planted_uv)
    # the planted paths are valid per the independent contract check (tol 1e-7 as the contract)
    chk = bf.check_path(chain, d["x0"][pt], d["x2"][pt], d["P"][pt], d["N"][pt], d["eta"][pt], np.asarray(pu))
    assert chk.valid.all(), np.unique(chk.reason[~chk.valid], return_counts=True)
    m = match_paths(pt, pu, d["bf_t"], d["bf_uv"])
    counts = np.bincount(d["bf_t"], minlength=n)
    two = d["cat"] == "two_path"
    print(
        f"\n[{chain}] tuples={n} generation {d['t_gen']:.1f}s brute force {d['t_bf']:.1f}s: "
        f"paths={len(d['bf_t'])} tuples with >=2 paths={int((counts >= 2).sum())} "
        f"(>=3: {int((counts >= 3).sum())}); planted paths={len(pt)} recovered={int((m >= 0).sum())}"
    )
    for cat in COUNTS[chain]:
        sel = d["cat"] == cat
        print(
            f"    {cat:15s} tuples={int(sel.sum()):5d} paths={int(counts[sel].sum()):5d} "
            f">=2 paths={int((counts[sel] >= 2).sum()):5d} zero paths={int((counts[sel] == 0).sum()):5d}"
        )
    missed = pt[m < 0]
    msg = "".join(_describe(d, t, "planted path not recovered") for t in missed[:5])
    assert (m >= 0).all(), f"brute force lost {len(missed)} planted paths\n{msg}"
    # every brute-force path is valid and inside (the reference's own post-condition)
    assert d["bf_chk"].valid.all()
    assert (counts[two] >= 2).all()
    assert (counts >= 2).sum() >= 2000


# ----------------------------------------------------------------------------------------------
# the solver
# ----------------------------------------------------------------------------------------------
@pytest.mark.slow  # the 10,000-tuple brute-force truth (reference/truth.py): ~30-60 s per chain here
@pytest.mark.parametrize("chain", ["R", "T"])
def test_solver_against_bruteforce(chain):
    d = dataset_with_truth(chain)
    n = len(d["x0"])
    (ti, uv), t_solve = _run_solver(chain, d)

    # ---- output format per the contract
    assert isinstance(ti, np.ndarray) and isinstance(uv, np.ndarray)
    assert ti.dtype == np.int64, ti.dtype
    assert uv.dtype == np.float64, uv.dtype
    assert ti.ndim == 1 and uv.shape == (len(ti), 2), (ti.shape, uv.shape)
    assert np.isfinite(uv).all(), f"NaN/Inf in uv at rows {np.flatnonzero(~np.isfinite(uv).all(1))[:10]}"
    assert (np.diff(ti) >= 0).all(), "tuple_index not ascending"
    assert ti.size == 0 or (ti.min() >= 0 and ti.max() < n)

    # ---- zero false paths (independent contract check)
    chk = bf.check_path(chain, d["x0"][ti], d["x2"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv, tol=FALSE_TOL)
    false = np.flatnonzero(~chk.valid)
    # ---- duplicates (the same path reported twice would double its energy): two rows of a tuple
    # whose reference-Newton polish (eq. 3, started at the solver's uv) lands on the same root
    pol, moved, sig_s = _polished(chain, d, ti, uv)
    dup = []  # (row kept, duplicate row)
    bounds = np.flatnonzero(np.diff(ti)) + 1
    for s_, e_ in zip(np.r_[0, bounds], np.r_[bounds, len(ti)]):
        for a in range(s_, e_):
            for b in range(a + 1, e_):
                if np.abs(pol[a] - pol[b]).max() < DUP_TOL or np.abs(uv[a] - uv[b]).max() < DUP_TOL:
                    dup.append((a, b) if moved[a] <= moved[b] else (b, a))

    # ---- recall against the brute force
    bchk = d["bf_chk"]
    required = (
        (bchk.inside_margin >= RECALL_MARGIN)
        & (bchk.cos_i >= GRAZE_MARGIN)
        & (bchk.k_min >= TIR_MARGIN)
        & (d["bf_sigma"] >= SIGMA_MARGIN)
    )
    m = match_paths(d["bf_t"], d["bf_uv"], ti, uv)
    miss = np.flatnonzero(required & (m < 0))
    miss_edge = int((~required & (m < 0)).sum())
    back = match_paths(ti, uv, d["bf_t"], d["bf_uv"])
    extra = int((back < 0).sum())  # solver paths the brute force did not find (valid ones are fine)

    counts = np.bincount(d["bf_t"], minlength=n)
    print(
        f"\n[{chain}] solve_tuples: {t_solve:.2f}s for {n} tuples; solver paths={len(ti)}; "
        f"brute-force paths={len(d['bf_t'])} (required for recall {int(required.sum())}), "
        f"tuples with >=2 paths={int((counts >= 2).sum())}"
    )
    print(
        f"    misses={len(miss)} (recall {1 - len(miss) / max(1, required.sum()):.6f}); "
        f"misses among edge/grazing/near-TIR/ill-conditioned paths not required={miss_edge}/{int((~required).sum())}; "
        f"false paths={len(false)}; duplicates={len(dup)}; valid solver paths not in brute force={extra}"
    )
    if len(ti):
        print(
            f"    solver path residual: max={chk.residual.max():.3g}, >1e-10: {int((chk.residual > 1e-10).sum())}, "
            f">1e-7 (contract): {int((chk.residual > 1e-7).sum())}"
        )
    for cat in COUNTS[chain]:
        sel_b = d["cat"][d["bf_t"]] == cat
        print(
            f"    {cat:15s} bf paths={int(sel_b.sum()):5d} required={int((required & sel_b).sum()):5d} "
            f"missed={int((required & sel_b & (m < 0)).sum()):4d} "
            f"false={int((d['cat'][ti[false]] == cat).sum()) if len(false) else 0:4d}"
        )

    msgs = []
    if len(false):
        msgs.append(f"{len(false)} FALSE paths returned by solve_tuples; first ones:")
        for r in false[:5]:
            msgs.append(
                _describe(d, ti[r], f"solver uv={uv[r].tolist()!r} fails check: {chk.reason[r]} "
                          f"residual={chk.residual[r]:.3g} cos_i={chk.cos_i[r]:.3g} "
                          f"inside_margin={chk.inside_margin[r]:.3g} k={chk.k_min[r]:.3g}")
            )
    if dup:
        msgs.append(
            f"{len(dup)} DUPLICATE paths (two solver rows of one tuple converge to the same root of "
            f"eq. 3 under the reference Newton polish: the same physical path counted twice); first ones:"
        )
        for a, b in dup[:4]:
            msgs.append(
                _describe(d, ti[a], f"solver rows {uv[a].tolist()!r} (residual {chk.residual[a]:.3g}) and "
                          f"{uv[b].tolist()!r} (residual {chk.residual[b]:.3g}) both polish to "
                          f"{pol[a].tolist()!r}; all solver rows of this tuple: {uv[ti == ti[a]].tolist()!r}")
            )
    if len(miss) > int(np.floor((1 - RECALL_MIN) * required.sum())):
        msgs.append(f"{len(miss)} MISSED brute-force paths (of {int(required.sum())} required); first ones:")
        for b in miss[:5]:
            t = d["bf_t"][b]
            msgs.append(
                _describe(d, t, f"missed uv={d['bf_uv'][b].tolist()!r} cos_i={bchk.cos_i[b]:.3g} "
                          f"k={bchk.k_min[b]:.3g} margin={bchk.inside_margin[b]:.3g} "
                          f"sigma_min={d['bf_sigma'][b]:.3g}; "
                          f"solver uv for this tuple: {uv[ti == t].tolist()!r}")
            )
    assert not msgs, "\n".join(msgs)
    assert required.sum() > 10_000  # the comparison really covers many paths


@pytest.mark.slow  # the 10,000-tuple brute-force truth (reference/truth.py): ~30-60 s per chain here
@pytest.mark.parametrize("chain", ["R", "T"])
def test_solver_paths_polished(chain):
    """Contract: 'returned paths are Newton-polished to ~1e-12'. Checked in uv space (the
    direction residual is ill-conditioned next to TIR): every solver path at a well-conditioned
    root (sigma_min >= 1e-5) lies within 1e-7 of the root the reference Newton converges to."""
    d = dataset_with_truth(chain)
    (ti, uv), _ = _run_solver(chain, d)
    pol, moved, sig = _polished(chain, d, ti, uv)
    chk = bf.check_path(chain, d["x0"][ti], d["x2"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv, tol=FALSE_TOL)
    well = sig >= SIGMA_MARGIN
    bad = np.flatnonzero(well & (moved > POLISH_TOL))
    print(
        f"\n[{chain}] solver rows={len(ti)} well-conditioned={int(well.sum())}; distance to the polished root: "
        f"max={moved[well].max() if well.any() else 0:.3g}, >1e-9: {int((well & (moved > 1e-9)).sum())}, "
        f">1e-7: {len(bad)}; direction residual >1e-10: {int((chk.residual > 1e-10).sum())}, "
        f">1e-7 (contract tolerance): {int((chk.residual > 1e-7).sum())}"
    )
    msg = "".join(
        _describe(d, ti[r], f"solver uv={uv[r].tolist()!r} residual={chk.residual[r]:.3g} is {moved[r]:.3g} "
                  f"from the root {pol[r].tolist()!r} (sigma_min={sig[r]:.3g})")
        for r in bad[:4]
    )
    assert len(bad) == 0, f"{len(bad)} solver paths are not polished roots\n{msg}"


def make_normal_incidence(chain, n=400, seed=SEED):
    """Planted paths at normal incidence: x0 and x_end on the line through x1 along the shading
    normal (x0, x1, x_end collinear: the mirror sends the light straight back, the interface lets
    it straight through). Half flat (vertex normals = face normal), half tilted / curved fields."""
    rng = np.random.default_rng([seed, ord(chain), 7])
    P = bf.random_triangles(rng, n)
    N = mixed_normals(rng, P, 0.3)
    flat = np.arange(n) < n // 2
    fn, _ = bf._unit(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    sgn = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    N[flat] = (fn * sgn[:, None])[flat][:, None, :] * np.ones((1, 3, 1))
    eta = bf.random_eta(rng, n)
    a = rng.random((n, 2))
    f = a.sum(1) > 1
    a[f] = 1 - a[f]
    a = 0.01 + 0.97 * a
    x1, nh, _, _ = bf.interpolate(P, N, a[:, 0], a[:, 1])
    size = bf.tri_size(P)
    s = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    x0 = x1 + (size * 10.0 ** rng.uniform(-0.5, 2, n) * s)[:, None] * nh
    out = s if chain == "R" else -s
    x2 = x1 + (size * 10.0 ** rng.uniform(-0.5, 2, n) * out)[:, None] * nh
    return dict(chain=chain, P=P[:, None].copy(), N=N[:, None].copy(), eta=eta, x0=x0, x2=x2, uv=a, flat=flat,
                cat=np.where(flat, "normal_inc_flat", "normal_inc_curved").astype(object))


@pytest.mark.parametrize("chain", ["R", "T"])
def test_solver_normal_incidence(chain):
    """x0, x1, x_end collinear along the normal (e.g. a light straight above a window / mirror and a
    receiver point on that line): a valid path (cos_i = 1) that must be found, not dropped."""
    solve_tuples = _solver()
    d = make_normal_incidence(chain)
    n = len(d["x0"])
    A = (d["x0"], d["x2"], d["P"], d["N"], d["eta"])
    chk = bf.check_path(chain, *A, d["uv"])
    assert chk.valid.all(), np.unique(chk.reason[~chk.valid], return_counts=True)
    ti, uv = solve_tuples(chain, *A)
    m = match_paths(np.arange(n), d["uv"], ti, uv)
    schk = bf.check_path(chain, *[x[ti] for x in A], uv, tol=FALSE_TOL)
    bt, bu = bf.solve_bruteforce(chain, *A)
    mb = match_paths(np.arange(n), d["uv"], bt, bu)
    d.update(bf_t=bt, bf_uv=bu)
    miss = np.flatnonzero(m < 0)
    print(
        f"\n[{chain}] normal incidence: planted={n} (flat {int(d['flat'].sum())}) brute force recovers "
        f"{int((mb >= 0).sum())}; solver finds {int((m >= 0).sum())} (flat {int((m[d['flat']] >= 0).sum())}, "
        f"curved {int((m[~d['flat']] >= 0).sum())}); false paths={int((~schk.valid).sum())}"
    )
    assert (mb >= 0).all()
    msg = "".join(_describe(d, t, f"planted uv={d['uv'][t].tolist()!r}; solver uv for this tuple: "
                                  f"{uv[ti == t].tolist()!r}") for t in miss[:4])
    assert schk.valid.all(), "false paths at normal incidence"
    assert len(miss) == 0, f"{len(miss)} normal-incidence paths missed\n{msg}"


def test_solver_input_validation():
    """Contract: NaN/Inf, wrong shapes, unknown chain -> ValueError; degenerate -> no path."""
    solve_tuples = _solver()
    d = make_dataset("R", counts=dict(planted_tilt=4))
    args = [d["x0"], d["x2"], d["P"], d["N"], d["eta"]]
    ti, uv = solve_tuples("R", *args)
    assert len(ti) >= 4
    bad = [a.copy() for a in args]
    bad[0][1, 2] = np.nan
    with pytest.raises(ValueError):
        solve_tuples("R", *bad)
    bad = [a.copy() for a in args]
    bad[2][0, 0, 1, 0] = np.inf
    with pytest.raises(ValueError):
        solve_tuples("R", *bad)
    with pytest.raises(ValueError):
        solve_tuples("X", *args)
    with pytest.raises(ValueError):
        solve_tuples("R", args[0][:3], *args[1:])
    with pytest.raises(ValueError):
        solve_tuples("R", args[0], args[1], args[2][:, :, :2], args[3], args[4])
    # degenerate tuples: zero-area triangle, zero normals, endpoints in the plane -> no path
    P = d["P"].copy()
    P[0, 0, 2] = P[0, 0, 0] + 0.5 * (P[0, 0, 1] - P[0, 0, 0])  # collinear corners
    N = d["N"].copy()
    N[1] = 0.0
    x0 = d["x0"].copy()
    x0[2] = d["P"][2, 0].mean(0) + 3.0 * (d["P"][2, 0, 1] - d["P"][2, 0, 0])  # in the plane
    ti, uv = solve_tuples("R", x0, d["x2"], P, N, d["eta"])
    assert not np.isin(ti, [0, 1, 2]).any(), ti
    assert np.isin(3, ti)
