"""The √β of refraction at vertex 1 (eq 21-22): the piecewise rational √ of eq (23)
(``sqrt_approx``, ``sqrt_piece``), one Heron step on a quadratic fitted to β over the whole
triangle where that fits (``heron_sqrt_fit``, ``heron_sqrt_cut``), and which √ pieces a tuple
has to solve (β as a polynomial, ``beta_poly``; its range on a grid, ``beta_mask``; a
piece's band, ``sqrt_band``; the TIR fallback, ``centroid_piece``).

Tested in tests/solver/test_solver_two_bounce.py (the rational √ against √x, the Heron fit's
error and degrees).
"""

import math

from ...runtime.jit import kernel
from .params import (BETA_GRID, BETA_MASK_FROM, BETA_SLOT, HERON_CHECK_GRID, HERON_CUTS, HERON_FIT_GRID, HERON_TOL,
                     SQRT_BAND_REACH, SQRT_BANDS, SQRT_PIECES)
from ...polynomials.bivariate import bmul_acc, bzero, vdot, vlin
from .prepass import box_range


@kernel
def centroid_piece(xc, mask):
    """(mask with the √ piece of the centroid's β/S² = xc (clamped to ≥ 0) added, the piece
    solved only as the TIR fallback or -2).  With the centroid in total internal reflection
    (xc ≤ 0) and piece 0 not sampled already, piece 0 (its band reaches β = 0) is solved for
    the paths next to the TIR curve, its sign changes only: that system is the noisiest of
    all (the √'s pole sits at the TIR curve) and its kink refinement cost 45 % of random TT's
    determinants for ~0.05 % of the paths (docs/decisions/two-bounce-solver.md)."""
    if xc > 0.0 or mask & 1:
        return mask | (1 << sqrt_piece(xc)), -2
    return mask | 1, 0


@kernel
def sqrt_piece(x):
    k = 0
    while k < SQRT_PIECES.shape[0] - 1 and x > SQRT_PIECES[k, 1]:
        k += 1
    return k


@kernel
def sqrt_approx(x):
    """The piecewise rational √x of eq (23) (x clamped to [0, 1])."""
    x = min(max(x, 0.0), 1.0)
    k = 0
    while k < SQRT_PIECES.shape[0] - 1 and x > SQRT_PIECES[k, 1]:
        k += 1
    return (SQRT_PIECES[k, 2] + SQRT_PIECES[k, 3] * x) / (1.0 + SQRT_PIECES[k, 4] * x)


# --- one √ for the whole triangle: a Heron step from a fitted quadratic ---------------------


@kernel
def beta_local(u, v, geo_l, r):
    """β(u1, v1) = |n1|²|d0|²(1 - η'²) + η'²(d0·n1)² of eq (22) at one point (local frame)."""
    d0 = (u * geo_l[2, 0] + v * geo_l[3, 0] - geo_l[0, 0], u * geo_l[2, 1] + v * geo_l[3, 1] - geo_l[0, 1],
          u * geo_l[2, 2] + v * geo_l[3, 2] - geo_l[0, 2])
    n1 = (geo_l[4, 0] + u * geo_l[5, 0] + v * geo_l[6, 0], geo_l[4, 1] + u * geo_l[5, 1] + v * geo_l[6, 1],
          geo_l[4, 2] + u * geo_l[5, 2] + v * geo_l[6, 2])
    nn = n1[0] * n1[0] + n1[1] * n1[1] + n1[2] * n1[2]
    dd = d0[0] * d0[0] + d0[1] * d0[1] + d0[2] * d0[2]
    dn = d0[0] * n1[0] + d0[1] * n1[1] + d0[2] * n1[2]
    return nn * dd * (1.0 - r * r) + r * r * dn * dn


@kernel
def _quadratic_at(c, u, v):
    return c[0] + u * c[1] + v * c[2] + u * u * c[3] + u * v * c[4] + v * v * c[5]


