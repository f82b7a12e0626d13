"""The two-bounce pipeline of ``solve.py`` cut into batch stages, for the OpenCL back end.

``solve_two_bounce_batch`` runs every tuple start to end in one Numba kernel.  Here the same
algorithm (Fan et al. 2024, §4.2-4.3: the Bézout resultant of eq 28-29 scanned in v1, its
sign changes pinned, the candidates back-substituted and polished in path space) runs in
stages over a whole batch of tuples, so that they can run on an OpenCL device, many systems
and tuples at once:

A           per tuple and orientation (forward, reversed): the side tests, then every
            bivariate system {a = 0, b = 0} (eq 6 with 10 or 13; the Heron-step √ of
            ``heron_sqrt_fit`` where it fits and the √ pieces of eq 23 below its cut, or all
            the pieces; the refraction's two normal orientations) built by ``build_system``, normalised
            and rejected early (Bernstein test) exactly as ``_solve_system`` does, and
            packed (row i of a total-degree-d polynomial: the coefficients of u^i v^j),
            with the pieces the (u1, v1) pre-pass keeps live.
B           ``find_v_roots`` per system: det R(v) at the samples the live pieces need, the
            degeneracy test, every sign change pinned to ROOT_TOL by Illinois, the root lists.
C           ``candidates_at`` at each scan root (u1 from a(·, v1), exact map to triangle
            2, Gauss-Newton polish in path space): the paths, and which roots were
            productive.
D           ``refine_v_roots`` per system on B's samples and C's productive flags: ghost
            samples, kink flags, sub-samples, new sign changes pinned, one-signed dips
            resolved; at most a capacity of new roots per system (REFINE_CAP, within
            REFINE_BYTES).
E           candidates at the refined roots, the seeded polish of degenerate systems,
            the straight-line candidate, the statistics.

A batch runs on a device object's ``solve_batch``: ``opencl.backend.OpenCLSystemSolver`` runs
stages A-E on the device (opencl/stage_a.cl, two_bounce.cl; two waits a batch: the systems'
counts, the paths), or on CPU devices stage A on Numba (:func:`stage_a_on_host`) and B-E on
the device; :class:`NumbaSystemSolver` runs stage A on Numba, B and D with the one-kernel
path's own ``find_v_roots`` and ``refine_v_roots`` and C and E with ``stage_c`` / ``stage_e``
(:func:`solve_systems_on_host`: the tests).  Tuples with more than ``SYS_CAP`` systems, and on
OpenCL those with a system whose refined roots overflow the capacity, are solved by the
one-kernel path on the host (:func:`solve_on_host`).  Only the
order in which candidates of different systems of one tuple are tried differs from the
one-kernel path (all scan roots of a tuple before its refined roots), which can change which
of two copies of one path is kept (both polished to ~1e-15) but not the set of paths.

Stage A shares ``_solve_oriented``'s set-up (``frame``); tests/solver/test_opencl_two_bounce.py
compares the staging on Numba and on OpenCL with the one-kernel solver.  Limits:
``REFINE_LEVELS`` ≤ 1.
"""


import numpy as np

from ...runtime.jit import kernel, parallel_range, run_calls
from ...paths.two_vertex import pack_geometry
from .params import (BOTH_DIRECTIONS, CHUNK, LIVE_PREPASS, LIVE_STACK, MAX_PATHS_TWO_BOUNCE, MAX_PIECES, MAXD, N_SLOTS,
                     N_STATS, REFINE_LEVELS, SQRT_PIECES, STAT_DETS, STAT_NEAR, STAT_PATHS, STAT_ROOTS, STAT_SKIPPED,
                     V_MARGIN_APPROX, V_MARGIN_EXACT)
from ...polynomials.bivariate import bernstein_has_zero, bmax, u_degree
from .prepass import live_pieces_band
from .sqrt import sqrt_band
from .frame import sqrt_pieces_to_solve, tuple_frame
from .system import build_system
from .resultant import find_v_roots, refine_v_roots, v_major
from .solve import candidates_at, make_scratch2, seeded, solve_two_bounce_tuple, straight_candidate

SYS_CAP = 24  # systems per tuple held by stage A; a tuple with more is solved by the one-kernel path
MAX_ROOTS = 4096  # roots per system (the capacity of the one-kernel path's root list)
REFINE_BYTES = 32 << 20  # the refinement's dense output: new roots per system within this (32-256 a system) ...
REFINE_CAP = 256  # ... a system with more (planted TT: ~2 % have over 64) is refined again with MAX_ROOTS


