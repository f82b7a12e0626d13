"""The resultant scan of the two-bounce solver (Fan et al. 2024 eq 28-31): u1 eliminated.

The hybrid Bézout matrix of a(·, v1) and b(·, v1) (its determinant is the Sylvester
resultant) is evaluated at one v1 by pivoted elimination carrying sign and log magnitude
(``det_bezout``: dense, or a sliding window of ``LANES`` for large matrices).  The live v1
pieces are scanned for sign changes (``find_v_roots``), each pinned by Illinois regula falsi
to ``ROOT_TOL``; pieces around productive roots and convex kinks of the deflated log|det|
are refined (``refine_v_roots``), one-signed dips resolved (``resolve_dip``).

Tested in tests/solver/test_solver_two_bounce.py (the determinant against the Sylvester
resultant, window against dense bit for bit) and through the solver's recall tests.
"""

import math

import numpy as np

from ...runtime.jit import kernel
from ...runtime.simd import CHUNK as SIMD_CHUNK
from ...runtime.simd import lanes_abs_argmax, lanes_sub_scaled, rows_scale_add
from .params import (DIP_FLAT, DIP_STEPS, KINK, LANES, NOISY_CHANGES, REFINE_LEVELS, ROOT_TOL, STACK_CAP, STAT_DETS,
                     SUB_SAMPLES, WINDOW_FROM)
from .prepass import check_whole_vectors, transpose_square


