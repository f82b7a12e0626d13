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

from ...runtime.jit import kernel, parallel_range
from ...paths.one_vertex import line_crossing_barycentrics
from ...paths.two_vertex import pack_geometry, polish_and_validate2, trace_to_second
from ...geometry.vec3 import row
from ...polynomials.roots import MAX_DEGREE, roots_in_interval
from .params import (ACCEPT_RESIDUAL, B_RELATIVE, BOTH_DIRECTIONS, CHUNK, LIVE_PREPASS, LIVE_STACK,
                     MAX_PATHS_TWO_BOUNCE, MAX_PIECES, MAXD, N_SEEDS, N_SLOTS, N_STATS, NEAR_PATH, POLISH_STEPS,
                     PRODUCTIVE_RADIUS, SAME_PATH, SQRT_PIECES, STAT_ACCEPTED, STAT_CANDIDATES, STAT_NEAR, STAT_PATHS,
                     STAT_ROOTS, STAT_SKIPPED, V_MAJOR_SLOT, V_MARGIN_APPROX, V_MARGIN_EXACT)
from ...polynomials.bivariate import bernstein_has_zero, bmax, u_degree
from .prepass import live_pieces_band
from .sqrt import sqrt_band
from .frame import sqrt_pieces_to_solve, tuple_frame
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
    ok, side0, side3, inv, S, any_front1, any_back1, any_front2, any_back2, flat2, cx, c2 = tuple_frame(
        refract1, refract2, x0, x3, PA, NA, PB, NB, geo, geo_l, stats)
    if not ok:
        return count_in
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
        ok, mask, fallback_piece, heron_ok, heron_cut, heron = sqrt_pieces_to_solve(refract1, geo, geo_l, inv, S, cx, r1,
                                                                                   margin, biv)
        if not ok:
            continue
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


@parallel_range("x_start", CHUNK)
def solve_two_bounce_batch(refract1, refract2, x_start, x_end, P, N, eta, pieces, stop_after, out_uv, out_count, stats,
                           first, last):
    """:func:`solve_two_bounce_tuple` for every tuple t (x_start[t], x_end[t], P[t], N[t],
    eta[t]) into out_uv[t], out_count[t], stats[t], chunks [first, last) of CHUNK tuples."""
    n = x_start.shape[0]
    for ch in range(first, last):
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