def refine_capacity(n_systems):
    """New roots per system a device's refinement returns for a batch of n_systems: REFINE_CAP
    within REFINE_BYTES, at least 32."""
    return min(REFINE_CAP, max(32, REFINE_BYTES // (8 * max(n_systems, 1))))
DEGREES = {(False, False): (8, 15), (False, True): (8, 22), (True, False): (16, 31), (True, True): (16, 46)}


def _tri(d):
    return (d + 1) * (d + 2) // 2


def layout(refract1, refract2):
    """(stride, b_offset) of one packed system for a chain: both orientations fit."""
    da = max(DEGREES[(refract1, refract2)][0], DEGREES[(refract2, refract1)][0])
    db = max(DEGREES[(refract1, refract2)][1], DEGREES[(refract2, refract1)][1])
    return _tri(da) + _tri(db), _tri(da)


# --- stage A ---------------------------------------------------------------------------------


@kernel
def _pack(p, d, out, off):
    k = off
    for i in range(d + 1):
        for j in range(d + 1 - i):
            out[k] = p[i, j]
            k += 1


@kernel
def _unpack(src, off, d, p):
    k = off
    for i in range(d + 1):
        for j in range(d + 1 - i):
            p[i, j] = src[k]
            k += 1


@kernel
def _unpack_v_major(src, off, d, scratch, pt):
    """``_unpack`` into pt in the layout the determinants read (``resultant.v_major``), by way
    of scratch (48 x 48)."""
    _unpack(src, off, d, scratch)
    v_major(scratch, d, pt)


@kernel
def _prepare_system(biv, da, db, refract1, stats):
    """The part of ``_solve_system`` and ``_eliminate`` before the scan: normalise a and b,
    the Bernstein early exit, the u-degrees.  Returns (status, na, nb, n): status 1 to
    solve, 0 rejected early, -1 degenerate (seeded polish)."""
    a = biv[0]
    b = biv[1]
    ma = bmax(a, da)
    mb = bmax(b, db)
    if not (ma > 0.0 and mb > 0.0) or not (np.isfinite(ma) and np.isfinite(mb)):
        return -1, 0, 0, 0
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
    if da <= 20 and not bernstein_has_zero(a, da, 1e-2 if refract1 else 1e-9, biv[2, 0]):
        stats[STAT_SKIPPED] = 1
        return 0, 0, 0, 0
    na = u_degree(a, da, 1e-14)
    nb = u_degree(b, db, 1e-15)
    n = max(na, nb)
    if n == 0 or n >= MAXD:
        return -1, na, nb, n
    return 1, na, nb, n


@kernel
def _stage_a_oriented(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, rev, biv, geo, geo_l, b_offset, coef, sysint,
                      nsys, stats, pieces, live_mask, live_work):
    """``_solve_oriented`` up to the systems: the same set-up (``frame``) and system loop, each
    system stored instead of solved (sysint has room for sysint.shape[0]).  Returns the new
    system count (more than there is room for: the tuple goes to the one-kernel path)."""
    ok, side0, side3, inv, S, any_front1, any_back1, any_front2, any_back2, flat2, cx, c2 = tuple_frame(
        refract1, refract2, x0, x3, PA, NA, PB, NB, geo, geo_l, stats)
    if not ok:
        return nsys

    n_orient1 = 2 if refract1 else 1
    n_side2 = 2 if refract2 else 1
    n_pieces_sqrt = SQRT_PIECES.shape[0] if refract1 else 1
    for o1 in range(n_orient1):
        sigma1 = 1.0 if o1 == 0 else -1.0
        if refract1 and ((sigma1 > 0.0 and not any_front1) or (sigma1 < 0.0 and not any_back1)):
            continue
        s_in1 = sigma1 * (1.0 if side0 > 0.0 else -1.0)
        r1 = (1.0 / eta) if s_in1 > 0.0 else eta
        ok, mask, fallback_piece, heron_ok, heron_cut, heron = sqrt_pieces_to_solve(refract1, geo, geo_l, inv, S, cx, r1,
                                                                                   V_MARGIN_APPROX, biv)
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
                    s_in2 = -sigma2 * (1.0 if side3 > 0.0 else -1.0)
                    eta_in2 = 1.0 if s_in2 > 0.0 else eta
                    eta_out2 = eta if s_in2 > 0.0 else 1.0
                da, db = build_system(refract1, refract2, s_in1, r1, piece, S, heron, eta_in2, eta_out2,
                                       flat2, c2, geo_l, biv)
                status, na, nb, n = _prepare_system(biv, da, db, refract1, stats)
                if status == 0:
                    continue
                live = live_work[0]
                if status == 1:
                    if LIVE_PREPASS:
                        boxes = live_work[1, 0:LIVE_STACK * 4].reshape((LIVE_STACK, 4))
                        blo, bhi = sqrt_band(piece, S * S, refract1)
                        if live_pieces_band(biv[0], da, biv[1], db, V_MARGIN_APPROX if refract1 else V_MARGIN_EXACT,
                                            pieces, biv, boxes, live, blo, bhi) == 0:
                            continue  # as ``_eliminate``: no common zero near the triangle
                    else:
                        for k in range(pieces):
                            live[k] = 1
                if nsys < sysint.shape[0]:
                    sysint[nsys, 0] = rev + (2 if piece == fallback_piece else 0)  # bit 1: not refined
                    sysint[nsys, 1] = status
                    sysint[nsys, 2] = da
                    sysint[nsys, 3] = db
                    sysint[nsys, 4] = na
                    sysint[nsys, 5] = nb
                    sysint[nsys, 6] = n
                    if status == 1:
                        _pack(biv[0], da, coef[nsys], 0)
                        _pack(biv[1], db, coef[nsys], b_offset)
                        for k in range(pieces):
                            live_mask[nsys, k] = live[k]
                nsys += 1
    return nsys


@kernel
def stage_a_systems(refract1, refract2, x_start, x_end, P, N, eta, b_offset, stride, sys_cap, pieces, nsys, state, stats,
                    first, last):
    """Stage A over tuples [first, last): their system count nsys, state (0 nothing to solve, 1
    staged, 2 more than sys_cap systems: solved by the one-kernel path in stage E) and stats;
    returns the systems of the staged tuples, tuple by tuple in stage A's order: (coef (m,
    stride) packed a and b (row i of a total-degree-d polynomial: the coefficients of u^i v^j;
    the rest of a row is not written), sysint (m, 7) = (rev + 2 · not refined, status, da, db,
    na, nb, n) (bit 1: the TIR fallback's system, sign changes only, as ``_solve_oriented``),
    live (m, pieces) the scan pieces ``live_pieces`` keeps (0 for a system not to solve)).
    A tuple's systems go to a scratch of sys_cap rows and then to the output, which grows by
    doubling: the output holds the systems found, not room for sys_cap per tuple."""
    biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
    geo = np.zeros((3, 15, 3))
    live_work = np.zeros((2, MAX_PIECES + 1))
    p = max(pieces, 1)
    tuple_coef = np.empty((sys_cap, stride))
    tuple_int = np.zeros((sys_cap, 7), dtype=np.int64)
    tuple_live = np.zeros((sys_cap, p), dtype=np.int8)
    room = 2 * max(1, last - first)
    coef = np.empty((room, stride))
    sysint = np.zeros((room, 7), dtype=np.int64)
    live = np.zeros((room, p), dtype=np.int8)
    m = 0
    for t in range(first, last):
        k = _stage_a_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, tuple_coef, tuple_int, stats[t], t, biv,
                           geo, pieces, tuple_live, live_work)
        nsys[t] = max(k, 0)
        state[t] = 0 if k < 0 else (2 if k > sys_cap else 1)
        if state[t] != 1:
            continue
        if m + k > room:
            room = max(2 * room, m + k)
            coef = _grown(coef, room, m)
            sysint = _grown(sysint, room, m)
            live = _grown(live, room, m)
        for i in range(k):
            status = tuple_int[i, 1]
            for c in range(7):
                sysint[m + i, c] = tuple_int[i, c]
            if status == 1:
                coef[m + i, :] = tuple_coef[i, :]
                live[m + i, :] = tuple_live[i, :]
            else:
                live[m + i, :] = 0
        m += k
    return coef[:m], sysint[:m], live[:m]


@kernel
def _grown(a, rows, keep):
    """A copy of a with ``rows`` rows, its first ``keep`` rows a's (the rest not set)."""
    out = np.empty((rows,) + a.shape[1:], dtype=a.dtype)
    out[:keep] = a[:keep]
    return out


@kernel
def _stage_a_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, stats, t, biv, geo, pieces,
                   live_mask, live_work):
    """Stage A of tuple t: its systems into coef, sysint, live_mask (room for sysint.shape[0]
    of them); returns their count (more than the room: the tuple goes to the one-kernel
    path), or -1 when the tuple has nothing to solve."""
    for k in range(N_STATS):
        stats[k] = 0
    x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
    x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
    if not pack_geometry(x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], geo[0]) or not (eta[t] > 0.0):
        stats[STAT_SKIPPED] = 1
        return -1
    m = _stage_a_oriented(refract1, refract2, x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], eta[t], 0, biv, geo[0],
                          geo[1], b_offset, coef, sysint, 0, stats, pieces, live_mask, live_work)
    if BOTH_DIRECTIONS:
        m = _stage_a_oriented(refract2, refract1, x3, x0, P[t, 1], N[t, 1], P[t, 0], N[t, 0], eta[t], 1, biv,
                              geo[2], geo[1], b_offset, coef, sysint, m, stats, pieces, live_mask, live_work)
    return m


