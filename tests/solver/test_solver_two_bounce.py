"""Two-bounce Specular Polynomials (chains RR, RT, TR, TT) against independent references.

Ground truth: tests/reference/bruteforce.py (dense seeds on both triangles, Levenberg-Marquardt on
eq. (3) at both vertices, every side assignment of the refracting vertices, deflation; validated by
the independent contract check ``check_path``).  Tuples: tests/reference/two_bounce_data.py (planted paths
through both triangles with tilted or sphere-like normal fields, random triangle pairs).

Tuple counts.  Per tuple, on this 2-core machine: brute force ~15 ms (RR) to ~120 ms (TT), the
solver ~1 ms (RR) to ~50 ms (TT, planted).  The default run uses ``TWO_BOUNCE_TUPLES`` = 300 tuples
per chain: ~2-5 min for the whole file, ~70 s of it compiling the kernels on an empty Numba cache.
The acceptance run of the issue (>= 10,000 per chain) is

    TWO_BOUNCE_TUPLES=10000 .venv/bin/python -m pytest tests/solver/test_solver_two_bounce.py -s

(about 1 h on 2 cores, the brute force dominating; bench/two_bounce_recall.py runs one chain of it
from a brute force cached once and lists the misses; its recall per chain, with the test's
margins, is in docs/perf-log.md).

Asserts: contract output format, no NaN, zero false paths (check_path, direction tolerance 1e-6, both
vertices, sides, inside both triangles), no duplicates, recall of the brute-force paths that are
inside by >= 1e-7, not grazing (cos_i >= 1e-4), not next to TIR (k >= 1e-6) and not ill-conditioned
(sigma_min >= 1e-5): >= RECALL_MIN[chain].  Plus: the √ fit's error, the path-space Jacobian, the
flat glass slab (TT) against the analytic exit point / lateral shift / irradiance, the two-bounce
geometry term against finite differences of a traced map, and degenerate / grazing / near-TIR tuples
(no NaN, no crash, no false path).
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from fixtures.marks import slow_cases
from reference import bruteforce as bf
from reference.two_bounce_data import plant_two_bounce
from reference.truth_two_bounce import (DUP_TOL, FALSE_TOL, GRAZE_MARGIN, RECALL_MARGIN, SEED,
                                        SIGMA_MARGIN, TIR_MARGIN, dataset_with_truth, match_paths)

CHAINS = ("RR", "RT", "TR", "TT")
# The issue asks 99.9 % (RR, RT, TR) and 99 % (TT).
ISSUE_RECALL = {"RR": 0.999, "RT": 0.999, "TR": 0.999, "TT": 0.99}
RECALL_MIN = dict(ISSUE_RECALL)


def _api():
    from addon.solver import path_irradiance, solve_tuples

    return solve_tuples, path_irradiance


def _describe(d, t, extra=""):
    return (f"--- tuple {t} ({d['cat'][t]}) {extra}\nchain={d['chain']!r}\nx_start=np.array([{d['x0'][t].tolist()!r}])\n"
            f"x_end=np.array([{d['x3'][t].tolist()!r}])\nP=np.array([{d['P'][t].tolist()!r}])\n"
            f"N=np.array([{d['N'][t].tolist()!r}])\neta={float(d['eta'][t])!r}\n")


# ------------------------------------------------------------------------------------------------
def _sylvester_slogdet(F, G):
    """numpy's slogdet of the Sylvester matrix of f, g (ascending coefficient vectors): the
    resultant, computed independently of det_bezout's matrix and elimination."""
    f, g = np.trim_zeros(F, "b")[::-1], np.trim_zeros(G, "b")[::-1]
    n, m = len(f) - 1, len(g) - 1
    S = np.zeros((n + m, n + m))
    for r in range(m):
        S[r, r:r + n + 1] = f
    for r in range(n):
        S[m + r, r:r + m + 1] = g
    return np.linalg.slogdet(S)


@pytest.mark.parametrize("m,n", [(0, 9), (1, 12), (8, 34), (12, 34), (16, 46), (16, 16), (5, 5), (16, 20)])
def test_det_bezout_is_the_resultant(m, n):
    """det_bezout (the hybrid Bézout matrix of eq 29, Bézoutian rows by their recurrence,
    the sliding-window elimination) against numpy's LU of the Sylvester matrix, on random
    polynomial pairs with coefficients graded over 8 orders of magnitude: the same log|det|
    and a sign that differs from the Sylvester determinant's by one constant per (m, n);
    the dense elimination of the full matrix gives the same numbers bit for bit."""
    from addon.solver.spoly.two_bounce.params import MAXD
    from addon.solver.spoly.two_bounce.resultant import det_bezout, det_hybrid_dense, det_hybrid_window, v_major

    rng = np.random.default_rng([m, n])
    ratio = set()
    for trial in range(40):
        A = np.zeros((MAXD + 1, MAXD + 1))
        B = np.zeros((MAXD + 1, MAXD + 1))
        A[:m + 1, 0] = rng.normal(size=m + 1) * 10.0 ** rng.uniform(-8, 0, m + 1)
        B[:n + 1, 0] = rng.normal(size=n + 1) * 10.0 ** rng.uniform(-8, 0, n + 1)
        cf = np.zeros((2, MAXD + 2))
        mat = np.zeros((MAXD, MAXD))
        At, Bt = np.zeros_like(A), np.zeros_like(B)
        v_major(A, m, At)
        v_major(B, n, Bt)
        sign, logdet = det_bezout(At, m, Bt, n, n, 0.5, cf, mat)  # constant in v: a(u), b(u)
        F = B[:n + 1, 0] / np.abs(B[:n + 1, 0]).max()
        G = A[:m + 1, 0] / np.abs(A[:m + 1, 0]).max()
        s_ref, l_ref = _sylvester_slogdet(F, G)
        assert sign != 0 and s_ref != 0
        assert abs(logdet - l_ref) <= 1e-9 * max(1.0, abs(l_ref)), (trial, logdet, l_ref)
        ratio.add(int(sign * s_ref))
        if m > 0:
            Fw, Gw = np.zeros(MAXD + 2), np.zeros(MAXD + 2)
            Fw[:n + 1], Gw[:m + 1] = F, G
            dense = det_hybrid_dense(Fw.copy(), Gw, n, m, np.zeros(MAXD + 2), np.zeros((MAXD, MAXD)))
            window = det_hybrid_window(Fw.copy(), Gw, n, m, np.zeros((MAXD, MAXD)))
            assert dense == window, (trial, dense, window)
    assert len(ratio) == 1


