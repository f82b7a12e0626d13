"""The two-bounce solver per tuple and per batch (Fan et al. 2024 §3.4-4.3).

``solve_two_bounce_batch`` runs ``solve_two_bounce_tuple`` over tuples in parallel chunks
with fixed-size scratch (``make_scratch2``).  Per tuple: side tests, the local frame, the √
pieces and orientations to solve (forward and reversed), each system built
(``system.build_system``), pre-passed and scanned (``resultant``); at each v1 root the u1
roots of a(·, v1) are candidates (``candidates_at``), polished in path space by Gauss-Newton
and validated (``paths.two_vertex``), merged when two converge onto one path; a seeded
polish covers degenerate systems, the line x0 -> x3 the normal-incidence path.

Tested in tests/solver/test_solver_two_bounce.py (analytic cases, planted paths,
brute-force recall) and bench/two_bounce_recall.py.
"""

import math

import numpy as np

from ...runtime.jit import kernel, prange
from ...paths.one_vertex import line_crossing_barycentrics
from ...paths.two_vertex import pack_geometry, polish_and_validate2, trace_to_second
from ...geometry.vec3 import row
from ...polynomials.roots import MAX_DEGREE, roots_in_interval
from .params import (ACCEPT_RESIDUAL, B_RELATIVE, BOTH_DIRECTIONS, CHUNK, HERON_CUT, HERON_SQRT, LIVE_PREPASS,
                     LIVE_STACK, MAX_PATHS_TWO_BOUNCE, MAX_PIECES, MAXD, N_SEEDS, N_SLOTS, N_STATS, NEAR_PATH,
                     POLISH_STEPS, PRODUCTIVE_RADIUS, SAME_PATH, SQRT_BANDS, SQRT_PIECES, STAT_ACCEPTED,
                     STAT_CANDIDATES, STAT_NEAR, STAT_PATHS, STAT_ROOTS, STAT_SKIPPED, V_MAJOR_SLOT, V_MARGIN_APPROX,
                     V_MARGIN_EXACT)
from ...polynomials.bivariate import bernstein_has_zero, bmax, u_degree
from .prepass import live_pieces_band
from .sqrt import beta_mask, beta_poly, centroid_piece, heron_sqrt_cut, sqrt_band, sqrt_piece
from .system import build_system
from .resultant import find_v_roots, refine_v_roots, v_major


@kernel
def _store_path2(th, err, sigma, out_uv, meta, count):
    for q in range(min(count, out_uv.shape[0])):
        dist = 0.0
        for i in range(4):
            dist = max(dist, abs(out_uv[q, i] - th[i]))
        sig = min(sigma, meta[q, 1])
        radius = SAME_PATH
        if sig > 0.0:
            radius = max(radius, 4.0 * (err + meta[q, 0] + 1e-12) / sig)
        else:
            radius = NEAR_PATH
        if dist < min(radius, NEAR_PATH):
            if err < meta[q, 0]:
                for i in range(4):
                    out_uv[q, i] = th[i]
                meta[q, 0] = err
                meta[q, 1] = sigma
            return count
    if count < out_uv.shape[0]:
        for i in range(4):
            out_uv[count, i] = th[i]
        meta[count, 0] = err
        meta[count, 1] = sigma
    return count + 1


@kernel
def _try_candidate(u1, v1, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats):
    """(u1, v1) on the first triangle of the oriented chain -> exact map to the second ->
    polish and validate in forward path space (``rev``: the chain was solved reversed,
    from x3, and (u1, v1) are the forward (u2, v2))."""
    stats[STAT_CANDIDATES] += 1
    ok, u2, v2 = trace_to_second(u1, v1, geo, refract1, eta)
    if not ok:
        return count
    if rev:
        th[0] = u2
        th[1] = v2
        th[2] = u1
        th[3] = v1
        acc, err, sig = polish_and_validate2(th, geo_fwd, refract2, refract1, eta, POLISH_STEPS, ACCEPT_RESIDUAL, work)
    else:
        th[0] = u1
        th[1] = v1
        th[2] = u2
        th[3] = v2
        acc, err, sig = polish_and_validate2(th, geo_fwd, refract1, refract2, eta, POLISH_STEPS, ACCEPT_RESIDUAL, work)
    if not acc:
        return count
    stats[STAT_ACCEPTED] += 1
    return _store_path2(th, err, sig, out_uv, meta, count)


