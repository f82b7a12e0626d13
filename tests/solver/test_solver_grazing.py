"""T (one refraction) at grazing incidence and near the critical angle, against brute force.

The tuples are tests/reference/grazing.py's (light outside at cos_i 0.005-0.45 refracted into
water / glass, the reverse paths leaving at grazing angles, and light inside just under the
critical angle; flat-ish, tilted and curved normal fields; endpoints close to large triangles
and a far sun).  Every tuple holds a planted path.  Asserts: every planted path is returned
(fast test); zero false paths (independent contract check, 1e-6); recall >= 99.99 % of the
brute-force paths that are not at the contract's edge of validity, together with the planted
paths the brute force itself misses (slow test, reference bruteforce.py over every tuple).
"""
from __future__ import annotations

import numpy as np
import pytest

from reference import bruteforce as bf
from reference.grazing import CATEGORIES, grazing_with_truth, make_grazing
from reference.truth import FALSE_TOL, GRAZE_MARGIN, RECALL_MARGIN, SIGMA_MARGIN, TIR_MARGIN, match_paths

RECALL_MIN = 0.9999


def _solve(d):
    from addon.solver import solve_tuples

    return solve_tuples("T", d["x0"], d["x2"], d["P"], d["N"], d["eta"])


def _args(d, rows=None):
    A = (d["x0"], d["x2"], d["P"], d["N"], d["eta"])
    return A if rows is None else tuple(a[rows] for a in A)


def test_grazing_planted_paths_are_found():
    d = make_grazing(36_000)
    n = len(d["x0"])
    assert n > 30_000
    planted = bf.check_path("T", *_args(d), d["uv"])
    assert planted.valid.all()
    assert planted.cos_i.min() < 0.01 and np.median(planted.k_min) < 0.6  # really grazing / near-critical
    ti, uv = _solve(d)
    chk = bf.check_path("T", *_args(d, ti), uv, tol=FALSE_TOL)
    found = match_paths(np.arange(n), d["uv"], ti, uv) >= 0
    print(f"\n[grazing] tuples={n} paths={len(ti)} planted found={int(found.sum())} false={int((~chk.valid).sum())}")
    for cat in CATEGORIES:
        sel = d["cat"] == cat
        print(f"    {cat:14s} tuples={int(sel.sum()):6d} planted missed={int((~found & sel).sum())}")
    assert chk.valid.all(), f"{int((~chk.valid).sum())} false paths"
    assert found.mean() >= RECALL_MIN, f"{int((~found).sum())} planted paths missed of {n}"


@pytest.mark.slow  # brute force over 12,000 tuples: ~2 min here
def test_grazing_recall_against_bruteforce():
    d = grazing_with_truth(12_000)
    n = len(d["x0"])
    ti, uv = _solve(d)
    chk = bf.check_path("T", *_args(d, ti), uv, tol=FALSE_TOL)
    b = d["bf_chk"]
    required = ((b.inside_margin >= RECALL_MARGIN) & (b.cos_i >= GRAZE_MARGIN) & (b.k_min >= TIR_MARGIN)
                & (d["bf_sigma"] >= SIGMA_MARGIN))
    # the truth: the brute-force paths plus the planted ones it did not find (valid by construction;
    # dense seeding misses a few next to the near-root clusters of these tuples)
    planted_bf = match_paths(np.arange(n), d["uv"], d["bf_t"], d["bf_uv"]) >= 0
    extra = np.flatnonzero(~planted_bf)
    truth_t = np.concatenate([d["bf_t"][required], extra])
    truth_uv = np.concatenate([d["bf_uv"][required], d["uv"][extra]])
    m = match_paths(truth_t, truth_uv, ti, uv)
    miss = np.flatnonzero(m < 0)
    print(f"\n[grazing] tuples={n} brute-force paths={len(d['bf_t'])} required={int(required.sum())} "
          f"+ planted paths the brute force missed={len(extra)}: missed={len(miss)} of {len(truth_t)} "
          f"(recall {1 - len(miss) / max(1, len(truth_t)):.6f}) solver paths={len(ti)} false={int((~chk.valid).sum())}")
    assert planted_bf.mean() > 0.99  # the reference itself sees the planted paths
    assert len(truth_t) >= 10_000
    assert chk.valid.all()
    assert len(miss) <= int(np.floor((1 - RECALL_MIN) * len(truth_t))), (
        f"{len(miss)} missed: " + "; ".join(f"tuple {truth_t[k]} uv {truth_uv[k].tolist()}" for k in miss[:5]))


def test_fold_probe_is_abandoned_on_its_way_back():
    """The fold probe's polish (one_vertex.polish_validate_normal_matrix with a known path) stops
    once a step would take it back within return_radius of the known path, reporting RETURNED; polished
    without one from the same start, it converges onto that path.  The grazing tuples' near-critical
    partner paths, which only the probes find, are still found (test above, and the brute-force
    recall test)."""
    from addon.solver.paths.one_vertex import RETURNED, polish_validate_normal_matrix, triangle_frame, geometric_normal

    d = make_grazing(2_000)
    checked = 0
    for t in range(len(d["x0"])):
        p0, e1, e2, n0, m1, m2 = triangle_frame(d["P"][t, 0], d["N"][t, 0])
        ng, _ = geometric_normal(e1, e2)
        u, v = d["uv"][t]
        if min(u, v, 1.0 - u - v) < 0.01:
            continue
        args = (tuple(d["x0"][t]), tuple(d["x2"][t]), p0, e1, e2, n0, m1, m2, ng, True, float(d["eta"][t]), 40, 1e-12)
        ok, pu, pv, err, _, _, _, _ = polish_validate_normal_matrix(u, v, *args, np.inf)
        if not ok:
            continue
        start = (pu + 1e-4, pv - 1e-4)
        full = polish_validate_normal_matrix(*start, *args, np.inf)
        probe = polish_validate_normal_matrix(*start, *args, np.inf, pu, pv, 0.25e-4)
        if full[0] and max(abs(full[1] - pu), abs(full[2] - pv)) < 1e-9:
            assert not probe[0] and probe[3] == RETURNED, (t, probe)
            checked += 1
    assert checked > 500