@pytest.mark.parametrize("m,n", [(8, 15), (8, 22), (16, 31), (12, 34), (16, 46)])
def test_det_bezout_depends_on_v_as_the_resultant(m, n):
    """det_bezout on bivariate a(u, v), b(u, v) of total degrees (m, n) (the chains' systems),
    read v-major (``v_major``): at random v the same log|det| as numpy's LU of the Sylvester
    matrix of the coefficient vectors a_i(v), b_i(v) evaluated here with numpy's polyval,
    and a sign that differs from the Sylvester determinant's by one constant per (m, n) —
    the layout, the Horner in v and the elimination against an independent evaluation."""
    from addon.solver.spoly.two_bounce.params import MAXD
    from addon.solver.spoly.two_bounce.resultant import det_bezout, v_major

    rng = np.random.default_rng([m, n, 1])
    ratio = set()
    for trial in range(30):
        A = np.zeros((MAXD + 1, MAXD + 1))
        B = np.zeros((MAXD + 1, MAXD + 1))
        for P, d in ((A, m), (B, n)):
            for i in range(d + 1):
                P[i, :d + 1 - i] = rng.normal(size=d + 1 - i) * 10.0 ** rng.uniform(-4, 0, d + 1 - i)
            P[:, :] = np.where(np.add.outer(np.arange(MAXD + 1), np.arange(MAXD + 1)) <= d, P, 0.0)
        At, Bt = np.zeros_like(A), np.zeros_like(B)
        v_major(A, m, At)
        v_major(B, n, Bt)
        v = float(rng.uniform(-0.02, 1.02))
        sign, logdet = det_bezout(At, m, Bt, n, n, v, np.zeros((2, MAXD + 2)), np.zeros((MAXD, MAXD)))
        G = np.array([np.polyval(A[i, :m + 1 - i][::-1], v) for i in range(m + 1)])
        F = np.array([np.polyval(B[i, :n + 1 - i][::-1], v) for i in range(n + 1)])
        s_ref, l_ref = _sylvester_slogdet(F / np.abs(F).max(), G / np.abs(G).max())
        assert sign != 0 and s_ref != 0
        assert abs(logdet - l_ref) <= 1e-8 * max(1.0, abs(l_ref)), (trial, v, logdet, l_ref)
        ratio.add(int(sign * s_ref))
    assert len(ratio) == 1


def test_sqrt_fit():
    """The piecewise rational √ (eq 23) errs by < 1e-4 on [0, 1], including next to 0."""
    from addon.solver.spoly.two_bounce.params import SQRT_PIECES
    from addon.solver.spoly.two_bounce.sqrt import sqrt_approx

    x = np.unique(np.concatenate([[0.0], np.logspace(-300, 0, 20001), np.linspace(0, 1, 200001),
                                  SQRT_PIECES[:, 0], SQRT_PIECES[:, 1],
                                  np.nextafter(SQRT_PIECES[:, 1], 0), np.nextafter(SQRT_PIECES[:, 1], 2)]))
    x = x[(x >= 0) & (x <= 1)]
    approx = np.array([sqrt_approx(v) for v in x])
    err = np.abs(approx - np.sqrt(x))
    print(f"\n[sqrt fit] {len(SQRT_PIECES)} pieces; max |error| {err.max():.3g} at x={x[np.argmax(err)]:.3g}; at 0: {err[0]:.3g}")
    assert err.max() < 1e-4
    assert np.all(np.diff(SQRT_PIECES[:, 0]) > 0) and SQRT_PIECES[0, 0] == 0.0 and SQRT_PIECES[-1, 1] == 1.0
    assert np.all(SQRT_PIECES[1:, 0] == SQRT_PIECES[:-1, 1])