@kernel
def seeded(geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats):
    """Fallback for degenerate systems (determinant identically zero): polish from a grid."""
    for i in range(N_SEEDS + 1):
        for j in range(N_SEEDS + 1 - i):
            u = (i + 1.0 / 3.0) / (N_SEEDS + 1.0)
            v = (j + 1.0 / 3.0) / (N_SEEDS + 1.0)
            count = _try_candidate(u, v, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats)
    return count


@kernel
def straight_candidate(geo, refract1, refract2, eta, work, th, out_uv, meta, count, stats):
    """The straight line x0 -> x3 through triangle 1's plane as a candidate: the path at
    normal incidence through parallel faces (light and receiver on the normal of a slab),
    where the coplanarity polynomial vanishes identically and the resultant carries no root."""
    # geo holds positions relative to triangle 1's first vertex (p0 = origin).
    ok, u, v = line_crossing_barycentrics(row(geo, 0), row(geo, 1), (0.0, 0.0, 0.0), row(geo, 2), row(geo, 3), row(geo, 13))
    if not ok:
        return count
    if u < -1e-6 or v < -1e-6 or u + v > 1.0 + 1e-6:
        return count
    return _try_candidate(u, v, geo, refract1, refract2, eta, False, geo, work, th, out_uv, meta, count, stats)


@kernel
def solve_two_bounce_tuple(refract1, refract2, x0, x3, P, N, eta, pieces, stop_after, sc_biv, sc_cf, sc_mat, sc_scan,
                           sc_geo, sc_work, sc_roots, sc_chain, sc_lists, out_uv, stats):
    """All admissible two-bounce paths of one tuple; returns their count (may exceed the
    capacity of out_uv: the caller reports the overflow).

    The system is solved twice: parametrised by triangle 1 (x0 -> 1 -> 2 -> x3) and, by
    reciprocity, by triangle 2 on the reversed chain (x3 -> 2 -> 1 -> x0).  When the first
    bounce magnifies (a curved or small triangle 1 seeing a large or far triangle 2), every
    solution through triangle 2 lies in a tiny patch of (u1, v1), where a sign scan cannot
    separate their v1 roots; on the reversed chain the same solutions spread over (u2, v2)."""
    for k in range(N_STATS):
        stats[k] = 0
    geo_fwd = sc_geo[0]
    meta = sc_roots[0:out_uv.shape[0] + 1, 0:2]
    if not pack_geometry(x0, x3, P[0], N[0], P[1], N[1], geo_fwd) or not (eta > 0.0):
        stats[STAT_SKIPPED] = 1
        return 0
    count = _solve_oriented(refract1, refract2, x0, x3, P[0], N[0], P[1], N[1], eta, pieces, stop_after, sc_biv, sc_cf,
                            sc_mat, sc_scan, sc_geo[0], sc_geo[1], False, geo_fwd, sc_work, sc_roots, sc_chain, sc_lists,
                            out_uv, meta, 0, stats)
    if stop_after == 0:
        count = straight_candidate(geo_fwd, refract1, refract2, eta, sc_work, sc_roots[out_uv.shape[0] + 1, 0:4],
                                    out_uv, meta, count, stats)
    if BOTH_DIRECTIONS:
        pack_geometry(x3, x0, P[1], N[1], P[0], N[0], sc_geo[2])
        count = _solve_oriented(refract2, refract1, x3, x0, P[1], N[1], P[0], N[0], eta, pieces, stop_after, sc_biv,
                                sc_cf, sc_mat, sc_scan, sc_geo[2], sc_geo[1], True, geo_fwd, sc_work, sc_roots, sc_chain,
                                sc_lists, out_uv, meta, count, stats)
    # skipped: every orientation's system was rejected before solving
    stats[STAT_SKIPPED] = 1 if stats[STAT_SKIPPED] >= (2 if BOTH_DIRECTIONS else 1) else 0
    stats[STAT_PATHS] = count
    return count