# --- stages C and E: candidates ---------------------------------------------------------------


@kernel
def _oriented(refract1, refract2, rev):
    if rev:
        return refract2, refract1
    return refract1, refract2


@parallel_range("x_start", CHUNK)
def stage_c(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, sys_first, state, roots, nv,
            productive, out_uv, meta, out_count, stats, first, last):
    """Candidates at the scan roots of every system, in system order, per tuple; productive
    (S, pieces) says which roots polished into a path (``_eliminate``'s flag)."""
    n = x_start.shape[0]
    for ch in range(first, last):
        biv, cf, mat, scan, geo, work, sroots, chain, lists = make_scratch2()
        for t in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            _stage_c_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, sys_first, state,
                           roots, nv, productive, out_uv, meta, out_count, stats, t, biv, geo, work, sroots, chain, lists)


@kernel
def _stage_c_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, sys_first, state, roots, nv,
                   productive, out_uv, meta, out_count, stats, t, biv, geo, work, sroots, chain, lists):
    out_count[t] = 0
    if state[t] != 1:
        return
    x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
    x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
    pack_geometry(x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], geo[0])
    pack_geometry(x3, x0, P[t, 1], N[t, 1], P[t, 0], N[t, 0], geo[2])
    th = sroots[0, 0:4]
    u_roots = sroots[1]
    coeffs = sroots[2]
    count = 0
    for s in range(sys_first[t], sys_first[t + 1]):
        if sysint[s, 1] != 1:
            continue
        rev = (sysint[s, 0] & 1) == 1
        r1, r2 = _oriented(refract1, refract2, rev)
        da = sysint[s, 2]
        db = sysint[s, 3]
        _unpack(coef[s], 0, da, biv[0])
        _unpack(coef[s], b_offset, db, biv[1])
        margin = V_MARGIN_APPROX if r1 else V_MARGIN_EXACT
        g = geo[2] if rev else geo[0]
        for iv in range(nv[s]):
            near = stats[t, STAT_NEAR]
            count = candidates_at(roots[s, iv], biv[0], da, biv[1], db, sysint[s, 4], sysint[s, 5], r1, r2,
                                   margin, g, eta[t], work, th, u_roots, coeffs, chain, lists, rev, geo[0], out_uv[t],
                                   meta[t], count, stats[t])
            productive[s, iv] = 1.0 if stats[t, STAT_NEAR] > near else 0.0
    out_count[t] = count