def test_heron_sqrt_fit():
    """The one-system √ (``heron_sqrt_fit`` at the cut ``heron_sqrt_cut`` picks): where the
    fit is accepted, the Heron step (β + q²) / (2q) errs by at most ~HERON_TOL relative to √β
    at random points of the widened triangle with β/S² above the cut (the check grid is
    finite: 3x slack), the cut is the first of HERON_CUTS where the fit is accepted, and the
    TT system built with it has total degrees (12, 34) instead of the √ pieces' (16, 46)."""
    from addon.solver.spoly.two_bounce.params import HERON_CUTS, HERON_TOL, MAXD, N_SLOTS, V_MARGIN_APPROX
    from addon.solver.spoly.two_bounce.sqrt import beta_local, heron_sqrt_cut, heron_sqrt_fit
    from addon.solver.spoly.two_bounce.system import build_system

    rng = np.random.default_rng(7)
    accepted = 0
    above_first = 0
    worst = 0.0
    m = V_MARGIN_APPROX
    for _ in range(200):
        geo_l = np.zeros((13, 3))
        geo_l[2], geo_l[3] = rng.normal(size=3), rng.normal(size=3)  # e11, e12 (p10 at the origin)
        ng = np.cross(geo_l[2], geo_l[3])
        ng /= np.linalg.norm(ng)
        nc = ng + 0.3 * rng.normal(size=(3, 3))  # shading normals at the corners
        geo_l[4], geo_l[5], geo_l[6] = nc[0], nc[1] - nc[0], nc[2] - nc[0]
        geo_l[0] = (geo_l[2] + geo_l[3]) / 3 + ng * rng.uniform(1.0, 4.0) + rng.normal(size=3)  # x0
        geo_l[7] = ng * -2.0 + rng.normal(size=3)  # p20, e21, e22, n20 (for the degrees only)
        geo_l[8], geo_l[9] = rng.normal(size=3), rng.normal(size=3)
        geo_l[10] = -ng
        geo_l[11], geo_l[12] = 0.1 * rng.normal(size=3), 0.1 * rng.normal(size=3)
        r = 1 / 1.5
        S2 = max(np.sum(nc ** 2, 1)) * max(np.sum((np.array([[0, 0, 0], geo_l[2], geo_l[3]]) - geo_l[0]) ** 2, 1))
        ok, cut, c = heron_sqrt_cut(geo_l, r, m, S2, np.zeros((6, 7)))
        first_ok = [heron_sqrt_fit(geo_l, r, m, S2, k, np.zeros((6, 7)))[0] for k in HERON_CUTS]
        assert ok == any(first_ok)
        if not ok:
            continue
        assert cut == HERON_CUTS[first_ok.index(True)]
        accepted += 1
        above_first += cut > HERON_CUTS[0]
        uv = rng.uniform(-m, 1 + 2 * m, size=(400, 2))
        uv = uv[uv.sum(1) <= 1 + m]
        for u, v in uv:
            beta = beta_local(u, v, geo_l, r)
            if beta < cut * S2:
                continue
            q = c[0] + u * c[1] + v * c[2] + u * u * c[3] + u * v * c[4] + v * v * c[5]
            worst = max(worst, abs((beta + q * q) / (2 * q) / np.sqrt(beta) - 1))
        if accepted == 1:
            biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
            c2 = np.cross(geo_l[0], ng)
            c2 = tuple(c2 / np.linalg.norm(c2))  # a 3-tuple, as tuple_frame returns it
            heron_deg = build_system(True, True, 1.0, r, -1, np.sqrt(S2), c, 1.5, 1.0, False, c2, geo_l, biv)
            piece_deg = build_system(True, True, 1.0, r, 12, np.sqrt(S2), c, 1.5, 1.0, False, c2, geo_l, biv)
            assert heron_deg == (12, 34) and piece_deg == (16, 46)
    print(f"\n[heron sqrt] accepted {accepted}/200 configurations ({above_first} above the first cut); worst relative "
          f"error {worst:.3g} (HERON_TOL {HERON_TOL})")
    assert accepted >= 50
    assert worst <= 3 * HERON_TOL


def _poly_from_factors(factors):
    """Triangular power-basis array p[i, j] (u^i v^j) of a product of (c, cu, cv) linear factors."""
    p = np.zeros((48, 48))
    p[0, 0] = 1.0
    d = 0
    for c, cu, cv in factors:
        q = np.zeros_like(p)
        q[:d + 1, :d + 1] += c * p[:d + 1, :d + 1]
        q[1:d + 2, :d + 1] += cu * p[:d + 1, :d + 1]
        q[:d + 1, 1:d + 2] += cv * p[:d + 1, :d + 1]
        p, d = q, d + 1
    return p / np.abs(p).max(), d