@kernel
def _solve_oriented(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, pieces, stop_after, sc_biv, sc_cf, sc_mat, sc_scan,
                    geo, geo_l, rev, geo_fwd, sc_work, sc_roots, sc_chain, sc_lists, out_uv, meta, count_in, stats):
    """The pipeline for one orientation of the chain (triangle A first); see
    :func:`solve_two_bounce_tuple`.  Returns the new path count."""
    th = sc_roots[out_uv.shape[0] + 1, 0:4]
    v_roots = sc_roots[out_uv.shape[0] + 2]
    u_roots = sc_roots[out_uv.shape[0] + 3]
    coeffs = sc_roots[out_uv.shape[0] + 4]
    if not pack_geometry(x0, x3, PA, NA, PB, NB, geo):
        return count_in
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
        return count_in
    # triangle 2's corners against plane 1 (through the origin p1,0)
    lo2 = math.inf
    hi2 = -math.inf
    for c in range(3):
        q = p20
        if c == 1:
            q = (p20[0] + e21[0], p20[1] + e21[1], p20[2] + e21[2])
        elif c == 2:
            q = (p20[0] + e22[0], p20[1] + e22[1], p20[2] + e22[2])
        sd = q[0] * ng1[0] + q[1] * ng1[1] + q[2] * ng1[2]
        lo2 = min(lo2, sd * side0)
        hi2 = max(hi2, sd * side0)
    tol1 = 1e-9 * (L1 + L2) * abs(side0)
    if (not refract1 and hi2 <= tol1) or (refract1 and lo2 >= -tol1):
        stats[STAT_SKIPPED] += 1
        return count_in
    # x3 and triangle 1's corners against plane 2
    side3 = (geo[1, 0] - p20[0]) * ng2[0] + (geo[1, 1] - p20[1]) * ng2[1] + (geo[1, 2] - p20[2]) * ng2[2]
    if abs(side3) <= 1e-12 * L2:
        stats[STAT_SKIPPED] += 1
        return count_in
    lo1 = math.inf
    hi1 = -math.inf
    for c in range(3):
        q = (0.0, 0.0, 0.0)
        if c == 1:
            q = e11
        elif c == 2:
            q = e12
        sd = (q[0] - p20[0]) * ng2[0] + (q[1] - p20[1]) * ng2[1] + (q[2] - p20[2]) * ng2[2]
        lo1 = min(lo1, sd * side3)
        hi1 = max(hi1, sd * side3)
    tol2 = 1e-9 * (L1 + L2) * abs(side3)
    if (not refract2 and hi1 <= tol2) or (refract2 and lo1 >= -tol2):
        stats[STAT_SKIPPED] += 1
        return count_in

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
        return count_in
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
            return count_in
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

    count = count_in
    margin = V_MARGIN_APPROX if refract1 else V_MARGIN_EXACT
    biv = sc_biv
    n_orient1 = 2 if refract1 else 1
    n_side2 = 2 if refract2 else 1
    n_pieces_sqrt = SQRT_PIECES.shape[0] if refract1 else 1
    for o1 in range(n_orient1):
        sigma1 = 1.0 if o1 == 0 else -1.0  # orientation of the shading normal vs ng1
        if refract1 and ((sigma1 > 0.0 and not any_front1) or (sigma1 < 0.0 and not any_back1)):
            continue
        s_in1 = sigma1 * (1.0 if side0 > 0.0 else -1.0)  # incoming side at vertex 1
        r1 = (1.0 / eta) if s_in1 > 0.0 else eta
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
            if xhi <= 0.0:
                continue  # TIR everywhere on the triangle
            # the pieces holding x at the corners, edge thirds and centroid (the
            # Gauss-Newton polish in path space removes the error of a piece used
            # a little outside its interval)
            mask, fallback_piece = centroid_piece(xc, mask)
        if refract1 and SQRT_BANDS:
            beta_poly(geo_l, r1, biv)
            if xlo > 0.0:
                mask |= beta_mask(biv, margin, S * S)
        heron_ok = False
        heron_cut = HERON_CUT
        heron = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if refract1 and HERON_SQRT:
            heron_ok, heron_cut, heron = heron_sqrt_cut(geo_l, r1, margin, S * S, biv[45, 0:6, 0:7])
        for piece in range(-1, n_pieces_sqrt):
            # piece -1: the Heron √ (β/S² above its cut), then the eq (23) pieces (only
            # those reaching below the cut when the Heron √ is used)
            if piece < 0 and not heron_ok:
                continue
            if piece >= 0 and heron_ok and SQRT_PIECES[piece, 0] >= heron_cut:
                continue
            if piece >= 0 and refract1 and not (mask >> piece) & 1:
                continue
            for o2 in range(n_side2):
                eta_in2 = 1.0
                eta_out2 = 1.0
                if refract2:
                    sigma2 = 1.0 if o2 == 0 else -1.0
                    if (sigma2 > 0.0 and not any_front2) or (sigma2 < 0.0 and not any_back2):
                        continue
                    # incoming side at vertex 2: x1's side of plane 2 (ng2 oriented by σ2),
                    # which for a refraction is the side opposite to x3's
                    s_in2 = -sigma2 * (1.0 if side3 > 0.0 else -1.0)
                    eta_in2 = 1.0 if s_in2 > 0.0 else eta
                    eta_out2 = eta if s_in2 > 0.0 else 1.0
                da, db = build_system(refract1, refract2, s_in1, r1, piece, S, heron, eta_in2,
                                       eta_out2, flat2, c2, geo_l, biv)
                blo, bhi = sqrt_band(piece, S * S, refract1)
                count = _solve_system(biv, da, db, blo, bhi, refract1, refract2, margin, pieces, stop_after,
                                      piece != fallback_piece, geo, eta, sc_cf,
                                      sc_mat, sc_scan, sc_work, th, v_roots, u_roots, coeffs, sc_chain, sc_lists, rev, geo_fwd, out_uv, meta,
                                      count, stats)
                if count < 0:
                    count = -count - 1
                    count = seeded(geo, refract1, refract2, eta, rev, geo_fwd, sc_work, th, out_uv, meta, count, stats)
    return count