@parallel_range("x_start", CHUNK)
def stage_e(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sys_first, state, nv,
            ref_first, ref_count, ref_roots, out_uv, meta, out_count, stats, first, last):
    """Candidates at the refined roots, the seeded polish of degenerate systems (sysint
    status -1), the straight-line candidate after the forward systems, the statistics."""
    n = x_start.shape[0]
    for ch in range(first, last):
        biv, cf, mat, scan, geo, work, sroots, chain, lists = make_scratch2()
        for t in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            _stage_e_tuple(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sys_first, state,
                           nv, ref_first, ref_count, ref_roots, out_uv, meta, out_count, stats, t, biv, cf, mat, scan, geo,
                           work, sroots, chain, lists)


@kernel
def _stage_e_tuple(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sys_first, state, nv,
                   ref_first, ref_count, ref_roots, out_uv, meta, out_count, stats, t, biv, cf, mat, scan, geo, work, sroots,
                   chain, lists):
    if state[t] != 1:
        return
    x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
    x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
    pack_geometry(x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], geo[0])
    pack_geometry(x3, x0, P[t, 1], N[t, 1], P[t, 0], N[t, 0], geo[2])
    th = sroots[0, 0:4]
    u_roots = sroots[1]
    coeffs = sroots[2]
    count = out_count[t]
    straight = False
    for s in range(sys_first[t], sys_first[t + 1]):
        rev = (sysint[s, 0] & 1) == 1
        if rev and not straight:
            count = straight_candidate(geo[0], refract1, refract2, eta[t], work, th, out_uv[t], meta[t], count,
                                        stats[t])
            straight = True
        r1, r2 = _oriented(refract1, refract2, rev)
        g = geo[2] if rev else geo[0]
        if sysint[s, 1] == -1:
            count = seeded(g, r1, r2, eta[t], rev, geo[0], work, th, out_uv[t], meta[t], count, stats[t])
            continue
        da = sysint[s, 2]
        db = sysint[s, 3]
        if ref_count[s] > 0:
            _unpack(coef[s], 0, da, biv[0])
            _unpack(coef[s], b_offset, db, biv[1])
            margin = V_MARGIN_APPROX if r1 else V_MARGIN_EXACT
            for iv in range(ref_first[s], ref_first[s] + ref_count[s]):
                count = candidates_at(ref_roots[iv], biv[0], da, biv[1], db, sysint[s, 4], sysint[s, 5], r1,
                                       r2, margin, g, eta[t], work, th, u_roots, coeffs, chain, lists, rev, geo[0],
                                       out_uv[t], meta[t], count, stats[t])
        stats[t, STAT_ROOTS] += nv[s] + ref_count[s]
    if not straight:
        count = straight_candidate(geo[0], refract1, refract2, eta[t], work, th, out_uv[t], meta[t], count, stats[t])
    stats[t, STAT_SKIPPED] = 1 if stats[t, STAT_SKIPPED] >= (2 if BOTH_DIRECTIONS else 1) else 0
    stats[t, STAT_PATHS] = count
    out_count[t] = count