def test_live_prepass():
    """The pre-pass that keeps the scan pieces where a and b can vanish together
    (``live_pieces``): its tensor Bernstein form equals the polynomial (evaluated directly)
    at degree 46, and on systems with known common zeros (products of lines) every piece
    holding a common zero inside the triangle is kept, few others are, and a system whose
    common zeros all lie outside the triangle keeps none."""
    from math import comb

    from addon.solver.spoly.two_bounce.params import (LIVE_DEPTH, LIVE_DEPTH_LOW, LIVE_LOW_DEGREE, LIVE_STACK,
                                                      MAX_PIECES, MAXD, N_SLOTS, V_MARGIN_APPROX)
    from addon.solver.spoly.two_bounce.prepass import binomial_ratios, live_pieces, tensor_bernstein

    rng = np.random.default_rng(3)
    biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
    # 1. the Bernstein form of a random degree-46 polynomial over [-m, 1 + m]²
    d = 46
    p = np.zeros((48, 48))
    for i in range(d + 1):
        p[i, :d + 1 - i] = rng.normal(size=d + 1 - i)
    m = V_MARGIN_APPROX
    R = np.zeros((48, 48))
    out = np.zeros((48, 48))
    binomial_ratios(d, R)
    tensor_bernstein(p, d, -m, 1 + 2 * m, R, out, np.zeros((48, 48)), np.zeros((48, 48)))
    worst = 0.0
    for s, t in rng.random((6, 2)):
        bs = np.array([comb(d, k) * s ** k * (1 - s) ** (d - k) for k in range(d + 1)])
        bt = np.array([comb(d, k) * t ** k * (1 - t) ** (d - k) for k in range(d + 1)])
        u, v = -m + (1 + 2 * m) * s, -m + (1 + 2 * m) * t
        direct = sum(p[i, j] * u ** i * v ** j for i in range(d + 1) for j in range(d + 1 - i))
        worst = max(worst, abs(bs @ out[:d + 1, :d + 1] @ bt - direct) / np.abs(p).sum())
    assert worst < 1e-13

    # 2. known common zeros of products of lines (a's and b's lines crossing)
    pieces = 100
    boxes = np.zeros((LIVE_STACK, 4))
    live = np.zeros(MAX_PIECES + 1)
    h = (1 + 2 * m) / pieces
    cases = [
        # (a factors, b factors (b of degree > 16 for the deep pre-pass), common zeros (u, v))
        ([(-0.3, 1, 0)], [(-0.6, 0, 1)] + [(2.0, 0.3, 0.1)] * 16, [(0.3, 0.6)]),
        ([(-0.3, 1, 0), (-0.45, 1, 1)] + [(1.5, 0.2, -0.1)] * 4, [(-0.6, 0, 1), (0.1, 2, -1)] + [(3.0, -1, 0.5)] * 25,
         [(0.3, 0.6), (0.3, 0.7), (-0.15, 0.6), (0.35 / 3, 0.1 + 0.7 / 3)]),
    ]
    for fa, fb, zeros in cases:
        a, da = _poly_from_factors(fa)
        b, db = _poly_from_factors(fb)
        n_live = live_pieces(a, da, b, db, m, pieces, biv, boxes, live)
        for u, v in zeros:
            if -m <= u and -m <= v <= 1 + m and u + v <= 1 + m:
                k = int((v + m) / h)
                assert live[k] == 1, (u, v, k)
        inside = sum(1 for u, v in zeros if -m <= u and -m <= v and u + v <= 1 + m)
        # around a crossing the leaves that hold both lines span at most 3 leaves in v (plus
        # one piece each side): the rest of the range is not scanned
        leaf = (1 + 2 * m) / 2 ** (LIVE_DEPTH_LOW if db <= LIVE_LOW_DEGREE else LIVE_DEPTH)
        print(f"[live pre-pass] {inside} common zeros inside: {n_live} of {pieces} pieces live")
        assert 0 < n_live <= inside * (3 * leaf / h + 3) and n_live == int(live[:pieces].sum())
    # 3. common zeros only outside the triangle: a = u - 0.9, b = v - 0.8 (u + v = 1.7)
    a, da = _poly_from_factors([(-0.9, 1, 0)] + [(1.5, 0.1, 0.2)] * 5)
    b, db = _poly_from_factors([(-0.8, 0, 1)] + [(2.0, 0.3, 0.1)] * 20)
    assert live_pieces(a, da, b, db, m, pieces, biv, boxes, live) == 0


