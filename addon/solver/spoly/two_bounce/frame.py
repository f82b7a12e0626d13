"""The per-orientation set-up of a two-bounce tuple (Fan et al. 2024 §3.4, §4.1), shared by the
one-kernel solver (``solve._solve_oriented``) and the staged pipeline (``staged._stage_a_oriented``).

:func:`tuple_frame`: the cheap side tests (x0 and triangle 2 against plane 1, x3 and triangle 1
against plane 2: a reflection keeps its side, a refraction crosses), the local frame (unit = the
longest edge of triangle 1, origin its first corner), which shading-normal orientations occur on
each face, the plane-of-incidence normal c2 at vertex 2 and the √β scale S.
:func:`sqrt_pieces_to_solve`: for one orientation at vertex 1, the β/S² range sampled over
triangle 1, the √ pieces (eq 23) holding it and the Heron √ cut; the TIR-everywhere case.
Both are pure functions of the tuple; the callers loop over the pieces and the orientations at
vertex 2 and solve (or store) each system.  Tested through tests/solver/test_solver_two_bounce.py
and tests/solver/test_opencl_two_bounce.py (the staged pipeline returns the one-kernel paths).
"""

import math

from ...runtime.jit import kernel
from ...paths.two_vertex import pack_geometry
from .params import HERON_CUT, HERON_SQRT, SQRT_BANDS, STAT_SKIPPED
from .sqrt import beta_mask, beta_poly, centroid_piece, heron_sqrt_cut, sqrt_piece