@parallel_range("tuples")
def solve_on_host(refract1, refract2, x_start, x_end, P, N, eta, pieces, tuples, out_uv, out_count, stats, first, last):
    """The one-kernel path (``solve_two_bounce_tuple``) for the tuples listed: those with more
    than SYS_CAP systems, and those a device left to the host."""
    biv, cf, mat, scan, geo, work, sroots, chain, lists = make_scratch2()
    for i in range(first, last):
        t = tuples[i]
        x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
        x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
        out_count[t] = solve_two_bounce_tuple(refract1, refract2, x0, x3, P[t], N[t], eta[t], pieces, 0, biv, cf, mat,
                                              scan, geo, work, sroots, chain, lists, out_uv[t], stats[t])


# --- stages B and D on Numba: the resultant scan device for the tests ---------------------------


@kernel
def _scan_scratch():
    a = np.zeros((MAXD + 1, MAXD + 1))
    scratch = np.zeros((MAXD + 1, MAXD + 1))
    b = np.zeros((MAXD + 1, MAXD + 1))
    cf = np.zeros((2, MAXD + 2))
    mat = np.zeros((MAXD + 1, MAXD + 1))
    scan = np.zeros((9, MAX_PIECES + 1))
    out = np.zeros((1, MAX_ROOTS))
    st = np.zeros(N_STATS, dtype=np.int64)
    return a, scratch, b, cf, mat, scan, out, st


@kernel
def _load_system(coef, sysint3, b_offset, live_mask, s, pieces, scratch, a, b, scan):
    """System s v-major into a, b; its live pieces into scan[7] (``find_v_roots``'s live)."""
    _unpack_v_major(coef[s], 0, sysint3[s, 0], scratch, a)
    _unpack_v_major(coef[s], b_offset, sysint3[s, 1], scratch, b)
    for k in range(pieces):
        scan[7, k] = live_mask[s, k]


@parallel_range("margin")
def numba_scan(coef, sysint3, b_offset, live_mask, margin, solve, pieces, sg, lg, piece_of, nv, roots, dets, first, last):
    """``find_v_roots`` (the one-kernel path's own function) for every system s with solve[s]:
    nv[s] roots in roots[s] (-1: degenerate), the samples' signs and raw log|det| in sg, lg
    (S, pieces + 1) and each root's piece in piece_of (S, pieces), for :func:`numba_refine`."""
    a, scratch, b, cf, mat, scan, out, st = _scan_scratch()
    for s in range(first, last):
        nv[s] = 0
        dets[s] = 0
        if not solve[s]:
            continue
        _load_system(coef, sysint3, b_offset, live_mask, s, pieces, scratch, a, b, scan)
        st[STAT_DETS] = 0
        nv[s] = find_v_roots(a, sysint3[s, 0], b, sysint3[s, 1], sysint3[s, 2], -margin[s], 1.0 + margin[s], pieces,
                             scan[7], cf, mat, scan, roots[s], st)
        dets[s] = st[STAT_DETS]
        for k in range(pieces + 1):
            sg[s, k] = scan[1, k]
            lg[s, k] = scan[2, k]
        for k in range(pieces):
            piece_of[s, k] = scan[4, k]