@kernel
def heron_sqrt_fit(geo_l, r, margin, S2, cut, M):
    """A quadratic q(u1, v1) ≈ √β over triangle 1 widened by the v margin, for the Heron
    step √β ≈ (β + q²) / (2q) (exact where q = √β; relative error (q - √β)² / (2 q √β), the
    square of the fit's); returns (ok, q's coefficients (1, u, v, u², uv, v²)).

    Replaces eq (23)'s piecewise rational in x = β/S² where it fits: that approximation is
    accurate only on its own x interval, and β/S² spans several intervals over a triangle
    (β grows with |x1 - x0|²), so the system had to be solved once per interval (TT planted:
    7.2 systems per tuple); the Heron form is one system, and d̃1 has degree 5 instead of 7
    (numerator β + q² of degree 4 times n1, denominator 2q of degree 2 times the degree-3
    tangential part), so b has total degree 34 instead of 46 for TT.  Only the part of the
    triangle with β/S² ≥ ``cut`` is fitted and checked: near β = 0 (grazing exit, the TIR
    border) √ is too steep for any smooth fit, and the √ pieces of eq (23) that lie below the
    cut are still solved as before (each its own system; :func:`heron_sqrt_cut` picks the
    cut).  ok is False where fewer than 12 fit points lie above the cut, q ≤ 0 at a check
    point above it, or the relative error there exceeds HERON_TOL.  Weighted least squares
    (weight 1/β: relative error) on a barycentric grid of order HERON_FIT_GRID; M: (6, 7)
    scratch."""
    ok, _, c = _heron_fit(geo_l, r, margin, S2, cut, M)
    return ok, c


@kernel
def _heron_fit(geo_l, r, margin, S2, cut, M):
    """:func:`heron_sqrt_fit`, also returning whether enough fit points lie above the cut
    (ok, enough, c): with too few, every higher cut has too few as well."""
    c = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for i in range(6):
        for j in range(7):
            M[i, j] = 0.0
    w = 1.0 + 3.0 * margin
    G = HERON_FIT_GRID
    n_fit = 0
    for i in range(G + 1):
        for j in range(G + 1 - i):
            u = -margin + w * i / G
            v = -margin + w * j / G
            beta = beta_local(u, v, geo_l, r)
            if not beta >= cut * S2:
                continue
            n_fit += 1
            y = math.sqrt(beta)
            wt = 1.0 / beta
            phi = (1.0, u, v, u * u, u * v, v * v)
            for k in range(6):
                for l in range(6):
                    M[k, l] += wt * phi[k] * phi[l]
                M[k, 6] += wt * phi[k] * y
    if n_fit < 12:
        return False, False, c
    # Gaussian elimination with partial pivoting on the 6 x 7 augmented matrix
    for k in range(6):
        p = k
        for i in range(k + 1, 6):
            if abs(M[i, k]) > abs(M[p, k]):
                p = i
        if not abs(M[p, k]) > 1e-300:
            return False, True, c
        if p != k:
            for j in range(7):
                t = M[k, j]
                M[k, j] = M[p, j]
                M[p, j] = t
        for i in range(k + 1, 6):
            f = M[i, k] / M[k, k]
            for j in range(k, 7):
                M[i, j] -= f * M[k, j]
    for k in range(5, -1, -1):
        acc = M[k, 6]
        for j in range(k + 1, 6):
            acc -= M[k, j] * M[j, 6]
        M[k, 6] = acc / M[k, k]
    c = (M[0, 6], M[1, 6], M[2, 6], M[3, 6], M[4, 6], M[5, 6])
    G = HERON_CHECK_GRID
    for i in range(G + 1):
        for j in range(G + 1 - i):
            u = -margin + w * i / G
            v = -margin + w * j / G
            beta = beta_local(u, v, geo_l, r)
            if not beta >= cut * S2:
                continue
            q = _quadratic_at(c, u, v)
            if not q > 0.0:
                return False, True, c
            y = math.sqrt(beta)
            if not (q - y) * (q - y) <= HERON_TOL * 2.0 * q * y:
                return False, True, c
    return True, True, c


@kernel
def heron_sqrt_cut(geo_l, r, margin, S2, M):
    """:func:`heron_sqrt_fit` above the first cut of HERON_CUTS where it fits; returns (ok,
    cut, q's coefficients).  The eq (23) pieces starting at or above the cut are replaced by
    the one Heron system, those below it are solved each on its own.

    At HERON_CUT alone the fit failed for ~40 % of the planted TT orientations (β/S² spanning
    much of [0, 1] over the triangle: √ is steep at its low end), which then solved ~3 eq
    (23) pieces of degree 46 instead; a higher cut drops that steep part from the fit
    (measurements: docs/decisions/two-bounce-solver.md)."""
    ok = False
    cut = HERON_CUTS[0]
    c = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for k in range(HERON_CUTS.shape[0]):
        cut = HERON_CUTS[k]
        ok, enough, c = _heron_fit(geo_l, r, margin, S2, cut, M)
        if ok or not enough:
            break
    return ok, cut, c