FAIL = (False, 0.0, 0.0, 0.0, 0.0, False, False, False, False, False, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


@kernel
def _corner_sides(p0, e1, e2, o, n, side):
    """Least and greatest (q - o) . n x side over the corners q of the triangle (p0, e1, e2):
    where a triangle lies against the plane through o with normal n, relative to the side of
    the chain's endpoint at that plane (``side``)."""
    lo = math.inf
    hi = -math.inf
    for c in range(3):
        q = p0
        if c == 1:
            q = (p0[0] + e1[0], p0[1] + e1[1], p0[2] + e1[2])
        elif c == 2:
            q = (p0[0] + e2[0], p0[1] + e2[1], p0[2] + e2[2])
        sd = (q[0] - o[0]) * n[0] + (q[1] - o[1]) * n[1] + (q[2] - o[2]) * n[2]
        lo = min(lo, sd * side)
        hi = max(hi, sd * side)
    return lo, hi


@kernel
def tuple_frame(refract1, refract2, x0, x3, PA, NA, PB, NB, geo, geo_l, stats):
    """Side tests, local frame and orientation cases of the tuple (triangle A first; module doc).
    Fills geo (``pack_geometry``) and geo_l (the frame).  Returns (ok, side0, side3, inv, S,
    any_front1, any_back1, any_front2, any_back2, flat2, cx, c2); ok False (and
    stats[STAT_SKIPPED] counted where a test failed) when no path can exist."""
    if not pack_geometry(x0, x3, PA, NA, PB, NB, geo):
        return FAIL
    # --- cheap side tests -------------------------------------------------------------------
    ng1 = (geo[13, 0], geo[13, 1], geo[13, 2])
    ng2 = (geo[14, 0], geo[14, 1], geo[14, 2])
    e11 = (geo[2, 0], geo[2, 1], geo[2, 2])
    e12 = (geo[3, 0], geo[3, 1], geo[3, 2])
    p20 = (geo[7, 0], geo[7, 1], geo[7, 2])
    e21 = (geo[8, 0], geo[8, 1], geo[8, 2])
    e22 = (geo[9, 0], geo[9, 1], geo[9, 2])
    L1 = max(math.sqrt(e11[0] ** 2 + e11[1] ** 2 + e11[2] ** 2), math.sqrt(e12[0] ** 2 + e12[1] ** 2 + e12[2] ** 2))
    L2 = max(math.sqrt(e21[0] ** 2 + e21[1] ** 2 + e21[2] ** 2), math.sqrt(e22[0] ** 2 + e22[1] ** 2 + e22[2] ** 2))
    side0 = geo[0, 0] * ng1[0] + geo[0, 1] * ng1[1] + geo[0, 2] * ng1[2]
    if abs(side0) <= 1e-12 * L1:
        stats[STAT_SKIPPED] += 1
        return FAIL
    # triangle 2's corners against plane 1 (through the origin p1,0)
    lo2, hi2 = _corner_sides(p20, e21, e22, (0.0, 0.0, 0.0), ng1, side0)
    tol1 = 1e-9 * (L1 + L2) * abs(side0)
    if (not refract1 and hi2 <= tol1) or (refract1 and lo2 >= -tol1):
        stats[STAT_SKIPPED] += 1
        return FAIL
    # x3 and triangle 1's corners against plane 2
    side3 = (geo[1, 0] - p20[0]) * ng2[0] + (geo[1, 1] - p20[1]) * ng2[1] + (geo[1, 2] - p20[2]) * ng2[2]
    if abs(side3) <= 1e-12 * L2:
        stats[STAT_SKIPPED] += 1
        return FAIL
    lo1, hi1 = _corner_sides((0.0, 0.0, 0.0), e11, e12, p20, ng2, side3)
    tol2 = 1e-9 * (L1 + L2) * abs(side3)
    if (not refract2 and hi1 <= tol2) or (refract2 and lo1 >= -tol2):
        stats[STAT_SKIPPED] += 1
        return FAIL

    # --- local frame: unit = L1, origin p1,0 (geo is already relative to p1,0) ------------
    inv = 1.0 / L1
    for r in range(13):
        f = inv if (r <= 3 or (r >= 7 and r <= 9)) else 1.0
        for c in range(3):
            geo_l[r, c] = geo[r, c] * f
    # normal orientation over each face (a normal field that turns over the face gives two
    # side assignments to try)
    any_front1 = False
    any_back1 = False
    any_front2 = False
    any_back2 = False
    nmax1 = 0.0
    flat2 = True
    nscale2 = 0.0
    for c in range(3):
        n1c = (geo[4, 0], geo[4, 1], geo[4, 2])
        n2c = (geo[10, 0], geo[10, 1], geo[10, 2])
        if c > 0:
            n1c = (n1c[0] + geo[4 + c, 0], n1c[1] + geo[4 + c, 1], n1c[2] + geo[4 + c, 2])
            n2c = (n2c[0] + geo[10 + c, 0], n2c[1] + geo[10 + c, 1], n2c[2] + geo[10 + c, 2])
        s_1 = n1c[0] * ng1[0] + n1c[1] * ng1[1] + n1c[2] * ng1[2]
        s_2 = n2c[0] * ng2[0] + n2c[1] * ng2[1] + n2c[2] * ng2[2]
        any_front1 = any_front1 or s_1 > 0.0
        any_back1 = any_back1 or s_1 < 0.0
        any_front2 = any_front2 or s_2 > 0.0
        any_back2 = any_back2 or s_2 < 0.0
        nmax1 = max(nmax1, n1c[0] ** 2 + n1c[1] ** 2 + n1c[2] ** 2)
        nscale2 = max(nscale2, math.sqrt(n2c[0] ** 2 + n2c[1] ** 2 + n2c[2] ** 2))
    for r in (11, 12):
        if abs(geo[r, 0]) + abs(geo[r, 1]) + abs(geo[r, 2]) > 1e-12 * nscale2:
            flat2 = False
    if not (nmax1 > 0.0 and nscale2 > 0.0):
        stats[STAT_SKIPPED] += 1
        return FAIL
    # plane-of-incidence normal at vertex 2: (x3 - centroid1) × mean n2
    cx = ((e11[0] + e12[0]) / 3.0, (e11[1] + e12[1]) / 3.0, (e11[2] + e12[2]) / 3.0)
    w = (geo[1, 0] - cx[0], geo[1, 1] - cx[1], geo[1, 2] - cx[2])
    nb = (3.0 * geo[10, 0] + geo[11, 0] + geo[12, 0], 3.0 * geo[10, 1] + geo[11, 1] + geo[12, 1], 3.0 * geo[10, 2] + geo[11, 2] + geo[12, 2])
    c2 = (w[1] * nb[2] - w[2] * nb[1], w[2] * nb[0] - w[0] * nb[2], w[0] * nb[1] - w[1] * nb[0])
    lc = math.sqrt(c2[0] ** 2 + c2[1] ** 2 + c2[2] ** 2)
    lw = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    lnb = math.sqrt(nb[0] ** 2 + nb[1] ** 2 + nb[2] ** 2)
    if not lc > 1e-6 * lw * lnb:
        c2 = (e21[1] * nb[2] - e21[2] * nb[1], e21[2] * nb[0] - e21[0] * nb[2], e21[0] * nb[1] - e21[1] * nb[0])
        lc = math.sqrt(c2[0] ** 2 + c2[1] ** 2 + c2[2] ** 2)
        if not lc > 0.0:
            stats[STAT_SKIPPED] += 1
            return FAIL
    c2 = (c2[0] / lc, c2[1] / lc, c2[2] / lc)

    # √β scale and the x = β/S² range over triangle 1 (for the pieces to use)
    dmax = 0.0
    for c in range(3):
        q = (0.0, 0.0, 0.0)
        if c == 1:
            q = e11
        elif c == 2:
            q = e12
        dv = (q[0] - geo[0, 0], q[1] - geo[0, 1], q[2] - geo[0, 2])
        dmax = max(dmax, (dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2) * inv * inv)
    S = math.sqrt(nmax1 * dmax)

    return True, side0, side3, inv, S, any_front1, any_back1, any_front2, any_back2, flat2, cx, c2


@kernel
def sqrt_sampling(refract1, geo, inv, S, cx, r1):
    """The β/S² samples of :func:`sqrt_pieces_to_solve` over triangle 1 (corners, edge thirds,
    centroid) for the IOR ratio r1 at vertex 1: (ok, mask, fallback_piece, xlo, xhi); ok False
    where β < 0 at every sample (total internal reflection everywhere); mask bit k: eq 23's
    piece k holds a sample; fallback_piece: the piece solved only as the TIR fallback (or -2);
    xlo, xhi the samples' range.  Without a refraction at vertex 1: (True, 0, -2, inf, -inf)."""
    e11 = (geo[2, 0], geo[2, 1], geo[2, 2])
    e12 = (geo[3, 0], geo[3, 1], geo[3, 2])
    # x = β/S² range: sample the triangle
    xlo = math.inf
    xhi = -math.inf
    fallback_piece = -2  # the √ piece solved only as the TIR fallback (piece -1 is Heron)
    mask = 0  # √ pieces holding β/S² at the sample points
    if refract1:
        for iu in range(4):
            for iv in range(4 - iu):
                uu = iu / 3.0
                vv = iv / 3.0
                nn = (geo[4, 0] + uu * geo[5, 0] + vv * geo[6, 0], geo[4, 1] + uu * geo[5, 1] + vv * geo[6, 1], geo[4, 2] + uu * geo[5, 2] + vv * geo[6, 2])
                dv = ((uu * e11[0] + vv * e12[0] - geo[0, 0]) * inv, (uu * e11[1] + vv * e12[1] - geo[0, 1]) * inv, (uu * e11[2] + vv * e12[2] - geo[0, 2]) * inv)
                n2_ = nn[0] ** 2 + nn[1] ** 2 + nn[2] ** 2
                d2_ = dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2
                dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2]
                beta = n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn
                x = beta / (S * S)
                xlo = min(xlo, x)
                xhi = max(xhi, x)
                if x >= 0.0:
                    mask |= 1 << sqrt_piece(x)
        nn = (geo[4, 0] + (geo[5, 0] + geo[6, 0]) / 3.0, geo[4, 1] + (geo[5, 1] + geo[6, 1]) / 3.0, geo[4, 2] + (geo[5, 2] + geo[6, 2]) / 3.0)
        dv = ((cx[0] - geo[0, 0]) * inv, (cx[1] - geo[0, 1]) * inv, (cx[2] - geo[0, 2]) * inv)
        n2_ = nn[0] ** 2 + nn[1] ** 2 + nn[2] ** 2
        d2_ = dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2
        dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2]
        xc = min(1.0, max(0.0, (n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn) / (S * S)))
        if xhi <= 0.0:  # TIR everywhere on the triangle
            return False, 0, -2, xlo, xhi
        # the pieces holding x at the corners, edge thirds and centroid (the
        # Gauss-Newton polish in path space removes the error of a piece used
        # a little outside its interval)
        mask, fallback_piece = centroid_piece(xc, mask)
    return True, mask, fallback_piece, xlo, xhi