@parallel_range("margin")
def numba_refine(coef, sysint3, b_offset, live_mask, margin, refined, pieces, sg, lg, piece_of, nv, roots, productive, cap,
                 ref_roots, ref_count, dets, first, last):
    """``refine_v_roots`` (the one-kernel path's own function) for every system s with
    refined[s], on :func:`numba_scan`'s samples: its new roots in ref_roots[s, :ref_count[s]],
    at most cap of them; ref_count[s] = -1 where the cap may have cut them short (count within
    2 of it: a dip pins two at once)."""
    a, scratch, b, cf, mat, scan, out, st = _scan_scratch()
    for s in range(first, last):
        ref_count[s] = 0
        dets[s] = 0
        if not refined[s]:
            continue
        _load_system(coef, sysint3, b_offset, live_mask, s, pieces, scratch, a, b, scan)
        lo = -margin[s]
        h = (1.0 + margin[s] - lo) / pieces  # find_v_roots's samples, the same doubles
        for k in range(pieces + 1):
            scan[0, k] = lo + k * h
            scan[1, k] = sg[s, k]
            scan[2, k] = lg[s, k]
        m = nv[s]
        for k in range(pieces):
            scan[4, k] = piece_of[s, k]
            scan[5, k] = productive[s, k]
        for i in range(m):
            out[0, i] = roots[s, i]
        st[STAT_DETS] = 0
        end = min(m + cap, MAX_ROOTS)  # MAX_ROOTS: the one-kernel path's own capacity
        count = refine_v_roots(a, sysint3[s, 0], b, sysint3[s, 1], sysint3[s, 2], pieces, scan[7], cf, mat, scan,
                               out[0, :end], m, scan[5], st)
        dets[s] = st[STAT_DETS]
        if end < MAX_ROOTS and count + 2 > end:
            ref_count[s] = -1
            continue
        ref_count[s] = count - m
        for i in range(m, count):
            ref_roots[s, i - m] = out[0, i]


class NumbaSystemSolver:
    """Stages A-E on Numba (:meth:`solve_batch`): A by ``stage_a``, B and D system by system
    with the one-kernel path's own ``find_v_roots`` and ``refine_v_roots`` (:meth:`scan`,
    :meth:`refine`), C and E by ``stage_c`` / ``stage_e``: the staged pipeline without OpenCL
    (the tests), and the re-run of a system whose refined roots overflow the capacity."""

    name = "numba"

    def solve_batch(self, refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, out_uv,
                    out_count, stats):
        """Stages A-E of one batch (``_solve_batch``): :func:`stage_a_on_host`, then
        :func:`solve_systems_on_host`.  Returns (state, left) as
        ``opencl.backend.OpenCLSystemSolver.solve_batch``."""
        state, batch = stage_a_on_host(refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap,
                                       stats)
        out_count[state != 1] = 0
        return state, solve_systems_on_host(self, batch, out_uv, out_count, stats)

    def load(self, coef, sysint3, b_offset, live_mask, margin, pieces):
        """The packed systems coef (S, stride), sysint3 (S, 3) int32 = (da, db, n), their live
        scan pieces (S, pieces) int8 and v margins (S,): the scan runs over [-margin, 1 + margin]."""
        self.args = (coef, sysint3, b_offset, live_mask, margin)
        self.pieces = pieces

    def scan(self, solve):
        """``find_v_roots`` of the systems with solve (S,) bool: (nv (S,), -1 for a degenerate
        system; roots (S, pieces) with nv[s] of them in row s; determinants per system)."""
        S = solve.shape[0]
        p = max(self.pieces, 1)
        self.sg = np.zeros((S, self.pieces + 1))
        self.lg = np.zeros((S, self.pieces + 1))
        self.piece_of = np.zeros((S, p))
        self.nv = np.zeros(S, dtype=np.int64)
        self.roots = np.zeros((S, p))
        dets = np.zeros(S, dtype=np.int64)
        if S:
            numba_scan(*self.args, solve.astype(np.bool_), self.pieces, self.sg, self.lg, self.piece_of, self.nv,
                       self.roots, dets)
        return self.nv.copy(), self.roots, dets

    def refine(self, productive, refined, cap=None):
        """``refine_v_roots`` of the systems with refined (S,) bool, the productive scan roots
        (S, pieces) from stage C: (ref_count (S,), -1 where cut short by cap; ref_roots (S, cap);
        determinants per system)."""
        S = refined.shape[0]
        cap = REFINE_CAP if cap is None else cap
        ref_roots = np.zeros((S, cap))
        ref_count = np.zeros(S, dtype=np.int64)
        dets = np.zeros(S, dtype=np.int64)
        if S:
            numba_refine(*self.args, refined.astype(np.bool_), self.pieces, self.sg, self.lg, self.piece_of,
                         np.maximum(self.nv, 0), self.roots, np.ascontiguousarray(productive, dtype=np.float64),
                         cap, ref_roots, ref_count, dets)
        return ref_count, ref_roots, dets