@kernel
def v_major(p, d, out):
    """out[j, i] = p[i, j] for i + j ≤ d and 0 beyond, in rows j ≤ d up to the block edge:
    a bivariate polynomial (p[i, j] u^i v^j, total degree d) in the layout the determinant
    family reads (``det_bezout`` and its callers: their ``at``, ``bt``).  There one Horner
    step in v of all the u-coefficients at once is one vector operation on a row, where
    on p it gathers a column (:func:`_coeffs_at`)."""
    check_whole_vectors(out, d)
    transpose_square(p, d, out)
    w = SIMD_CHUNK * ((d + SIMD_CHUNK) // SIMD_CHUNK)
    for j in range(d + 1):
        for i in range(d - j + 1, w):
            out[j, i] = 0.0


@kernel
def _coeffs_at(pt, d, n, v, out):
    """out[i] = p_i(v) (coefficient of u^i) for i ≤ n, scaled to unit max-norm; returns the scale.
    pt: p in the v-major layout (:func:`v_major`).

    Horner in v for all rows at once: step j is out = out v + pt[j], a vector operation on
    whole vectors (rows_scale_add; pt's zeros beyond the triangle keep each out[i] at 0
    until its first term, so every out[i] for i ≤ n gets exactly one Horner loop's
    operations; out[n + 1 ..] up to the block edge is scratch).  Gathering the column p[:, j]
    instead was ~0.5 µs of a ~4 µs (16, 34) determinant."""
    w = SIMD_CHUNK * ((n + SIMD_CHUNK) // SIMD_CHUNK)
    for i in range(w):
        out[i] = 0.0
    for j in range(d, -1, -1):
        rows_scale_add(out, pt[j], v, min(n, d - j) + 1)
    m = 0.0
    for i in range(n + 1):
        m = max(m, abs(out[i]))
    if m > 0.0 and np.isfinite(m):
        inv = 1.0 / m
        for i in range(n + 1):
            out[i] *= inv
    return m


@kernel
def top_row(pt, d, n):
    """The u-degree of p, at most n (rows above it were zeroed by ``u_degree``); pt: p
    v-major (:func:`v_major`)."""
    i = min(n, d)
    while i > 0:
        for j in range(d - i + 1):
            if pt[j, i] != 0.0:
                return i
        i -= 1
    return 0


@kernel
def det_bezout(at, da, bt, db, n, v, cf, mat):
    """Sign and log|det| of the hybrid Bézout matrix of (a(·, v), b(·, v)): the resultant
    in u1 at v1 (eq 29), up to a sign that is constant for the system.

    The paper (../shared/seeds/specular_polynomials.txt §2, §4.1-4.2) takes the Bézout
    matrix of eq 29 "due to its numerical stability" and evaluates its determinant by
    Gaussian elimination.  For f of u-degree n and g of u-degree m < n (a has u-degree 8 or
    16 against b's 15 … 46) that matrix has n - m rows that are multiples of g by the leading
    coefficients of f: its determinant is lc(f)^(n-m) times the resultant, and tiny leading
    coefficients (|b_n| ~ 1e-11 of max|b_i| is common) grade those rows so steeply that the
    elimination in doubles loses the determinant: within ±0.004 of the v1 of 18 planted RT
    paths the sign came out wrong at 19 % of the samples (24 of 126, against exact rational
    arithmetic on the same double coefficients: ``bench/two_bounce_recall.py --exact``), so a
    root pair closer than a piece was invisible to the scan and to its refinement, and some
    RT systems were sign noise over whole pieces.  The hybrid Bézout matrix replaces those
    rows by the plain shifts u^k g (k < n - m) and keeps the m rows φ_c = F_hi G_lo - G_hi F_lo
    (f = u^c F_hi + F_lo, g = u^c G_hi + G_lo, c = m … 1) of the Bézoutian: the same size n,
    its determinant the Sylvester resultant (lc(f)^(n-m) divided out, and with it the sign
    changes of lc(f), roots at infinity), and the elimination keeps the sign (wrong at 4 of
    those 126 samples; median log error 8e-8 instead of 1.5).  RT recall at 10,000 tuples:
    99.756 % -> 99.866 % with half the determinant evaluations (sign noise made roots).

    The elimination (:func:`det_hybrid_window` for n ≥ WINDOW_FROM, else
    :func:`det_hybrid_dense`) gives the same numbers bit for bit either way.

    at, bt: a and b in the v-major layout (:func:`v_major`).  cf: (2, MAXD + 2) scratch, mat:
    (MAXD, MAXD) scratch.  Returns (sign, log|det|); sign 0 when the elimination meets an
    exactly zero column (or a coefficient vector vanishes)."""
    A = cf[0]
    B = cf[1]
    na = top_row(at, da, n)
    nb = top_row(bt, db, n)
    ma = _coeffs_at(at, da, na, v, A)
    mb = _coeffs_at(bt, db, nb, v, B)
    if not (ma > 0.0 and mb > 0.0) or not (np.isfinite(ma) and np.isfinite(mb)):
        return 0, -math.inf
    # f: the polynomial of the larger u-degree nf, g: the other one (degree m)
    F = B
    G = A
    nf = nb
    m = na
    if na > nb:
        F = A
        G = B
        nf = na
        m = nb
    n = nf
    if n == 0:
        return 1, 0.0
    if m == 0:
        # n shift rows of the constant g: G_0^n
        if G[0] == 0.0:
            return 0, -math.inf
        return (-1 if G[0] < 0.0 and n % 2 == 1 else 1), n * math.log(abs(G[0]))
    if m <= LANES and n >= WINDOW_FROM:
        return det_hybrid_window(F, G, n, m, mat)
    return det_hybrid_dense(F, G, n, m, A, mat)


@kernel
def _bezoutian_rows(F, G, n, m, out, stride_rows):
    """The m Bézoutian rows φ_c (c = m … 1) of the hybrid Bézout matrix of (f, g) (u-degrees
    n, m ≤ n; F, G their coefficient vectors): φ_c = F_hi G_lo - G_hi F_lo with
    F_hi = Σ_(i ≥ c) F_i u^(i-c), G_lo = Σ_(l < c) G_l u^l (G_hi, F_lo alike), by the
    recurrence up from φ_0 = 0: φ_c[k] = φ_(c-1)[k + 1] + (G_(c-1) F_(k+1) - F_(c-1) G_(k+1))
    (F_hi = F_(c-1) + u F_hi', G_lo = G_lo' + G_(c-1) u^(c-1)): φ_c[k] is the direct sum
    Σ_(l < c) (G_l F_(c+k-l) - F_l G_(c+k-l)), its 2c terms in pairs by ascending l, in
    O(n m) instead of O(n m²) (a (16, 34) determinant 4.2 -> 3.6 µs).  Every rounding
    variant tried moved the 10,000-tuple recall by a few paths either way (the direct sums,
    G terms first: TT 43 missed, RT 7, TR 2; this: 49, 4, 1; the recurrence down from φ_m:
    47, 6, 1; the direct sums along diagonals, one subtraction per element: 46, 7, 1).
    φ_c[k] goes to out[k, m - c] (stride_rows: the rows are columns of out) or out[n - c, k]."""
    for c in range(1, m + 1):
        fc = F[c - 1]
        gc = G[c - 1]
        lane = m - c  # stride_rows: φ_c in column lane of out, φ_(c-1) in lane + 1
        r = n - c  # else: φ_c in row r, φ_(c-1) in row r + 1
        for k in range(n):
            gk = G[k + 1] if k + 1 <= m else 0.0
            t = gc * F[k + 1] - fc * gk
            if c > 1 and k < n - 1:  # φ_(c-1)[n] = 0
                t = (out[k + 1, lane + 1] if stride_rows else out[r + 1, k + 1]) + t
            if stride_rows:
                out[k, lane] = t
            else:
                out[r, k] = t


@kernel
def _log_accumulate(prod, logm, x):
    """log of a product of positive factors, one log per ~100 orders of magnitude instead
    of one per factor: x joins the running product prod (kept within 1e±150, so a factor
    within 1e±100 neither overflows nor underflows it); a factor outside that range, or a
    product leaving it, goes into logm.  The result is log(prod) + logm; its rounding is
    that of the product, ~n ulp, as the sum of n logs (34 logs were ~5 % of a (16, 34)
    determinant)."""
    if x > 1e-100 and x < 1e100:
        prod *= x
        if prod < 1e-150 or prod > 1e150:
            return 1.0, logm + math.log(prod)
        return prod, logm
    return prod, logm + math.log(x)


@kernel
def det_hybrid_window(F, G, n, m, mat):
    """det of the hybrid Bézout matrix (shift rows u^r g, r < n - m, then the Bézoutian rows
    φ_m … φ_1) by Gaussian elimination with partial pivoting on a sliding window.

    Column k of the elimination involves only m + 1 rows: the m that are not yet pivots among
    the Bézoutian rows and the shift rows reached so far, and the shift row u^k g, whose
    first nonzero is column k (the others are zero there: the dense loop skips them).  The m
    rows live column-major in LANES lanes, W[j, lane] = mat[j, lane], so one column update
    is a fixed-length vector operation; the shift row enters untouched (g's coefficients) and
    takes the place of the pivot when that is not it itself.  The arithmetic on every entry
    is the dense elimination's (f = x_ik / pivot, x_ij -= f x_kj), the pivot the largest in
    the column (ties may pick another row than the dense order), so the result is the
    dense elimination's (tests/solver/test_solver_two_bounce.py, bit for bit).  The sign is that of
    the pivots and of the permutation (original row of each pivot, parity by cycles).
    F is overwritten (the multipliers)."""
    L = LANES
    perm = mat[:, L]  # original row of the k-th pivot
    ids = mat[:, L + 1]  # original row in each lane
    seen = mat[:, L + 2]
    for j in range(n):
        for i in range(L):
            mat[j, i] = 0.0
    _bezoutian_rows(F, G, n, m, mat, True)
    f = F  # no longer needed: the multipliers
    for i in range(L):
        ids[i] = n - m + i if i < m else -1.0
    sign = 1
    logm = 0.0
    prod = 1.0  # the pivots' product not yet in logm (_log_accumulate)
    n_shift = n - m
    for k in range(n):
        entering = k < n_shift
        # pivot: the largest |x_ik| over the lanes and the entering row (g's constant term)
        row = mat[k]
        # the first lane whose |x| exceeds g's constant term (entering) and every other lane
        big, p = lanes_abs_argmax(row, abs(G[0]) if entering else 0.0, LANES)
        if big == 0.0 or not np.isfinite(big):
            return 0, -math.inf
        piv = G[0] if p < 0 else row[p]
        if piv < 0.0:
            sign = -sign
        prod, logm = _log_accumulate(prod, logm, abs(piv))
        inv = 1.0 / piv
        for i in range(L):
            f[i] = row[i] * inv
        if p >= 0:
            f[p] = 0.0  # the pivot lane is not updated (it is replaced or retired)
        fv = (f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8], f[9], f[10], f[11], f[12], f[13], f[14], f[15])
        if p < 0:
            # the entering shift row is the pivot: g's coefficients, zero beyond column k + m
            perm[k] = k
            for j in range(k + 1, min(n, k + m + 1)):
                lanes_sub_scaled(mat[j], fv, G[j - k])
        else:
            perm[k] = ids[p]
            fs = G[0] * inv if entering else 0.0
            for j in range(k + 1, n):
                row = mat[j]
                x = row[p]
                lanes_sub_scaled(row, fv, x)
                # lane p: the entering row (updated by the pivot row) takes its place
                if entering:
                    row[p] = (G[j - k] if j - k <= m else 0.0) - fs * x
                else:
                    row[p] = 0.0
            ids[p] = k if entering else -1.0
    # the permutation's parity: n minus its number of cycles
    for k in range(n):
        seen[k] = 0.0
    cycles = 0
    for k in range(n):
        if seen[k] == 0.0:
            cycles += 1
            q = k
            while seen[q] == 0.0:
                seen[q] = 1.0
                q = int(perm[q])
    if (n - cycles) % 2 == 1:
        sign = -sign
    return sign, logm + math.log(prod)


@kernel
def det_hybrid_dense(F, G, n, m, A, mat):
    """det of the hybrid Bézout matrix built in full (n < WINDOW_FROM, where the window does
    not pay, or m > LANES, not met by the systems of this module): dense Gaussian elimination
    with partial pivoting, skipping the rows with a zero in the pivot column.  A: scratch
    (MAXD)."""
    for r in range(n - m):
        for j in range(n):
            mat[r, j] = 0.0
    for r in range(n - m):
        for i in range(m + 1):
            mat[r, r + i] = G[i]
    _bezoutian_rows(F, G, n, m, mat, False)
    sign = 1
    logm = 0.0
    prod = 1.0  # the pivots' product not yet in logm (_log_accumulate)
    for k in range(n):
        p = k
        big = abs(mat[k, k])
        for i in range(k + 1, n):
            x = abs(mat[i, k])
            if x > big:
                big = x
                p = i
        if big == 0.0 or not np.isfinite(big):
            return 0, -math.inf
        if p != k:
            sign = -sign
            for j in range(k, n):
                t = mat[k, j]
                mat[k, j] = mat[p, j]
                mat[p, j] = t
        piv = mat[k, k]
        if piv < 0.0:
            sign = -sign
        prod, logm = _log_accumulate(prod, logm, abs(piv))
        inv = 1.0 / piv
        # the pivot row's tail in a separate buffer (A: the coefficients are in the matrix
        # now): the row updates then provably do not alias it and vectorise
        w = n - k - 1
        for j in range(w):
            A[j] = mat[k, k + 1 + j]
        for i in range(k + 1, n):
            f = mat[i, k] * inv
            if f != 0.0:
                for j in range(w):
                    mat[i, k + 1 + j] -= f * A[j]
    return sign, logm + math.log(prod)


@kernel
def det_checked(at, da, bt, db, n, v, cf, mat, stats):
    """det_bezout, with an exact zero re-checked a hair away (never taken as a root as is)."""
    stats[STAT_DETS] += 1
    s, lg = det_bezout(at, da, bt, db, n, v, cf, mat)
    if s != 0:
        return s, lg
    for k in range(1, 4):
        h = 1e-13 * (10.0 ** k)
        stats[STAT_DETS] += 1
        s, lg = det_bezout(at, da, bt, db, n, v + h, cf, mat)
        if s != 0:
            return s, lg
    return 0, -math.inf


@kernel
def illinois(at, da, bt, db, n, lo, hi, slo, llo, shi, lhi, cf, mat, stats):
    """Root of det in [lo, hi] (opposite signs at the ends) pinned to ROOT_TOL."""
    side = 0
    width_before = hi - lo
    for it in range(200):
        w = hi - lo
        if w <= ROOT_TOL:
            break
        dl = lhi - llo
        if dl > 700.0:
            t = 0.0
        elif dl < -700.0:
            t = 1.0
        else:
            t = 1.0 / (1.0 + math.exp(dl))
        if it % 4 == 3:
            # safeguard: bisect unless the last steps shrank the bracket well
            if w > 0.25 * width_before:
                t = 0.5
            width_before = w
        x = lo + t * w
        if not (x > lo and x < hi):
            x = lo + 0.5 * w
            if not (x > lo and x < hi):
                break
        s, lg = det_checked(at, da, bt, db, n, x, cf, mat, stats)
        if s == 0:
            return x
        if s == slo:
            lo = x
            llo = lg
            if side == -1:
                lhi -= 0.6931471805599453
            side = -1
        else:
            hi = x
            lhi = lg
            if side == 1:
                llo -= 0.6931471805599453
            side = 1
    return 0.5 * (lo + hi)


@kernel
def find_v_roots(at, da, bt, db, n, lo, hi, pieces, live, cf, mat, scan, out_roots, stats):
    """Real roots of det R(v) in [lo, hi] seen by the piecewise sign scan, pinned by Illinois.

    The range is cut into ``pieces``; every sign change is pinned to ROOT_TOL (the path-space
    polish of its candidates takes v1 the rest of the way).  The scan (v, sign, log|det|)
    stays in scan[0:3] and each root's piece index in scan[4], for :func:`refine_v_roots`.
    Only the pieces with ``live[k]`` (:func:`live_pieces`) are scanned (their samples and
    the neighbours the kink test needs; the others hold sign 2).
    scan: (9, MAX_PIECES + 1) scratch.  Returns the root count, or -1 when the determinant
    vanishes at most samples (degenerate system)."""
    vs = scan[0]
    sg = scan[1]
    lgs = scan[2]
    piece_of = scan[4]
    h = (hi - lo) / pieces
    zeros = 0
    sampled = 0
    for k in range(pieces + 1):
        v = lo + k * h
        vs[k] = v
        # a sample is needed by the live pieces k - 1, k (sign changes) and k - 2, k + 1
        # (the kink test of refine_flags_one looks one sample beyond each end)
        need = False
        for q in range(max(0, k - 2), min(pieces - 1, k + 1) + 1):
            if live[q] != 0:
                need = True
        if not need:
            sg[k] = 2  # not sampled
            lgs[k] = 0.0
            continue
        s, lg = det_checked(at, da, bt, db, n, v, cf, mat, stats)
        sg[k] = s
        lgs[k] = lg
        sampled += 1
        if s == 0:
            zeros += 1
    if zeros * 2 > sampled:
        return -1
    cap = min(out_roots.shape[0], piece_of.shape[0])
    count = 0
    for k in range(pieces):
        if live[k] == 0:
            continue
        if sg[k] != sg[k + 1] and sg[k] != 0 and sg[k + 1] != 0 and count < cap:
            out_roots[count] = illinois(at, da, bt, db, n, vs[k], vs[k + 1], int(sg[k]), lgs[k], int(sg[k + 1]), lgs[k + 1], cf, mat, stats)
            piece_of[count] = k
            count += 1
        elif sg[k] == 0 and count < cap:
            out_roots[count] = vs[k]
            piece_of[count] = k
            count += 1
    return count


@kernel
def refine_v_roots(at, da, bt, db, n, pieces, live, cf, mat, scan, out_roots, n_found, productive, stats):
    """Roots the uniform scan of :func:`find_v_roots` missed; returns the new root count.

    Solutions cluster (all paths through a small or distant second triangle lie in a small
    patch of the first), so the pieces around a sign change whose root polished into a path
    (``productive[i]`` for root i) are cut again; so is a piece next to a convex kink of
    log|det| deflated by the roots found (what is left of a kink is a root the scan did not
    see: a pair inside one piece).  Sign changes whose roots gave no path are resultant roots
    with their common u1 outside the triangle or the path invalid — most of them — and are
    not refined around: that is most of the cost of the old always-refine rule.

    The kink rule needs both neighbours of a sample, so the scan's two end samples get one
    more (a "ghost" a piece outside the range, 2 determinants per system): a pair of roots
    in the first or last piece, next to the end of the range, was never refined (the paper's
    §4.2 scan has no refinement at all).  Consecutive flagged pieces are refined as one run
    (:func:`_refine_interval`'s ``carry``), so that a one-signed dip at a sample the pieces
    share — a root pair next to a scan sample — is seen with its neighbours on both sides."""
    if REFINE_LEVELS == 0:
        return n_found
    stack = scan[3, 0:STACK_CAP * 7].reshape((STACK_CAP, 7))
    sub = scan[3, STACK_CAP * 7:STACK_CAP * 7 + 3 * (SUB_SAMPLES + 3)].reshape((3, SUB_SAMPLES + 3))
    flags = scan[6]
    vs = scan[0]
    sg = scan[1]
    lgs = scan[2]
    piece_of = scan[4]
    h = vs[1] - vs[0]
    g_lo = 0.0
    g_hi = 0.0
    if live[0] != 0:
        _, g_lo = det_checked(at, da, bt, db, n, vs[0] - h, cf, mat, stats)
    if live[pieces - 1] != 0:
        _, g_hi = det_checked(at, da, bt, db, n, vs[pieces] + h, cf, mat, stats)
    g_lo = deflate(vs[0] - h, g_lo, out_roots, n_found)
    g_hi = deflate(vs[pieces] + h, g_hi, out_roots, n_found)
    raw = scan[8]  # the scan's log|det| before deflation: the ends of a refined piece
    for k in range(pieces + 1):
        raw[k] = lgs[k]
        if sg[k] != 2:  # unsampled (no live piece needs it): never read by the kink test
            lgs[k] = deflate(vs[k], lgs[k], out_roots, n_found)
    refine_flags_one(lgs, g_lo, g_hi, out_roots, n_found, piece_of, productive, pieces, live, flags)
    count = n_found
    carry = False
    cv = 0.0
    cs = 0
    cl = 0.0
    for k in range(pieces):
        if flags[k] == 0.0:
            carry = False
            continue
        last_of_run = k + 1 >= pieces or flags[k + 1] == 0.0
        count, carry, cv, cs, cl = _refine_interval(at, da, bt, db, n, vs[k], vs[k + 1], cf, mat, stack, sub, out_roots,
                                                     n_found, count, stats, carry, cv, cs, cl, last_of_run,
                                                     int(sg[k]), raw[k], int(sg[k + 1]), raw[k + 1])
    return count


@kernel
def refine_flags_one(lgs, g_lo, g_hi, roots, n_found, piece_of, productive, pieces, live, flags):
    """flags[k] = 1 for a live piece next to a convex kink of the deflated log|det| lgs
    (ghost samples g_lo, g_hi outside the two ends) or within one piece of a productive root."""
    for k in range(pieces):
        if live[k] == 0:
            flags[k] = 0
            continue
        left = g_lo if k == 0 else lgs[k - 1]
        right = g_hi if k + 2 > pieces else lgs[k + 2]
        flagged = left + lgs[k + 1] - 2.0 * lgs[k] > KINK or lgs[k] + right - 2.0 * lgs[k + 1] > KINK
        if not flagged:
            for i in range(n_found):
                if productive[i] and abs(int(piece_of[i]) - k) <= 1:
                    flagged = True
                    break
        flags[k] = 1 if flagged else 0


@kernel
def deflate(v, lg, roots, n_roots):
    """log|det(v)| minus Σ log|v - r| over known roots r (their share of the curvature)."""
    for i in range(n_roots):
        d = abs(v - roots[i])
        if d > 0.0:
            lg -= math.log(d)
    return lg


@kernel
def _refine_interval(at, da, bt, db, n, lo, hi, cf, mat, stack, sub, out_roots, n_scan, count, stats, carry, cv, cs, cl,
                     last_of_run, s_lo, l_lo, s_hi, l_hi):
    """Roots in [lo, hi] the uniform scan missed: recursive sub-sampling (explicit stack); a
    sub-piece next to a convex kink of the deflated log|det| is cut again (up to
    REFINE_LEVELS levels); new sign changes (not around one of the n_scan scan roots) are
    pinned by Illinois; at the last level a one-signed dip of the deflated log|det| — a
    local minimum with a convex kink, one sign at it and its neighbours — is resolved by
    :func:`resolve_dip` where log|det| falls monotonically into it over two samples on
    each side, and otherwise (log|det| at its rounding floor, where dips are noise) its
    deepest sample is a candidate as it is (the paths near grazing incidence whose
    resultant is that flat are still found from there).

    A flagged piece is one of a run of consecutive flagged pieces: (carry, cv, cs, cl) is
    the previous piece's last sub-sample before lo (v, sign, raw log|det|), so that the dip
    rule sees the sample at lo with both neighbours; the first piece of a run takes one
    more sample below lo instead, the last one (``last_of_run``) one above hi.  The ends lo
    and hi are scan samples: their (sign, raw log|det|) (s_lo, l_lo), (s_hi, l_hi) are
    taken as they are instead of being evaluated again (the same v, so the same values:
    2 of the SUB_SAMPLES + 1 determinants per piece).  Returns (count, carry, cv, cs, cl)
    for the next piece."""
    cap = out_roots.shape[0]
    stack[0, 0] = lo
    stack[0, 1] = hi
    stack[0, 6] = 1.0
    top = 1
    # sub[:, 1 .. M + 1] the samples of the interval, sub[:, 0] and sub[:, M + 2] their
    # neighbours outside it (the top-level interval only)
    sv = sub[0]
    ss = sub[1]
    sl = sub[2]
    M = SUB_SAMPLES
    out_carry = False
    out_v = 0.0
    out_s = 0
    out_l = 0.0
    while top > 0:
        top -= 1
        lo = stack[top, 0]
        hi = stack[top, 1]
        level = stack[top, 6]
        outer = level == 1.0
        h = (hi - lo) / M
        for k in range(M + 1):
            v = lo + k * h
            if k == M:
                v = hi
            if outer and k == 0 and s_lo != 2:
                s, lg = s_lo, l_lo
            elif outer and k == M and s_hi != 2:
                s, lg = s_hi, l_hi
            else:
                s, lg = det_checked(at, da, bt, db, n, v, cf, mat, stats)
            sv[k + 1] = v
            ss[k + 1] = s
            sl[k + 1] = lg
        has_left = False
        has_right = False
        if outer:
            if carry:
                sv[0] = cv
                ss[0] = cs
                sl[0] = cl
            else:
                s, lg = det_checked(at, da, bt, db, n, lo - h, cf, mat, stats)
                sv[0] = lo - h
                ss[0] = s
                sl[0] = lg
            has_left = True
            if last_of_run:
                s, lg = det_checked(at, da, bt, db, n, hi + h, cf, mat, stats)
                sv[M + 2] = hi + h
                ss[M + 2] = s
                sl[M + 2] = lg
                has_right = True
        if outer:
            out_carry = True
            out_v = sv[M]
            out_s = int(ss[M])  # an int, as the caller starts it (one signature)
            out_l = sl[M]
        # new sign changes (a sub-piece around a scan root is skipped); more than
        # NOISY_CHANGES of them in one piece is a stretch where the determinant's sign is at
        # rounding level (no polynomial of this degree wiggles like that): left alone
        changes = 0
        for k in range(1, M + 1):
            if ss[k] != ss[k + 1]:
                changes += 1
        if changes > NOISY_CHANGES:
            continue
        for k in range(1, M + 1):
            if ss[k] != ss[k + 1] and ss[k] != 0 and ss[k + 1] != 0 and count < cap:
                known = False
                for i in range(n_scan):
                    if out_roots[i] >= sv[k] and out_roots[i] <= sv[k + 1]:
                        known = True
                if not known:
                    out_roots[count] = illinois(at, da, bt, db, n, sv[k], sv[k + 1], int(ss[k]), sl[k], int(ss[k + 1]), sl[k + 1], cf, mat, stats)
                    count += 1
        k_lo = 0 if has_left else 1
        k_hi = M + 2 if has_right else M + 1
        for k in range(k_lo, k_hi + 1):
            sl[k] = deflate(sv[k], sl[k], out_roots, count)
        last = level >= REFINE_LEVELS
        if not last:
            for k in range(1, M + 1):
                kink_l = k > 1 and sl[k - 1] + sl[k + 1] - 2.0 * sl[k] > KINK
                kink_r = k < M and sl[k] + sl[k + 2] - 2.0 * sl[k + 1] > KINK
                if (kink_l or kink_r) and top < stack.shape[0]:
                    stack[top, 0] = sv[k]
                    stack[top, 1] = sv[k + 1]
                    stack[top, 6] = level + 1.0
                    top += 1
            continue
        # a one-signed dip of the deflated log|det| at a sample with both neighbours (the
        # shared end of two pieces of a run is judged by the right-hand piece)
        for k in range(max(k_lo + 1, 1), min(k_hi - 1, M + 1 if has_right else M) + 1):
            if count < cap and sl[k - 1] + sl[k + 1] - 2.0 * sl[k] > KINK and ss[k] == ss[k - 1] \
                    and ss[k] == ss[k + 1] and ss[k] != 0 and sl[k] < sl[k - 1] and sl[k] < sl[k + 1]:
                if (k - 2 < k_lo or sl[k - 2] >= sl[k - 1]) and (k + 2 > k_hi or sl[k + 2] >= sl[k + 1]):
                    count = resolve_dip(at, da, bt, db, n, sv[k - 1], sv[k], sv[k + 1], ss[k], sl[k - 1], sl[k],
                                         sl[k + 1], cf, mat, out_roots, count, stats)
                else:
                    # not monotone over the next samples: log|det| at its rounding floor, where a
                    # dip is noise; its deepest sample is still a (cheap) candidate
                    out_roots[count] = sv[k]
                    count += 1
    return count, out_carry, out_v, out_s, out_l


@kernel
def resolve_dip(at, da, bt, db, n, xl, xm, xr, sgn, fl, fm, fr, cf, mat, out_roots, count, stats):
    """A one-signed dip of the deflated log|det| at xm (fm below fl at xl and fr at xr, one
    sign at all three): a root pair closer than the samples, or a complex pair next to the
    real axis.  The issue's "refine pieces where |det| dips towards zero without a sign
    change, so clustered roots separate" (the paper, §4.2 Discussion: the piecewise
    bisection "requires a large number of pieces in the case that solutions are
    clustered").  Near either pair |det| is a quadratic factor times a slowly varying rest,
    so each step evaluates det at the vertex of the quadratic through the three samples
    (golden-section step when the vertex is too close to a sample or outside): a point of
    the other sign splits the dip into two sign changes, both pinned by Illinois; a model
    minimum above DIP_FLAT of the deepest sample is a complex pair whose bottom is reached
    (no real root: stop); otherwise the deepest point (to ROOT_TOL, DIP_STEPS at most) is
    reported as a (near-)double root candidate.  Before, the deepest sample was that
    candidate: up to half a sub-piece off the pair, too far for the path-space polish of a
    path near grazing (RT at 10,000 tuples: 4 paths).  Typically 3-8 determinants per dip.
    ``fl, fm, fr`` are deflated by ``out_roots[:count]``; returns the new count."""
    cap = out_roots.shape[0]
    for it in range(DIP_STEPS):
        w = xr - xl
        if w <= ROOT_TOL:
            break
        # |det| / |det(xm)| near a root pair (or a complex pair next to the axis) is a
        # quadratic factor times a slowly varying rest: fit q through the three samples
        ql = math.exp(min(fl - fm, 700.0))
        qr = math.exp(min(fr - fm, 700.0))
        d1 = (1.0 - ql) / (xm - xl)
        d2 = (qr - 1.0) / (xr - xm)
        A = (d2 - d1) / w
        x = xm
        qmin = 1.0
        if A > 0.0:
            x = 0.5 * (xl + xm) - d1 / (2.0 * A)
            qmin = ql + d1 * (x - xl) + A * (x - xl) * (x - xm)
        if qmin >= DIP_FLAT:
            break  # a complex pair whose bottom is reached: no real root here
        if not (x > xl + 0.01 * w and x < xr - 0.01 * w) or abs(x - xm) < 0.01 * w:
            # golden-section step into the larger side
            if xr - xm > xm - xl:
                x = xm + 0.3819660112501051 * (xr - xm)
            else:
                x = xm - 0.3819660112501051 * (xm - xl)
        s, lg = det_checked(at, da, bt, db, n, x, cf, mat, stats)
        if s == 0:
            break
        if s != sgn:
            # the pair straddles x: (xl or xm) .. x .. (xm or xr), all of sign sgn but x
            p = xm if x > xm else xl
            q = xr if x > xm else xm
            sp, lp = det_checked(at, da, bt, db, n, p, cf, mat, stats)
            sq, lq = det_checked(at, da, bt, db, n, q, cf, mat, stats)
            if count + 2 <= cap and sp == sgn and sq == sgn:
                out_roots[count] = illinois(at, da, bt, db, n, p, x, sp, lp, s, lg, cf, mat, stats)
                out_roots[count + 1] = illinois(at, da, bt, db, n, x, q, s, lg, sq, lq, cf, mat, stats)
                return count + 2
            break
        f = deflate(x, lg, out_roots, count)
        if f < fm:
            if x > xm:
                xl = xm
                fl = fm
            else:
                xr = xm
                fr = fm
            xm = x
            fm = f
        elif x > xm:
            xr = x
            fr = f
        else:
            xl = x
            fl = f
    if count < cap:
        out_roots[count] = xm  # (near-)double root candidate
        count += 1
    return count