@kernel
def sqrt_pieces_to_solve(refract1, geo, geo_l, inv, S, cx, r1, margin, biv):
    """The √ pieces to solve for the IOR ratio r1 at vertex 1 (module doc).  Returns (ok, mask,
    fallback_piece, heron_ok, heron_cut, heron): ok False where β < 0 on the whole triangle
    (total internal reflection everywhere); mask bit k: eq 23's piece k holds β/S² somewhere
    (:func:`sqrt_sampling`, and the β bounds of ``beta_mask``); fallback_piece: the piece solved
    only as the TIR fallback (piece -1 is the Heron √)."""
    ok, mask, fallback_piece, xlo, xhi = sqrt_sampling(refract1, geo, inv, S, cx, r1)
    if not ok:
        return False, 0, -2, False, HERON_CUT, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if refract1 and SQRT_BANDS:
        beta_poly(geo_l, r1, biv)
        if xlo > 0.0:
            mask |= beta_mask(biv, margin, S * S)
    heron_ok = False
    heron_cut = HERON_CUT
    heron = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if refract1 and HERON_SQRT:
        heron_ok, heron_cut, heron = heron_sqrt_cut(geo_l, r1, margin, S * S, biv[45, 0:6, 0:7])
    return True, mask, fallback_piece, heron_ok, heron_cut, heron
