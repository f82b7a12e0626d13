"""The two-bounce pipeline of ``solve.py`` cut into batch stages, for the OpenCL back end.

``solve_two_bounce_batch`` runs every tuple start to end in one Numba kernel.  Here the same
algorithm (Fan et al. 2024, §4.2-4.3: the Bézout resultant of eq 28-29 scanned in v1, its
sign changes pinned, the candidates back-substituted and polished in path space) runs in
stages over a whole batch of tuples, so that the expensive part — the determinant of the
Bézout matrix R(v1) (eq 29), evaluated some 10³-10⁵ times per tuple — can run on an OpenCL
device (``opencl/two_bounce.cl``), many systems at once:

A (Numba)   per tuple and orientation (forward, reversed): the side tests, then every
            bivariate system {a = 0, b = 0} (eq 6 with 10 or 13; the Heron-step √ of
            ``heron_sqrt_fit`` where it fits and the √ pieces of eq 23 below its cut, or all
            the pieces; the refraction's two normal orientations) built by ``build_system``, normalised
            and rejected early (Bernstein test) exactly as ``_solve_system`` does, and
            packed (row i of a total-degree-d polynomial: the coefficients of u^i v^j).
B (device)  the piecewise sign scan of ``find_v_roots``: det R(v) at the pieces' ends,
            then every sign change pinned to ROOT_TOL by the Illinois iteration.
C (Numba)   ``candidates_at`` at each scan root (u1 from a(·, v1), exact map to triangle
            2, Gauss-Newton polish in path space): the paths, and which roots were
            productive.
D (device)  ``refine_v_roots``: the ghost samples outside the range, the sub-samples
            (``SUB_SAMPLES``) of the pieces around productive roots and next to convex
            kinks of the deflated log|det| (with the extra samples at the ends of each run of
            flagged pieces) on the device, new sign changes pinned on the device; the
            bookkeeping (kink rule, deflation, noisy pieces, one-signed dips) runs here, in
            the same order as there, and so do the few determinants that resolve a dip
            (``resolve_dip``: Numba on the host, 3-8 per dip).
E (Numba)   candidates at the refined roots, the seeded polish of degenerate systems,
            the straight-line candidate, the statistics.

Every stage reuses the inner functions of the package's modules; only the order in which
candidates of different systems of one tuple are tried differs (all scan roots of a tuple
before its refined roots), which can change which of two copies of one path is kept
(both polished to ~1e-15) but not the set of paths.  A stage-B/D "device" written in Numba
(:class:`NumbaDeterminants`) runs the same staging without OpenCL, for the tests.

Stage A shares ``_solve_oriented``'s set-up (``frame``); tests/solver/test_opencl_two_bounce.py
compares the staging on Numba with the one-kernel solver.  Limits: ``REFINE_LEVELS`` ≤ 1;
a tuple with more than ``SYS_CAP`` systems is solved by the one-kernel path in stage E.
"""


import numpy as np

from ...runtime.jit import kernel, parallel_range
from ...paths.two_vertex import pack_geometry
from .params import (BOTH_DIRECTIONS, CHUNK, KINK, LIVE_PREPASS, LIVE_STACK, MAX_PATHS_TWO_BOUNCE, MAX_PIECES, MAXD,
                     N_SLOTS, N_STATS, NOISY_CHANGES, REFINE_LEVELS, SQRT_PIECES, STAT_DETS, STAT_NEAR, STAT_PATHS,
                     STAT_ROOTS, STAT_SKIPPED, SUB_SAMPLES, V_MARGIN_APPROX, V_MARGIN_EXACT)
from ...polynomials.bivariate import bernstein_has_zero, bmax, u_degree
from .prepass import live_pieces_band
from .sqrt import sqrt_band
from .frame import sqrt_pieces_to_solve, tuple_frame
from .system import build_system
from .resultant import deflate, det_checked, illinois, refine_flags_one, resolve_dip, v_major
from .solve import candidates_at, make_scratch2, seeded, solve_two_bounce_tuple, straight_candidate

SYS_CAP = 24  # systems per tuple held by stage A; a tuple with more is solved by the one-kernel path
MAX_ROOTS = 4096  # roots per system (the capacity of the one-kernel path's root list)
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