# --- √ pieces: which to solve, and where ----------------------------------------------------


@kernel
def beta_poly(geo_l, r, biv):
    """β = |n1|²|d0|²(1 - r²) + r²(d0·n1)² (eq 22) into biv[BETA_SLOT] (local frame, degree
    4; the same arithmetic as :func:`build_system`'s; slots 2-4, 7-12 as scratch)."""
    x0 = (geo_l[0, 0], geo_l[0, 1], geo_l[0, 2])
    D0 = biv[7:10]
    N1 = biv[10:13]
    vlin(D0, (-x0[0], -x0[1], -x0[2]), (geo_l[2, 0], geo_l[2, 1], geo_l[2, 2]), (geo_l[3, 0], geo_l[3, 1], geo_l[3, 2]))
    vlin(N1, (geo_l[4, 0], geo_l[4, 1], geo_l[4, 2]), (geo_l[5, 0], geo_l[5, 1], geo_l[5, 2]),
          (geo_l[6, 0], geo_l[6, 1], geo_l[6, 2]))
    vdot(D0, 1, N1, 1, biv[2])
    vdot(N1, 1, N1, 1, biv[3])
    vdot(D0, 1, D0, 1, biv[4])
    beta = biv[BETA_SLOT]
    bzero(beta, 4)
    bmul_acc(biv[3], 2, biv[4], 2, beta, 1.0 - r * r)
    bmul_acc(biv[2], 2, biv[2], 2, beta, r * r)


@kernel
def sqrt_band(piece, S2, refract1):
    """The β band [blo, bhi] where the system of eq (23)'s piece ``piece`` is solved: the
    piece's interval and SQRT_BAND_REACH neighbours' on each side (the piece's error grows outside its own
    interval; a root found there belongs to a neighbour, whose own system holds it more
    accurately).  β ≥ 0 below for the first pieces and for the Heron √ (piece < 0): β < 0 is
    total internal reflection at vertex 1, no refracted ray (β is exact, eq 22: the pre-pass
    drops a box where it is provably negative; TT, 10,000 tuples: 5.53M -> 5.26M determinants,
    the same paths); unbounded above for the last.  (-inf, inf) without a refraction at vertex 1
    or without ``SQRT_BANDS`` (β is not computed then)."""
    if not refract1 or not SQRT_BANDS:
        return -math.inf, math.inf
    if piece < 0:
        return 0.0, math.inf
    K = SQRT_PIECES.shape[0]
    blo = 0.0 if piece < SQRT_BAND_REACH else S2 * SQRT_PIECES[piece - SQRT_BAND_REACH, 0]
    bhi = math.inf if piece + SQRT_BAND_REACH >= K else S2 * SQRT_PIECES[piece + SQRT_BAND_REACH, 1]
    return blo, bhi


@kernel
def beta_mask(biv, margin, S2):
    """Bit k set for every eq (23) piece k ≥ BETA_MASK_FROM whose interval β/S² can reach
    on triangle 1 widened by the margin: bounds of β (biv[BETA_SLOT]) on a BETA_GRID² grid
    of boxes over [-m, 1 + m]² (boxes beyond u1 + v1 = 1 + m skipped).  With the pieces at
    the sample points (which can miss the extremes of β over the triangle), a path whose
    β/S² lies in such a piece has that piece's own system solved (``SQRT_BANDS``)."""
    mask = 0
    K = SQRT_PIECES.shape[0]
    w = (1.0 + 2.0 * margin) / BETA_GRID
    for i in range(BETA_GRID):
        for j in range(BETA_GRID):
            u0 = -margin + i * w
            v0 = -margin + j * w
            if u0 + v0 > 1.0 + margin:
                continue
            lo, hi = box_range(biv, BETA_SLOT, 4, u0, v0, w)
            lo /= S2
            hi /= S2
            for k in range(BETA_MASK_FROM, K):
                if hi >= SQRT_PIECES[k, 0] and (lo <= SQRT_PIECES[k, 1] or k == K - 1):
                    mask |= 1 << k
    return mask