@pytest.mark.slow
@pytest.mark.parametrize("refract1", [False, True])
def test_prepass_hit_test(refract1):
    """The pre-pass's test that a box of (u1, v1) cannot reach triangle 2 (``misses_second``,
    on the map x1 -> x2 of eq 14-17 that ``build_system`` stores): at 12 x 12 points of every
    box it drops, the exact scattered ray (numpy, exact √ for refraction) either points away
    from triangle 2's plane or meets it outside triangle 2 widened by the margin — the whole
    margin for the exact reflected map, half of it for the √-approximated refracted one (the
    rest is the approximation's allowance) — and it drops a good share of boxes of random
    configurations (not vacuous)."""
    from addon.solver.spoly.two_bounce.params import (HIT_MARGIN_APPROX, HIT_MARGIN_EXACT, MAXD, N_SLOTS,
                                                      V_MARGIN_APPROX, V_MARGIN_EXACT)
    from addon.solver.spoly.two_bounce.prepass import misses_second
    from addon.solver.spoly.two_bounce.sqrt import heron_sqrt_cut
    from addon.solver.spoly.two_bounce.system import build_system

    rng = np.random.default_rng(11)
    m = V_MARGIN_APPROX if refract1 else V_MARGIN_EXACT
    margin2 = HIT_MARGIN_APPROX if refract1 else HIT_MARGIN_EXACT
    allowed = 0.5 * margin2 if refract1 else margin2 - 1e-9
    dropped = tested = configs = 0
    for _ in range(60):
        geo_l = np.zeros((13, 3))
        geo_l[2], geo_l[3] = rng.normal(size=3), rng.normal(size=3)
        ng = np.cross(geo_l[2], geo_l[3])
        ng /= np.linalg.norm(ng)
        nc = ng + 0.3 * rng.normal(size=(3, 3))
        geo_l[4], geo_l[5], geo_l[6] = nc[0], nc[1] - nc[0], nc[2] - nc[0]
        geo_l[0] = (geo_l[2] + geo_l[3]) / 3 + ng * rng.uniform(1.0, 4.0) + rng.normal(size=3)  # x0
        geo_l[1] = rng.normal(size=3) * 3  # x3
        side = -1.0 if refract1 else 1.0  # triangle 2 on the far side for refraction, the near side for reflection
        geo_l[7] = ng * side * rng.uniform(0.5, 3.0) + rng.normal(size=3)
        geo_l[8], geo_l[9] = rng.normal(size=3), rng.normal(size=3)
        geo_l[10] = rng.normal(size=3)
        r = 1 / 1.5
        S2 = max(np.sum(nc ** 2, 1)) * max(np.sum((np.array([[0, 0, 0], geo_l[2], geo_l[3]]) - geo_l[0]) ** 2, 1))
        heron = (0.0,) * 6
        piece = 0
        if refract1:
            ok, cut, heron = heron_sqrt_cut(geo_l, r, m, S2, np.zeros((6, 7)))
            if not ok:
                continue
            piece = -1
        biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
        c2 = np.cross(geo_l[1], geo_l[10])
        c2 = tuple(c2 / np.linalg.norm(c2))  # a 3-tuple, as tuple_frame returns it
        build_system(refract1, False, 1.0, r, piece, np.sqrt(S2), heron, 1.0, 1.0, True, c2, geo_l, biv)
        configs += 1
        e21, e22, p20 = geo_l[8], geo_l[9], geo_l[7]
        for level in (1, 2, 3):
            w = (1 + 2 * m) / 2 ** level
            for iu in range(2 ** level):
                for iv in range(2 ** level - iu):
                    u0, v0 = -m + iu * w, -m + iv * w
                    tested += 1
                    if not misses_second(biv, u0, v0, w, (0.0, 0.0, 0.0, 0.0)):
                        continue
                    dropped += 1
                    for u in np.linspace(u0, u0 + w, 12):
                        for v in np.linspace(v0, v0 + w, 12):
                            x1 = u * geo_l[2] + v * geo_l[3]
                            n = geo_l[4] + u * geo_l[5] + v * geo_l[6]
                            d0 = x1 - geo_l[0]
                            if refract1:
                                beta = (n @ n) * (d0 @ d0) * (1 - r * r) + r * r * (d0 @ n) ** 2
                                if beta < 0:
                                    continue  # total internal reflection: no ray at all
                                d = r * (d0 * (n @ n) - (d0 @ n) * n) - np.sqrt(beta) * n
                            else:
                                d = -2 * (d0 @ n) * n + d0 * (n @ n)
                            # Möller-Trumbore against triangle 2's plane
                            pv = np.cross(d, e22)
                            det = pv @ e21
                            if abs(det) < 1e-12 * np.linalg.norm(d) * np.linalg.norm(e21) * np.linalg.norm(e22):
                                continue
                            tv = x1 - p20
                            u2 = (tv @ pv) / det
                            qv = np.cross(tv, e21)
                            v2 = (d @ qv) / det
                            t = (e22 @ qv) / det
                            hits = t > 0 and u2 >= -allowed and v2 >= -allowed and u2 + v2 <= 1 + allowed
                            assert not hits, (u0, v0, w, u, v, u2, v2, t)
    print(f"\n[pre-pass hit test] refract1={refract1}: {dropped} of {tested} boxes of {configs} configurations dropped")
    assert configs >= 30
    assert dropped >= 0.2 * tested


@pytest.mark.parametrize("chain", CHAINS)
def test_path_space_jacobian(chain):
    """Analytic Jacobian of the two-vertex residual against central differences."""
    from addon.solver.paths import two_vertex as ps

    rng = np.random.default_rng([SEED, 3, ord(chain[0]), ord(chain[1])])
    d = plant_two_bounce(rng, chain, 60)
    geo = np.zeros((15, 3))
    work = np.zeros((24, 6))  # the residual's scratch rows, laid out as in polish_and_validate2
    res, r2 = work[0], work[1]
    jac, j2 = work[2:8, 0:4], work[8:14, 0:4]
    worst = 0.0
    checked = 0
    for i in range(60):
        ps.pack_geometry(d["x0"][i], d["x3"][i], d["P"][i, 0], d["N"][i, 0], d["P"][i, 1], d["N"][i, 1], geo)
        th = d["uv"][i] + rng.uniform(-1e-3, 1e-3, 4)
        if not ps.two_vertex_residual(th, geo, chain[0] == "T", chain[1] == "T", d["eta"][i], res, jac):
            continue
        fd = np.zeros((6, 4))
        ok = True
        for p in range(4):
            cols = []
            for sgn in (1.0, -1.0):
                t = th.copy()
                t[p] += sgn * 1e-7
                ok &= ps.two_vertex_residual(t, geo, chain[0] == "T", chain[1] == "T", d["eta"][i], r2, j2)
                cols.append(r2.copy())
            fd[:, p] = (cols[0] - cols[1]) / 2e-7
        if ok:
            worst = max(worst, np.abs(fd - jac).max() / max(1.0, np.abs(jac).max()))
            checked += 1
    print(f"\n[{chain}] Jacobian vs finite differences: {checked} points, max rel err {worst:.3g}")
    assert checked >= 50 and worst < 1e-5