@parallel_range("x_start", CHUNK)
def stage_a(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, nsys, state, stats, pieces, live_mask, first, last):
    """Stage A over a batch: systems per tuple into coef (n, cap, stride) and sysint
    (n, cap, 7) = (rev + 2 · not refined, status, da, db, na, nb, n) (bit 1: the TIR fallback's
    system, sign changes only, as ``_solve_oriented``), their count nsys (n,), and state (n,):
    0 nothing to solve, 1 staged, 2 more than cap systems (solved by the one-kernel path in
    stage E); live_mask (n, cap, pieces): the scan pieces of each system ``live_pieces`` keeps."""
    n = x_start.shape[0]
    for ch in range(first, last):
        biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
        geo = np.zeros((3, 15, 3))
        live_work = np.zeros((2, MAX_PIECES + 1))
        for t in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            _stage_a_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, nsys, state, stats, t,
                           biv, geo, pieces, live_mask, live_work)


@kernel
def _stage_a_tuple(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, nsys, state, stats, t, biv, geo,
                   pieces, live_mask, live_work):
    for k in range(N_STATS):
        stats[t, k] = 0
    x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
    x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
    nsys[t] = 0
    if not pack_geometry(x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], geo[0]) or not (eta[t] > 0.0):
        stats[t, STAT_SKIPPED] = 1
        state[t] = 0
        return
    m = _stage_a_oriented(refract1, refract2, x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], eta[t], 0, biv, geo[0],
                          geo[1], b_offset, coef[t], sysint[t], 0, stats[t], pieces, live_mask[t], live_work)
    if BOTH_DIRECTIONS:
        m = _stage_a_oriented(refract2, refract1, x3, x0, P[t, 1], N[t, 1], P[t, 0], N[t, 0], eta[t], 1, biv,
                              geo[2], geo[1], b_offset, coef[t], sysint[t], m, stats[t], pieces, live_mask[t], live_work)
    nsys[t] = m
    state[t] = 2 if m > sysint.shape[1] else 1


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
    status -1), the straight-line candidate after the forward systems, the statistics;
    tuples with more than SYS_CAP systems are solved here by the one-kernel path."""
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
    if state[t] == 0:
        out_count[t] = 0
        return
    x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
    x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
    if state[t] == 2:
        out_count[t] = solve_two_bounce_tuple(refract1, refract2, x0, x3, P[t], N[t], eta[t], pieces, 0, biv, cf,
                                              mat, scan, geo, work, sroots, chain, lists, out_uv[t], stats[t])
        return
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


# --- stage D bookkeeping (the determinants themselves run on the device) -----------------------


@parallel_range("vs")
def refine_flags(vs, lgs, ghost, roots, nv, piece_of, productive, pieces, live, flags, first, last):
    """``refine_v_roots``'s choice of pieces: lgs (S, pieces + 1) and the ghost samples
    (S, 2: raw log|det| a piece below and above the range) are deflated by the scan roots;
    flags[s, k] = 1 for a piece next to a convex kink or around a productive root
    (``refine_flags_one``)."""
    for s in range(first, last):
        h = vs[s, 1] - vs[s, 0]
        g_lo = deflate(vs[s, 0] - h, ghost[s, 0], roots[s], nv[s])
        g_hi = deflate(vs[s, pieces] + h, ghost[s, 1], roots[s], nv[s])
        for k in range(pieces + 1):
            lgs[s, k] = deflate(vs[s, k], lgs[s, k], roots[s], nv[s])
        refine_flags_one(lgs[s], g_lo, g_hi, roots[s], nv[s], piece_of[s], productive[s], pieces, live[s], flags[s])


@parallel_range("ss")
def refine_brackets(job_sys, sv, ss, roots, nv, bracket, first, last):
    """Per flagged piece f (sub-samples sv[f], their signs ss[f]): bracket[f, k] = 1 for a
    new sign change in sub-piece k to pin (``_refine_interval``: none in a noisy piece, none
    in a sub-piece holding a scan root)."""
    M = ss.shape[1] - 1
    for f in range(first, last):
        s = job_sys[f]
        changes = 0
        for k in range(M):
            bracket[f, k] = 0
            if ss[f, k] != ss[f, k + 1]:
                changes += 1
        if changes > NOISY_CHANGES:
            continue
        for k in range(M):
            if ss[f, k] != ss[f, k + 1] and ss[f, k] != 0 and ss[f, k + 1] != 0:
                known = False
                for i in range(nv[s]):
                    if roots[s, i] >= sv[f, k] and roots[s, i] <= sv[f, k + 1]:
                        known = True
                if not known:
                    bracket[f, k] = 1


@parallel_range("nv")
def refine_assemble(flag_first, svx, ssx, slx, has_right, bracket, pinned, roots, nv, ref_first, ref_count, ref_roots,
                    coef, sysint3, b_offset, dip_dets, first, last):
    """The refined roots of each system in ``_refine_interval``'s order (pieces ascending;
    per piece its pinned sign changes, then its one-signed dips of the log|det| deflated by
    every root found so far), into ref_roots[ref_first[s]:] (ref_count[s] of them).

    svx, ssx, slx (F, M + 3): per flagged piece its M + 1 sub-samples at 1 .. M + 1, the
    sample before it at 0 (the previous piece's of the run, or the extra one of a run's
    first piece) and, for the last piece of a run (``has_right``), the extra one after it at
    M + 2.  A dip is resolved (``resolve_dip``) with Numba's determinants on the host, the
    one-kernel path's own function: 3-8 determinants per dip, a few per cent of the work
    (dip_dets[s] counts them)."""
    M = svx.shape[1] - 3
    for s in range(first, last):
        nf = flag_first[s + 1] - flag_first[s]
        buf = np.empty(nv[s] + (2 * M - 1) * nf)
        cap = min(buf.shape[0], MAX_ROOTS)
        out = buf[:cap]
        lg = np.empty(M + 3)
        a = np.empty((MAXD + 1, MAXD + 1))
        scratch = np.empty((MAXD + 1, MAXD + 1))
        b = np.empty((MAXD + 1, MAXD + 1))
        cf = np.empty((2, MAXD + 2))
        mat = np.empty((MAXD + 1, MAXD + 1))
        st = np.zeros(N_STATS, dtype=np.int64)
        loaded = False
        for i in range(nv[s]):
            buf[i] = roots[s, i]
        count = nv[s]
        for f in range(flag_first[s], flag_first[s + 1]):
            changes = 0
            for k in range(1, M + 1):
                if ssx[f, k] != ssx[f, k + 1]:
                    changes += 1
            if changes > NOISY_CHANGES:
                continue
            for k in range(M):
                if bracket[f, k] and count < cap:
                    buf[count] = pinned[f, k]
                    count += 1
            k_hi = M + 2 if has_right[f] else M + 1
            for k in range(k_hi + 1):
                lg[k] = deflate(svx[f, k], slx[f, k], buf, count)
            for k in range(1, (M + 1 if has_right[f] else M) + 1):
                if count < cap and lg[k - 1] + lg[k + 1] - 2.0 * lg[k] > KINK and ssx[f, k] == ssx[f, k - 1] \
                        and ssx[f, k] == ssx[f, k + 1] and ssx[f, k] != 0 and lg[k] < lg[k - 1] and lg[k] < lg[k + 1]:
                    if (k - 2 < 0 or lg[k - 2] >= lg[k - 1]) and (k + 2 > k_hi or lg[k + 2] >= lg[k + 1]):
                        if not loaded:
                            _unpack_v_major(coef[s], 0, sysint3[s, 0], scratch, a)
                            _unpack_v_major(coef[s], b_offset, sysint3[s, 1], scratch, b)
                            loaded = True
                        count = resolve_dip(a, sysint3[s, 0], b, sysint3[s, 1], sysint3[s, 2], svx[f, k - 1], svx[f, k],
                                             svx[f, k + 1], ssx[f, k], lg[k - 1], lg[k], lg[k + 1], cf, mat, out, count, st)
                    else:
                        buf[count] = svx[f, k]  # noise dip: its deepest sample is a candidate
                        count += 1
        dip_dets[s] = st[STAT_DETS]
        ref_count[s] = count - nv[s]
        for i in range(nv[s], count):
            ref_roots[ref_first[s] + i - nv[s]] = buf[i]


# --- a Numba "device" for stages B and D (reference and tests) ---------------------------------


@parallel_range("job_sys", 32)
def numba_det_batch(coef, sysint3, b_offset, job_sys, job_v, out_sign, out_log, out_dets, first, last):
    """det jobs with ``det_checked`` (the one-kernel path's own function)."""
    n_jobs = job_sys.shape[0]
    chunk = 32
    for c in range(first, last):
        a = np.zeros((MAXD + 1, MAXD + 1))
        scratch = np.empty((MAXD + 1, MAXD + 1))
        b = np.zeros((MAXD + 1, MAXD + 1))
        cf = np.zeros((2, MAXD + 2))
        mat = np.zeros((MAXD + 1, MAXD + 1))
        st = np.zeros(N_STATS, dtype=np.int64)
        loaded = -1
        for t in range(c * chunk, min(n_jobs, (c + 1) * chunk)):
            s = job_sys[t]
            if s != loaded:
                _unpack_v_major(coef[s], 0, sysint3[s, 0], scratch, a)
                _unpack_v_major(coef[s], b_offset, sysint3[s, 1], scratch, b)
                loaded = s
            before = st[STAT_DETS]
            sg, lg = det_checked(a, sysint3[s, 0], b, sysint3[s, 1], sysint3[s, 2], job_v[t], cf, mat, st)
            out_sign[t] = sg
            out_log[t] = lg
            out_dets[t] = st[STAT_DETS] - before


@parallel_range("job_sys", 8)
def numba_illinois_batch(coef, sysint3, b_offset, job_sys, job_f, job_s, out_root, out_dets, first, last):
    """Illinois jobs (lo, hi, log lo, log hi; sign lo, sign hi) with ``illinois``."""
    n_jobs = job_sys.shape[0]
    chunk = 8
    for c in range(first, last):
        a = np.zeros((MAXD + 1, MAXD + 1))
        scratch = np.empty((MAXD + 1, MAXD + 1))
        b = np.zeros((MAXD + 1, MAXD + 1))
        cf = np.zeros((2, MAXD + 2))
        mat = np.zeros((MAXD + 1, MAXD + 1))
        st = np.zeros(N_STATS, dtype=np.int64)
        loaded = -1
        for t in range(c * chunk, min(n_jobs, (c + 1) * chunk)):
            s = job_sys[t]
            if s != loaded:
                _unpack_v_major(coef[s], 0, sysint3[s, 0], scratch, a)
                _unpack_v_major(coef[s], b_offset, sysint3[s, 1], scratch, b)
                loaded = s
            before = st[STAT_DETS]
            out_root[t] = illinois(a, sysint3[s, 0], b, sysint3[s, 1], sysint3[s, 2], job_f[t, 0], job_f[t, 1],
                                    job_s[t, 0], job_f[t, 2], job_s[t, 1], job_f[t, 3], cf, mat, st)
            out_dets[t] = st[STAT_DETS] - before


class NumbaDeterminants:
    """Stages B and D on Numba (the same functions as the one-kernel path): the staged
    pipeline without OpenCL, to test the staging itself."""

    name = "numba"

    def load(self, coef, sysint3, b_offset):
        self.coef, self.sysint3, self.b_offset = coef, sysint3, b_offset

    def dets(self, job_sys, job_v):
        n = job_sys.shape[0]
        sign = np.zeros(n, dtype=np.int32)
        log = np.zeros(n)
        dets = np.zeros(n, dtype=np.int32)
        if n:
            numba_det_batch(self.coef, self.sysint3, self.b_offset, job_sys, job_v, sign, log, dets)
        return sign, log, dets

    def illinois(self, job_sys, job_f, job_s):
        n = job_sys.shape[0]
        root = np.zeros(n)
        dets = np.zeros(n, dtype=np.int32)
        if n:
            numba_illinois_batch(self.coef, self.sysint3, self.b_offset, job_sys, job_f, job_s, root, dets)
        return root, dets


# --- the driver ---------------------------------------------------------------------------------

BATCH_BYTES = 64 << 20  # stage A's per-batch system store


def solve_staged(det_device, refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats,
                 batch=None, sys_cap=SYS_CAP):
    """All paths of a batch of two-bounce tuples, stages A-E (module docstring); fills
    out_uv (n, MAX_PATHS_TWO_BOUNCE, 4), out_count (n,), stats (n, N_STATS) like
    ``solve_two_bounce_batch``.  ``det_device``: an object with load / dets / illinois
    (:class:`NumbaDeterminants`, ``opencl.backend.OpenCLDeterminants``).  ``batch``: tuples
    per pass (default: stage A's store within BATCH_BYTES); ``sys_cap``: systems per tuple
    held by stage A (a tuple with more is solved by the one-kernel path)."""
    if REFINE_LEVELS not in (0, 1):
        raise NotImplementedError("the staged two-bounce path implements REFINE_LEVELS <= 1")
    stride, b_offset = layout(refract1, refract2)
    n = x_start.shape[0]
    if batch is None:
        batch = max(16, BATCH_BYTES // (sys_cap * stride * 8))
    for t0 in range(0, n, batch):
        t1 = min(n, t0 + batch)
        _solve_batch(det_device, refract1, refract2, x_start[t0:t1], x_end[t0:t1], P[t0:t1], N[t0:t1], eta[t0:t1], pieces,
                     stride, b_offset, sys_cap, out_uv[t0:t1], out_count[t0:t1], stats[t0:t1])


def _solve_batch(dev, refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, out_uv, out_count,
                 stats):
    nb = x_start.shape[0]
    # coef is not cleared: of a system's row only its packed a and b are ever read (_unpack, the
    # device's coeffs_at), and stage A writes them; the live mask is 0 / 1 (int8: an eighth of
    # the bytes to clear)
    coef = np.empty((nb, sys_cap, stride))
    sysint = np.zeros((nb, sys_cap, 7), dtype=np.int64)
    nsys = np.zeros(nb, dtype=np.int64)
    state = np.zeros(nb, dtype=np.int64)
    live_mask = np.zeros((nb, sys_cap, max(pieces, 1)), dtype=np.int8)
    stage_a(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, nsys, state, stats, pieces, live_mask)
    # compact: the systems of staged tuples, tuple by tuple in stage A's order
    m = np.where(state == 1, nsys, 0)
    sys_first = np.concatenate([[0], np.cumsum(m)]).astype(np.int64)
    S = int(sys_first[-1])
    owner = np.repeat(np.arange(nb), m)
    slot = np.arange(S) - np.repeat(sys_first[:-1], m)
    coef = np.ascontiguousarray(coef[owner, slot])
    sysint = np.ascontiguousarray(sysint[owner, slot])
    live_mask = np.ascontiguousarray(live_mask[owner, slot])
    sysint3 = np.ascontiguousarray(sysint[:, [2, 3, 6]], dtype=np.int32)
    dets_per_sys = np.zeros(S, dtype=np.int64)
    dev.load(coef, sysint3, b_offset)

    # stage B: the sign scan (find_v_roots) ...
    r1_oriented = np.where((sysint[:, 0] & 1) == 1, refract2, refract1) if S else np.zeros(0, dtype=bool)
    margin = np.where(r1_oriented, V_MARGIN_APPROX, V_MARGIN_EXACT)
    lo = -margin
    hi = 1.0 + margin
    h = (hi - lo) / pieces
    vs = lo[:, None] + np.arange(pieces + 1)[None, :] * h[:, None]
    solve = np.flatnonzero(sysint[:, 1] == 1) if S else np.zeros(0, dtype=np.int64)
    # the samples find_v_roots takes: those of the live pieces and the neighbours their kink
    # test needs (sample k for the pieces k - 2 .. k + 1); the others hold sign 2
    padded = np.pad(live_mask != 0, ((0, 0), (2, 2)))
    need = padded[:, 0:pieces + 1] | padded[:, 1:pieces + 2] | padded[:, 2:pieces + 3] | padded[:, 3:pieces + 4]
    need[sysint[:, 1] != 1] = False
    sg = np.full((S, pieces + 1), 2, dtype=np.int32)
    lg = np.zeros((S, pieces + 1))
    ns, nk = np.nonzero(need)
    sign, log, dets = dev.dets(ns.astype(np.int32), np.ascontiguousarray(vs[ns, nk]))
    sg[ns, nk] = sign
    lg[ns, nk] = log
    np.add.at(dets_per_sys, ns, dets)
    degenerate = np.zeros(S, dtype=bool)
    degenerate[solve] = 2 * np.count_nonzero((sg[solve] == 0) & need[solve], axis=1) > np.count_nonzero(need[solve], axis=1)
    sysint[degenerate, 1] = -1
    live = sysint[:, 1] == 1
    in_live = (live_mask != 0) & live[:, None]
    change = (sg[:, :-1] != sg[:, 1:]) & (sg[:, :-1] != 0) & (sg[:, 1:] != 0) & in_live
    zero = (sg[:, :-1] == 0) & in_live
    picked = change | zero
    nv = np.count_nonzero(picked, axis=1).astype(np.int64)
    rank = np.cumsum(picked, axis=1) - 1
    roots = np.zeros((S, max(pieces, 1)))
    piece_of = np.zeros((S, max(pieces, 1)), dtype=np.int64)
    ps, pk = np.nonzero(picked)
    piece_of[ps, rank[ps, pk]] = pk
    zs, zk = np.nonzero(zero)
    roots[zs, rank[zs, zk]] = vs[zs, zk]
    # ... and its sign changes pinned (Illinois)
    cs, ck = np.nonzero(change)
    root, dets = dev.illinois(cs.astype(np.int32), np.ascontiguousarray(np.column_stack([vs[cs, ck], vs[cs, ck + 1], lg[cs, ck], lg[cs, ck + 1]])),
                              np.ascontiguousarray(np.column_stack([sg[cs, ck], sg[cs, ck + 1]]), dtype=np.int32))
    roots[cs, rank[cs, ck]] = root
    np.add.at(dets_per_sys, cs, dets)

    # stage C: candidates at the scan roots
    productive = np.zeros((S, max(pieces, 1)))
    meta = np.zeros((nb, MAX_PATHS_TWO_BOUNCE + 1, 2))
    stage_c(refract1, refract2, x_start, x_end, P, N, eta, b_offset, coef, sysint, sys_first, state, roots, nv,
            productive, out_uv, meta, out_count, stats)

    # stage D: refinement (refine_v_roots / _refine_interval at REFINE_LEVELS = 1)
    M = SUB_SAMPLES
    flags = np.zeros((S, max(pieces, 1)), dtype=np.int64)
    lg_raw = lg.copy()  # the scan's log|det| before refine_flags deflates it: a refined piece's ends
    if REFINE_LEVELS and S:
        # the ghost samples a piece outside either end of the range (where that end's piece is live)
        ghost = np.zeros((S, 2))
        refined = live & ((sysint[:, 0] & 2) == 0)  # the TIR fallback's system is not refined
        # both ends' samples in one batch (one device round trip)
        lo_sys = np.flatnonzero(refined & (live_mask[:, 0] != 0))
        hi_sys = np.flatnonzero(refined & (live_mask[:, pieces - 1] != 0))
        ghost_v = np.concatenate([vs[lo_sys, 0] - (vs[lo_sys, 1] - vs[lo_sys, 0]),
                                  vs[hi_sys, pieces] + (vs[hi_sys, 1] - vs[hi_sys, 0])])
        ghost_sys = np.concatenate([lo_sys, hi_sys])
        sign, log, dets = dev.dets(ghost_sys.astype(np.int32), np.ascontiguousarray(ghost_v))
        ghost[lo_sys, 0] = log[:lo_sys.size]
        ghost[hi_sys, 1] = log[lo_sys.size:]
        np.add.at(dets_per_sys, ghost_sys, dets)
        refine_flags(vs, lg, ghost, roots, nv, piece_of, productive, pieces, live_mask, flags)
        flags[~refined] = 0
    fs, fk = np.nonzero(flags)
    F = fs.shape[0]
    flag_first = np.concatenate([[0], np.cumsum(np.count_nonzero(flags, axis=1))]).astype(np.int64)
    # runs of consecutive flagged pieces: the previous piece of a run gives the sample before a
    # piece; a run's first piece takes an extra one below it, its last one an extra one above
    prev_flag = (fk > 0) & (flags[fs, np.maximum(fk - 1, 0)] != 0)
    next_flag = (fk + 1 < pieces) & (flags[fs, np.minimum(fk + 1, max(pieces - 1, 0))] != 0)
    a_ = vs[fs, fk]
    b_ = vs[fs, fk + 1]
    hsub = (b_ - a_) / M
    sv = a_[:, None] + np.arange(M + 1)[None, :] * hsub[:, None]
    sv[:, M] = b_
    first = np.flatnonzero(~prev_flag)
    last = np.flatnonzero(~next_flag)
    # the sub-samples inside each piece; its two ends are scan samples, taken as they are
    # (``_refine_interval``: the same v, so the same values)
    job_sys = np.concatenate([np.repeat(fs, M - 1), fs[first], fs[last]]).astype(np.int32)
    job_v = np.concatenate([sv[:, 1:M].ravel(), a_[first] - hsub[first], b_[last] + hsub[last]])
    sign, log, dets = dev.dets(job_sys, np.ascontiguousarray(job_v))
    np.add.at(dets_per_sys, job_sys, dets)
    ss = np.zeros((F, M + 1), dtype=np.int64)
    sl = np.zeros((F, M + 1))
    ss[:, 1:M] = sign[:F * (M - 1)].reshape(-1, M - 1)
    sl[:, 1:M] = log[:F * (M - 1)].reshape(-1, M - 1)
    ss[:, 0] = sg[fs, fk]
    sl[:, 0] = lg_raw[fs, fk]
    ss[:, M] = sg[fs, fk + 1]
    sl[:, M] = lg_raw[fs, fk + 1]
    svx = np.zeros((F, M + 3))
    ssx = np.zeros((F, M + 3), dtype=np.int64)
    slx = np.zeros((F, M + 3))
    svx[:, 1:M + 2] = sv
    ssx[:, 1:M + 2] = ss
    slx[:, 1:M + 2] = sl
    inner = np.flatnonzero(prev_flag)
    svx[inner, 0] = sv[inner - 1, M - 1]
    ssx[inner, 0] = ss[inner - 1, M - 1]
    slx[inner, 0] = sl[inner - 1, M - 1]
    o = F * (M - 1)
    svx[first, 0] = job_v[o:o + first.size]
    ssx[first, 0] = sign[o:o + first.size]
    slx[first, 0] = log[o:o + first.size]
    o += first.size
    svx[last, M + 2] = job_v[o:o + last.size]
    ssx[last, M + 2] = sign[o:o + last.size]
    slx[last, M + 2] = log[o:o + last.size]
    bracket = np.zeros((F, M), dtype=np.int64)
    if F:
        refine_brackets(fs.astype(np.int64), sv, ss, roots, nv, bracket)
    bf, bk = np.nonzero(bracket)
    pinned = np.zeros((F, M))
    root, dets = dev.illinois(fs[bf].astype(np.int32), np.ascontiguousarray(np.column_stack([sv[bf, bk], sv[bf, bk + 1], sl[bf, bk], sl[bf, bk + 1]])),
                              np.ascontiguousarray(np.column_stack([ss[bf, bk], ss[bf, bk + 1]]), dtype=np.int32))
    pinned[bf, bk] = root
    np.add.at(dets_per_sys, fs[bf], dets)
    ref_first = (flag_first * (2 * M - 1)).astype(np.int64)
    ref_roots = np.zeros(max(int(ref_first[-1]), 1))
    ref_count = np.zeros(S, dtype=np.int64)
    dip_dets = np.zeros(S, dtype=np.int64)
    if S:
        refine_assemble(flag_first, svx, ssx, slx, ~next_flag, bracket, pinned, roots, nv, ref_first, ref_count, ref_roots,
                        coef, sysint3, b_offset, dip_dets)
        dets_per_sys += dip_dets

    # stage E: candidates at the refined roots, seeded polish, straight line, statistics
    stage_e(refract1, refract2, x_start, x_end, P, N, eta, pieces, b_offset, coef, sysint, sys_first, state, nv,
            ref_first, ref_count, ref_roots, out_uv, meta, out_count, stats)
    per_tuple = np.zeros(nb, dtype=np.int64)
    np.add.at(per_tuple, owner, dets_per_sys)
    stats[:, STAT_DETS] += np.where(state == 1, per_tuple, 0)