class Systems:
    """One batch's staged systems (stage A's output, compacted) and its tuples' inputs."""

    def __init__(self, refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sysint3, sys_first,
                 state, live_mask, margin, owner):
        self.refract1, self.refract2 = refract1, refract2
        self.x_start, self.x_end, self.P, self.N, self.eta = x_start, x_end, P, N, eta
        self.pieces, self.b_offset = pieces, b_offset
        self.coef, self.sysint, self.sysint3, self.sys_first, self.state = coef, sysint, sysint3, sys_first, state
        self.live_mask, self.margin, self.owner = live_mask, margin, owner
        self.S = coef.shape[0]


def solve_systems_on_host(dev, b, out_uv, out_count, stats):
    """Stages B-E of a batch with stages C and E on Numba: the resultant scan and its
    refinement by ``dev`` (load / scan / refine); a system whose refined roots overflow the
    device's capacity is refined again here with the one-kernel path's capacity.  Fills the
    staged tuples' out_uv, out_count, stats; returns the tuples left to the one-kernel path
    (none)."""
    refract1, refract2, x_start, x_end, P, N, eta = b.refract1, b.refract2, b.x_start, b.x_end, b.P, b.N, b.eta
    pieces, b_offset, coef, sysint3, sys_first, state = b.pieces, b.b_offset, b.coef, b.sysint3, b.sys_first, b.state
    live_mask, margin, S, nb = b.live_mask, b.margin, b.S, x_start.shape[0]
    sysint = b.sysint.copy()
    # stage B: the sign scan and its roots (find_v_roots), on the device
    dev.load(coef, sysint3, b_offset, live_mask, margin, pieces)
    nv, roots, dets_per_sys = dev.scan(sysint[:, 1] == 1)
    sysint[nv < 0, 1] = -1  # degenerate: the seeded polish in stage E
    nv = np.maximum(nv, 0).astype(np.int64)

    # stage C: candidates at the scan roots
    productive = np.zeros((S, max(pieces, 1)))
    meta = np.zeros((nb, MAX_PATHS_TWO_BOUNCE + 1, 2))
    stage_c(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, sys_first, state, roots, nv,
            productive, out_uv, meta, out_count, stats)

    # stage D: the refinement (refine_v_roots), on the device; a system whose new roots
    # overflow the device's capacity is refined again on the host
    refined = (sysint[:, 1] == 1) & ((sysint[:, 0] & 2) == 0)  # the TIR fallback's system is not refined
    if REFINE_LEVELS and S:
        cap = refine_capacity(S)
        ref_count, ref_dense, dets = dev.refine(productive, refined, cap)
        over = np.flatnonzero(ref_count < 0)
        if over.size:
            host = NumbaSystemSolver()
            host.load(coef[over], sysint3[over], b_offset, live_mask[over], margin[over], pieces)
            host.scan(np.ones(over.size, dtype=bool))  # the samples refine_v_roots starts from
            ref_count_h, ref_h, dets[over] = host.refine(productive[over], np.ones(over.size, dtype=bool), cap=MAX_ROOTS)
        dets_per_sys += dets
        ref_first = np.arange(S, dtype=np.int64) * cap
        ref_roots = ref_dense.ravel()
        if over.size:
            ref_count[over] = ref_count_h
            ref_first[over] = ref_roots.size + np.arange(over.size) * ref_h.shape[1]
            ref_roots = np.concatenate([ref_roots, ref_h.ravel()])
    else:
        ref_count = np.zeros(S, dtype=np.int64)
        ref_first = np.zeros(S, dtype=np.int64)
        ref_roots = np.zeros(1)

    # stage E: candidates at the refined roots, seeded polish, straight line, statistics
    stage_e(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sys_first, state, nv,
            ref_first, ref_count, ref_roots, out_uv, meta, out_count, stats)
    per_tuple = np.zeros(nb, dtype=np.int64)
    np.add.at(per_tuple, b.owner, dets_per_sys.astype(np.int64))
    stats[:, STAT_DETS] += np.where(state == 1, per_tuple, 0)
    return np.zeros(nb, dtype=bool)