# Measured at the default 100 pieces (300 tuples per chain, this file's data): RR, RT, TR 100 %,
# TT 99.19 % (2 of 248 missed: their √-approximated systems have no real root near the path, a
# near-tangent pair made complex by the √ error; the padded Bézout's sign noise used to find both
# by chance, and missed another).  At 10,000 per chain see the module docstring.
@pytest.mark.parametrize("chain", slow_cases(CHAINS, {"RT", "TR", "TT"}))
def test_solver_against_bruteforce(chain):
    solve_tuples, _ = _api()
    d = dataset_with_truth(chain)
    n = len(d["x0"])
    t = time.time()
    ti, uv = solve_tuples(chain, d["x0"], d["x3"], d["P"], d["N"], d["eta"])
    t_solve = time.time() - t
    assert ti.dtype == np.int64 and uv.dtype == np.float64 and uv.shape == (len(ti), 4)
    assert np.isfinite(uv).all()
    assert (np.diff(ti) >= 0).all()
    chk = bf.check_path(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv, tol=FALSE_TOL)
    false = np.flatnonzero(~chk.valid)
    # duplicates: two rows of one tuple at the same root (after the reference polish)
    pol = bf.polish(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv) if len(ti) else uv
    dup = []
    bounds = np.flatnonzero(np.diff(ti)) + 1
    for s_, e_ in zip(np.r_[0, bounds], np.r_[bounds, len(ti)]):
        for a in range(s_, e_):
            for b in range(a + 1, e_):
                if np.abs(pol[a] - pol[b]).max() < DUP_TOL:
                    dup.append((a, b))
    bchk = d["bf_chk"]
    required = ((bchk.inside_margin >= RECALL_MARGIN) & (bchk.cos_i >= GRAZE_MARGIN) & (bchk.k_min >= TIR_MARGIN)
                & (d["bf_sigma"] >= SIGMA_MARGIN))
    m = match_paths(d["bf_t"], d["bf_uv"], ti, uv)
    miss = np.flatnonzero(required & (m < 0))
    recall = 1.0 - len(miss) / max(1, int(required.sum()))
    planted = np.flatnonzero(np.isfinite(d["uv"][:, 0]))
    mp = match_paths(planted, d["uv"][planted], ti, uv)
    print(f"\n[{chain}] {n} tuples: solve {t_solve:.2f}s ({1e6 * t_solve / n:.0f} µs/tuple incl. compile on first use), "
          f"brute force {d['t_bf']:.1f}s; solver paths {len(ti)}, brute-force paths {len(d['bf_t'])} "
          f"(required {int(required.sum())}); recall {recall:.5f} ({len(miss)} missed); planted recall "
          f"{(mp >= 0).mean():.5f}; false {len(false)}; duplicates {len(dup)}; "
          f"not-required misses {int((~required & (m < 0)).sum())}/{int((~required).sum())}")
    msgs = []
    for r in false[:3]:
        msgs.append(_describe(d, ti[r], f"FALSE uv={uv[r].tolist()!r}: {chk.reason[r]} residual {chk.residual[r]:.3g}"))
    for a, b in dup[:3]:
        msgs.append(_describe(d, ti[a], f"DUPLICATE rows {uv[a].tolist()!r} / {uv[b].tolist()!r}"))
    if recall < RECALL_MIN[chain]:
        for b in miss[:3]:
            tt = d["bf_t"][b]
            msgs.append(_describe(d, tt, f"MISSED uv={d['bf_uv'][b].tolist()!r} sigma={d['bf_sigma'][b]:.3g}; "
                                         f"solver: {uv[ti == tt].tolist()!r}"))
    assert len(false) == 0 and len(dup) == 0 and recall >= RECALL_MIN[chain], "\n".join(msgs)
    assert required.sum() >= 0.8 * (n // 2)


# ------------------------------------------------------------------------------------------------
def _slab(n, rng, eta=1.5):
    """A glass slab z in [-t, 0] (two big flat triangles, outward normals +z on top, -z below);
    light above, receiver below, off-axis."""
    t = rng.uniform(0.2, 2.0, n)
    big = 50.0
    top = np.array([[-big, -big, 0.0], [3 * big, -big, 0.0], [-big, 3 * big, 0.0]])
    P = np.zeros((n, 2, 3, 3))
    N = np.zeros((n, 2, 3, 3))
    P[:, 0] = top
    P[:, 1] = top[[0, 2, 1]]  # reversed winding: its geometric normal points down
    P[:, 1, :, 2] = -t[:, None]
    N[:, 0] = [0, 0, 1.0]
    N[:, 1] = [0, 0, -1.0]
    h0 = rng.uniform(0.5, 5.0, n)
    h3 = rng.uniform(0.5, 5.0, n)
    rho = rng.uniform(0.1, 8.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    x0 = np.stack([np.zeros(n), np.zeros(n), h0], 1) + rng.uniform(-3, 3, (n, 1)) * [1.0, 1.0, 0.0]
    x3 = x0 + np.stack([rho * np.cos(phi), rho * np.sin(phi), -(h0 + t + h3)], 1)
    return dict(x0=x0, x3=x3, P=P, N=N, eta=np.full(n, eta), t=t, h0=h0, h3=h3, rho=rho)


def _slab_angle(rho, h0, h3, t, eta):
    """Incidence angle θ0 with rho = (h0 + h3) tan θ0 + t tan θ1, sin θ0 = eta sin θ1 (bisection)."""
    lo = np.zeros_like(rho)
    hi = np.full_like(rho, np.pi / 2 - 1e-12)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        s1 = np.sin(mid) / eta
        f = (h0 + h3) * np.tan(mid) + t * s1 / np.sqrt(1 - s1 * s1) - rho
        lo = np.where(f < 0, mid, lo)
        hi = np.where(f < 0, hi, mid)
    return 0.5 * (lo + hi)


def test_slab_tt_analytic():
    solve_tuples, path_irradiance = _api()
    rng = np.random.default_rng([SEED, 11])
    n = 200
    eta = 1.5
    d = _slab(n, rng, eta)
    ti, uv = solve_tuples("TT", d["x0"], d["x3"], d["P"], d["N"], eta)
    assert np.array_equal(ti, np.arange(n)), "exactly one path per tuple through a slab"
    th0 = _slab_angle(d["rho"], d["h0"], d["h3"], d["t"], eta)
    th1 = np.arcsin(np.sin(th0) / eta)
    horiz = (d["x3"] - d["x0"]) * [1.0, 1.0, 0.0]
    horiz /= np.linalg.norm(horiz, axis=1, keepdims=True)
    x1_ref = d["x0"] + horiz * (d["h0"] * np.tan(th0))[:, None] - [0, 0, 1.0] * d["h0"][:, None]
    x2_ref = x1_ref + horiz * (d["t"] * np.tan(th1))[:, None] - [0, 0, 1.0] * d["t"][:, None]
    X = bf._vertex_points(d["P"], uv)
    e1 = np.abs(X[:, 0] - x1_ref).max()
    e2 = np.abs(X[:, 1] - x2_ref).max()
    # lateral shift: distance between the incident ray's line and the emergent ray
    w_in, _ = bf._unit(X[:, 0] - d["x0"])
    w_out, _ = bf._unit(d["x3"] - X[:, 1])
    q = X[:, 1] - d["x0"]
    shift = np.linalg.norm(q - w_in * np.sum(q * w_in, 1, keepdims=True), axis=1)
    shift_ref = d["t"] * np.sin(th0 - th1) / np.cos(th1)
    # irradiance: dΩ/dA⊥ = sin θ0 / (ρ ρ'(θ0) cos θ0), Fresnel T(1->η, θ0) T(η->1, θ1)
    drho = (d["h0"] + d["h3"]) / np.cos(th0) ** 2 + d["t"] * np.cos(th0) / (eta * np.cos(th1) ** 3)
    G_ref = np.sin(th0) / (d["rho"] * drho * np.cos(th0))
    F_ref = (1 - bf.fresnel_dielectric(np.cos(th0), 1.0, eta)) * (1 - bf.fresnel_dielectric(np.cos(th1), eta, 1.0))
    out = path_irradiance("TT", d["x0"], d["x3"], d["P"], d["N"], eta, ti, uv)
    g_rel = np.abs(np.asarray(out.geometry) / G_ref - 1).max()
    f_abs = np.abs(np.asarray(out.fresnel) - F_ref).max()
    i_rel = np.abs(np.asarray(out.irradiance) / (G_ref * F_ref) - 1).max()
    print(f"\n[slab TT] x1 err {e1:.3g}, exit point err {e2:.3g}, parallel emergent ray "
          f"{np.abs(w_out - w_in).max():.3g}, lateral shift err {np.abs(shift - shift_ref).max():.3g}; "
          f"geometry rel err {g_rel:.3g}, Fresnel err {f_abs:.3g}, irradiance rel err {i_rel:.3g}")
    assert e1 < 1e-9 and e2 < 1e-9
    assert np.abs(w_out - w_in).max() < 1e-9
    assert np.abs(shift - shift_ref).max() < 1e-9
    assert g_rel < 1e-6 and f_abs < 1e-12 and i_rel < 1e-6


def test_slab_on_axis():
    """Light and receiver on the slab's normal through it: the straight path (a degenerate,
    identically vanishing resultant) is still found; irradiance = 1/(h0 + h3 + t/η)² T²."""
    solve_tuples, path_irradiance = _api()
    rng = np.random.default_rng([SEED, 12])
    d = _slab(20, rng)
    d["x3"] = d["x0"] - np.stack([np.zeros(20), np.zeros(20), d["h0"] + d["t"] + d["h3"]], 1)
    ti, uv = solve_tuples("TT", d["x0"], d["x3"], d["P"], d["N"], 1.5)
    assert np.array_equal(ti, np.arange(20))
    out = path_irradiance("TT", d["x0"], d["x3"], d["P"], d["N"], 1.5, ti, uv)
    T = 1 - bf.fresnel_dielectric(1.0, 1.0, 1.5)
    ref = T * T / (d["h0"] + d["h3"] + d["t"] / 1.5) ** 2
    assert np.abs(np.asarray(out.irradiance) / ref - 1).max() < 1e-6


# ------------------------------------------------------------------------------------------------
def _trace_two(x0, direction, P, N, eta, chain, plane_point, plane_normal):
    """Reference forward trace through both (extended) triangle planes to a receiver plane."""
    big_n = np.cross(P[:, 1, 1] - P[:, 1, 0], P[:, 1, 2] - P[:, 1, 0])
    first = bf.trace_one_bounce(x0, direction, P[:, 0], N[:, 0], eta, chain[0], P[:, 1, 0], big_n)
    # start the second leg at x1 (starting on plane 2 itself would leave the incoming side undefined)
    second = bf.trace_one_bounce(first["x1"], first["wo"], P[:, 1], N[:, 1], eta, chain[1], plane_point, plane_normal)
    return second["hit"], first["ok"] & second["ok"]


@pytest.mark.parametrize("chain", CHAINS)
def test_geometry_term_finite_differences(chain):
    solve_tuples, path_irradiance = _api()
    rng = np.random.default_rng([SEED, 5, ord(chain[0]), ord(chain[1])])
    d = plant_two_bounce(rng, chain, 150, sphere_frac=0.4, max_theta_deg=70.0)
    ti, uv = solve_tuples(chain, d["x0"], d["x3"], d["P"], d["N"], d["eta"])
    m = match_paths(np.arange(150), d["uv"], ti, uv)
    rows = m[m >= 0]
    ti, uv = ti[rows], uv[rows]
    out = path_irradiance(chain, d["x0"], d["x3"], d["P"], d["N"], d["eta"], ti, uv)
    geo = np.asarray(out.geometry)
    assert np.isfinite(geo).all() and (geo > 0).all()
    x0, x3, P, N, eta = d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti]
    X = bf._vertex_points(P, uv)
    wi, L0 = bf._unit(X[:, 0] - x0)
    wo, _ = bf._unit(x3 - X[:, 1])
    a, b = bf._perp_basis(wi)
    size = bf.tri_size(P[:, 0])
    areas = []
    for f in (1e-3, 2.5e-4, 6.25e-5):
        delta = f * size / L0
        cols = []
        for axis in (0, 1):
            pts = {}
            for k in (-2, -1, 1, 2):
                dvec = wi + (k * delta)[:, None] * (a if axis == 0 else b)
                pts[k], ok = _trace_two(x0, dvec, P, N, eta, chain, x3, wo)
            cols.append((-pts[2] + 8 * pts[1] - 8 * pts[-1] + pts[-2]) / (12 * delta)[:, None])
        areas.append(bf._norm(np.cross(cols[0], cols[1])))
    areas = np.array(areas)
    spread = np.abs(areas[2] / areas[1] - 1)
    G = 1.0 / areas[2]
    use = np.isfinite(G) & (spread < 1e-6)
    rel = np.abs(geo / G - 1)
    print(f"\n[{chain}] geometry term: paths {len(ti)}, compared {int(use.sum())}, rel err max {rel[use].max():.3g}, "
          f"median {np.median(rel[use]):.3g}")
    assert use.sum() >= 80
    assert rel[use].max() < 1e-4


# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("chain", CHAINS)
def test_degenerate_grazing_near_tir(chain):
    """Degenerate, grazing and near-TIR tuples: no NaN, no crash, no false path."""
    solve_tuples, path_irradiance = _api()
    rng = np.random.default_rng([SEED, 9, ord(chain[0]), ord(chain[1])])
    d = plant_two_bounce(rng, chain, 120, max_theta_deg=89.9)
    x0, x3, P, N, eta = d["x0"].copy(), d["x3"].copy(), d["P"].copy(), d["N"].copy(), d["eta"].copy()
    P[0:10, 0, 2] = P[0:10, 0, 0]  # zero-area triangle 1 (coincident corners)
    P[10:20, 1, 2] = P[10:20, 1, 1]  # zero-area triangle 2
    N[20:30] = 0.0  # zero normals
    x0[30:40] = P[30:40, 0].mean(1) + 2.0 * (P[30:40, 0, 1] - P[30:40, 0, 0])  # x0 in plane 1
    x3[40:50] = P[40:50, 1].mean(1) + 2.0 * (P[40:50, 1, 1] - P[40:50, 1, 0])  # x3 in plane 2
    P[50:60, 1] = P[50:60, 0]  # both triangles the same
    eta[60:70] = 1.0 + 1e-9  # index matched
    # near-TIR / grazing: rescale heights of x0 so incidence is very oblique
    c = P[70:120, 0].mean(1)
    fn, _ = bf._unit(np.cross(P[70:120, 0, 1] - P[70:120, 0, 0], P[70:120, 0, 2] - P[70:120, 0, 0]))
    rel = x0[70:120] - c
    h = np.sum(rel * fn, 1, keepdims=True)
    x0[70:120] = c + (rel - h * fn) + h * fn * 10.0 ** rng.uniform(-6, -2, (50, 1))
    with np.errstate(all="raise"):
        pass
    ti, uv = solve_tuples(chain, x0, x3, P, N, eta)
    assert np.isfinite(uv).all()
    chk = bf.check_path(chain, x0[ti], x3[ti], P[ti], N[ti], eta[ti], uv, tol=FALSE_TOL)
    assert chk.valid.all(), np.unique(chk.reason[~chk.valid], return_counts=True)
    assert not np.isin(ti, np.r_[0:30]).any()
    out = path_irradiance(chain, x0, x3, P, N, eta, ti, uv, reflectance="dielectric")
    assert np.isfinite(out.irradiance).all() and np.isfinite(out.direction).all()
    print(f"\n[{chain}] degenerate/grazing set: {len(ti)} paths, all valid, finite")


def test_unknown_chain_and_shapes():
    solve_tuples, _ = _api()
    d = plant_two_bounce(np.random.default_rng(1), "RR", 4)
    with pytest.raises(ValueError):
        solve_tuples("RRR", d["x0"], d["x3"], d["P"], d["N"], d["eta"])
    with pytest.raises(ValueError):
        solve_tuples("RR", d["x0"], d["x3"], d["P"][:, :1], d["N"][:, :1], d["eta"])
    bad = d["x0"].copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError):
        solve_tuples("TT", bad, d["x3"], d["P"], d["N"], d["eta"])