@kernel
def _solve_system(biv, da, db, blo, bhi, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan, work, th,
                  v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Roots of {a = 0, b = 0} -> polished paths, where β lies in [blo, bhi] (the √ piece's
    band, :func:`sqrt_band`); ``refine``: refine the scan (:func:`refine_v_roots`) or take
    its sign changes only.  Returns the new count, or -(count + 1) when the system is
    degenerate (identically vanishing resultant)."""
    a = biv[0]
    b = biv[1]
    ma = bmax(a, da)
    mb = bmax(b, db)
    if not (ma > 0.0 and mb > 0.0) or not (np.isfinite(ma) and np.isfinite(mb)):
        return -(count + 1)
    for i in range(da + 1):
        for j in range(da + 1 - i):
            a[i, j] /= ma
            if abs(a[i, j]) <= 1e-14:
                a[i, j] = 0.0
    for i in range(db + 1):
        for j in range(db + 1 - i):
            b[i, j] /= mb
            if abs(b[i, j]) <= 1e-15:
                b[i, j] = 0.0
    # early exit: the coplanarity polynomial has no zero on triangle 1
    if da <= 20 and not bernstein_has_zero(a, da, 1e-2 if refract1 else 1e-9, coeffs):
        stats[STAT_SKIPPED] = 1
        return count
    if stop_after == 1:
        return count
    # hidden variable v1 (u1 eliminated)
    return _eliminate(a, da, b, db, blo, bhi, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan,
                      work, th, biv, v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)


@kernel
def _eliminate(a, da, b, db, blo, bhi, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan, work, th,
               biv, v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Eliminate the first variable (rows of a, b), scan the hidden one (columns), back-solve,
    polish."""
    na = u_degree(a, da, 1e-14)
    nb = u_degree(b, db, 1e-15)
    n = max(na, nb)
    if n == 0 or n >= MAXD:
        return -(count + 1)
    live = scan[7]
    if LIVE_PREPASS:
        boxes = scan[3, 0:LIVE_STACK * 4].reshape((LIVE_STACK, 4))
        if live_pieces_band(a, da, b, db, margin, pieces, biv, boxes, live, blo, bhi) == 0:
            return count
    else:
        for k in range(pieces):
            live[k] = 1
    # the determinant family reads the system v-major (the pre-pass's slots are free now)
    at = biv[V_MAJOR_SLOT]
    bt = biv[V_MAJOR_SLOT + 1]
    v_major(a, da, at)
    v_major(b, db, bt)
    nv = find_v_roots(at, da, bt, db, n, -margin, 1.0 + margin, pieces, live, cf, mat, scan, v_roots, stats)
    if nv < 0:
        return -(count + 1)
    if stop_after == 2:
        stats[STAT_ROOTS] += nv
        return count
    productive = scan[5]  # per scan root: did one of its candidates polish into a path?
    for iv in range(nv):
        near = stats[STAT_NEAR]
        count = candidates_at(v_roots[iv], a, da, b, db, na, nb, refract1, refract2, margin, geo, eta,
                               work, th, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)
        productive[iv] = 1.0 if stats[STAT_NEAR] > near else 0.0
    nv_all = refine_v_roots(at, da, bt, db, n, pieces, live, cf, mat, scan, v_roots, nv, productive, stats) if refine else nv

    for iv in range(nv, nv_all):
        count = candidates_at(v_roots[iv], a, da, b, db, na, nb, refract1, refract2, margin, geo, eta,
                               work, th, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)
    stats[STAT_ROOTS] += max(nv, nv_all)
    return count


@kernel
def candidates_at(v, a, da, b, db, na, nb, refract1, refract2, margin, geo, eta, work, th, u_roots, coeffs,
                   chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Back-substitution at a resultant root v (§4.3): the roots u of a(·, v) in the
    triangle whose b(u, v) is relatively small (the smallest always) are polished as paths."""
    # a(·, v) coefficients
    deg_u = na
    for i in range(na + 1):
        acc = 0.0
        for j in range(da - i, -1, -1):
            acc = acc * v + a[i, j]
        coeffs[i] = acc
    use_b = False
    big = 0.0
    for i in range(na + 1):
        big = max(big, abs(coeffs[i]))
    if not big > 1e-12 or na == 0:
        use_b = True
    if use_b:
        if nb > MAX_DEGREE:
            return count
        deg_u = nb
        for i in range(nb + 1):
            acc = 0.0
            for j in range(db - i, -1, -1):
                acc = acc * v + b[i, j]
            coeffs[i] = acc
    if deg_u > MAX_DEGREE or deg_u == 0:
        return count
    n_u = roots_in_interval(coeffs, deg_u, -margin, 1.0 - v + margin, 1e-14, 1e-10, chain, lists[0:2], u_roots)
    # rank by relative |b(u, v)|
    best = -1
    best_rel = math.inf
    for iu in range(n_u):
        u = u_roots[iu]
        val = 0.0
        mag = 0.0
        up = 1.0
        for i in range(nb + 1):
            acc = 0.0
            for j in range(db - i, -1, -1):
                acc = acc * v + b[i, j]
            val += acc * up
            mag += abs(acc * up)
            up *= u
        rel = abs(val) / mag if mag > 0.0 else 0.0
        lists[2, iu] = rel
        if rel < best_rel:
            best_rel = rel
            best = iu
    for iu in range(n_u):
        if iu != best and not lists[2, iu] < B_RELATIVE:
            continue
        u1 = min(max(u_roots[iu], 0.0), 1.0)
        v1 = min(max(v, 0.0), 1.0)
        if u1 + v1 > 1.0:
            excess = 0.5 * (u1 + v1 - 1.0)
            u1 -= excess
            v1 -= excess
        if _already_stored(u1, v1, out_uv, 2 if rev else 0, count):
            stats[STAT_ACCEPTED] += 1
            if abs(v1 - v) <= PRODUCTIVE_RADIUS:
                stats[STAT_NEAR] += 1
            continue
        accepted = stats[STAT_ACCEPTED]
        count = _try_candidate(u1, v1, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats)
        if stats[STAT_ACCEPTED] > accepted:
            # th: the polished path, forward order; the oriented chain's (u1, v1) are th[2:4]
            # when solved reversed
            hidden = th[(2 if rev else 0) + 1]
            if abs(hidden - v) <= PRODUCTIVE_RADIUS:
                stats[STAT_NEAR] += 1
    return count


@kernel
def _already_stored(u1, v1, out_uv, off, count):
    for q in range(min(count, out_uv.shape[0])):
        if abs(out_uv[q, off] - u1) < 1e-9 and abs(out_uv[q, off + 1] - v1) < 1e-9:
            return True
    return False


@kernel(parallel=True)
def solve_two_bounce_batch(refract1, refract2, x_start, x_end, P, N, eta, pieces, stop_after, out_uv, out_count, stats):
    n = x_start.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        biv, cf, mat, scan, geo, work, roots, chain, lists = make_scratch2()
        for t in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
            x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
            out_count[t] = solve_two_bounce_tuple(refract1, refract2, x0, x3, P[t], N[t], eta[t], pieces, stop_after,
                                                  biv, cf, mat, scan, geo, work, roots, chain, lists, out_uv[t], stats[t])


@kernel
def make_scratch2():
    biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
    cf = np.zeros((2, MAXD + 2))
    mat = np.zeros((MAXD + 1, MAXD + 1))
    scan = np.zeros((9, MAX_PIECES + 1))
    geo = np.zeros((3, 15, 3))
    work = np.zeros((25, 6))
    roots = np.zeros((MAX_PATHS_TWO_BOUNCE + 5, 4 * MAX_PIECES))
    chain = np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1))
    lists = np.zeros((3, MAX_DEGREE + 1))
    return biv, cf, mat, scan, geo, work, roots, chain, lists