# --- the driver ---------------------------------------------------------------------------------

BATCH_BYTES = 64 << 20  # stage A's per-batch system store


def solve_staged(device, refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats,
                 batch=None, sys_cap=SYS_CAP):
    """All paths of a batch of two-bounce tuples, stages A-E (module docstring); fills
    out_uv (n, MAX_PATHS_TWO_BOUNCE, 4), out_count (n,), stats (n, N_STATS) like
    ``solve_two_bounce_batch``.  ``device``: an object whose ``solve_batch`` runs stages A-E
    of a batch (:class:`NumbaSystemSolver`, ``opencl.backend.OpenCLSystemSolver``).  ``batch``: tuples
    per pass (default: stage A's store within the device's ``batch_bytes`` or BATCH_BYTES);
    ``sys_cap``: systems per tuple held by stage A (a tuple with more is solved by the
    one-kernel path)."""
    if REFINE_LEVELS not in (0, 1):
        raise NotImplementedError("the staged two-bounce path implements REFINE_LEVELS <= 1")
    stride, b_offset = layout(refract1, refract2)
    n = x_start.shape[0]
    if batch is None:
        store = getattr(device, "batch_bytes", None) or BATCH_BYTES  # a device may want larger batches (GPUs)
        batch = max(16, store // (sys_cap * stride * 8))
    for t0 in range(0, n, batch):
        t1 = min(n, t0 + batch)
        _solve_batch(device, refract1, refract2, x_start[t0:t1], x_end[t0:t1], P[t0:t1], N[t0:t1], eta[t0:t1], pieces,
                     stride, b_offset, sys_cap, out_uv[t0:t1], out_count[t0:t1], stats[t0:t1])


def _solve_batch(dev, refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, out_uv, out_count,
                 stats):
    state, left = dev.solve_batch(refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, out_uv,
                                  out_count, stats)
    # the one-kernel path for tuples with more than sys_cap systems, and those the device left
    host = np.flatnonzero((state == 2) | left).astype(np.int64)
    if host.size:
        solve_on_host(refract1, refract2, x_start, x_end, P, N, eta, pieces, host, out_uv, out_count, stats)


def stage_a_on_host(refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, stats):
    """Stage A on Numba over a batch (:func:`stage_a_systems`, CHUNK tuples a call on numba's
    threads), its systems compacted tuple by tuple: (state (n,), :class:`Systems`)."""
    nb = x_start.shape[0]
    nsys = np.zeros(nb, dtype=np.int64)
    state = np.zeros(nb, dtype=np.int64)
    inputs = [np.ascontiguousarray(a, dtype=np.float64) for a in (x_start, x_end, P, N, eta)]
    ranges = [(a, min(nb, a + CHUNK)) for a in range(0, nb, CHUNK)]
    parts = run_calls(lambda r: stage_a_systems(bool(refract1), bool(refract2), *inputs, b_offset, stride, sys_cap, pieces, nsys,
                                                state, stats, r[0], r[1]), ranges)
    coef = np.concatenate([c for c, _, _ in parts]) if parts else np.zeros((0, stride))
    sysint = np.concatenate([i for _, i, _ in parts]) if parts else np.zeros((0, 7), dtype=np.int64)
    live_mask = np.concatenate([v for _, _, v in parts]) if parts else np.zeros((0, max(pieces, 1)), dtype=np.int8)
    m = np.where(state == 1, nsys, 0)
    sys_first = np.concatenate([[0], np.cumsum(m)]).astype(np.int64)
    S = int(sys_first[-1])
    owner = np.repeat(np.arange(nb), m)
    sysint3 = np.ascontiguousarray(sysint[:, [2, 3, 6]], dtype=np.int32)
    r1_oriented = np.where((sysint[:, 0] & 1) == 1, refract2, refract1) if S else np.zeros(0, dtype=bool)
    margin = np.where(r1_oriented, V_MARGIN_APPROX, V_MARGIN_EXACT)
    return state, Systems(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sysint3, sys_first,
                          state, live_mask, margin, owner)
