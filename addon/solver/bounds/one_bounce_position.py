"""Position bound of a one-bounce piece, fast engine (Fan et al. 2025 §4.2–4.3, eq 4–13).

Per tuple, the polynomials whose coefficients do not depend on the box (everything of R; the
position numerators of T, which are linear in the √β approximation's coefficients a, b and in
ξ, eq 10–13) are built once on the unit box of (u1, v1) and restricted to each piece's box by
de Casteljau splits.  Those numerators are V·(ek2 × r), V·(r × ek1), V·(ek2 × ek1) for
direction fields V of the caster alone and r = x1 - Q0; the products V and s × V (s = x1 - P0)
are formed once per caster triangle (``setup_caster``), and each tuple combines them linearly
with its receiver's edge vectors (``make_context``).  ``box_position`` bounds uk = pu/q,
vk = pv/q and the UV coordinates with eq 3; ``box_irradiance_reflect`` is the explicit
Jacobian bound of R (eq 15–16) from the same per-tuple set-up.

Degrees equal the reference engine's generic degrees (R: position 4, irradiance 10; T:
position 6 per ξ slice); where the reference drops a degree because a gradient component
happens to be 0, the bound here is the same polynomial's coefficients at a higher degree, which
lie in the hull of the lower-degree ones, so it is at least as tight and still conservative.
Tested against the reference engine (tests/reference/bounds_one_bounce.py) in
tests/solver/test_bounds_validity.py and tests/solver/test_bounds_bernstein.py.
"""

import math

import numpy as np

from ..runtime.jit import kernel
from .slot_algebra import E2, affine2, axpy, coef_count, coef_minmax, dot_const, dot_fields, elevate2, mac2, pderiv, pmul, ratio_bound, restrict2, to_bernstein, to_bernstein2, zero_fill
from .layout import IRR_PAD, POS_PAD, ior_ratio
from ..polynomials.bernstein import abs_lower, abs_upper, clip_hull, sqrt_linearisation


# workspace slots
S_X, S_N, S_D, S_R = 0, 3, 6, 9          # x1, n1, d0 = x1 - x0, r = x1 - Q0 (3 each)
S_NN, S_DN, S_DD, S_T0, S_T1 = 12, 13, 14, 15, 16
S_V = 17                                  # a direction field (3)
S_E2R, S_RE1 = 20, 23                     # ek2 × r, r × ek1 (3 each)
S_TMP = 26                                # scratch (4)
S_PU, S_PV, S_Q = 30, 31, 32              # R: position numerators / denominator (plain Bernstein, unit box)
S_DET, S_NUM, S_DDB = 33, 34, 35          # R: irradiance det, numerator, |d0|² (plain Bernstein, unit box)
S_TB = 36                                 # T: 4 fields x (pu, pv, q) = 12 slots, then nndd, dn2
S_NNDD, S_DN2 = 48, 49                    # = S_TB + 12, 13 (box_position reads them so)
S_BOX = 50                                # restricted copies (12 + 2)
S_REST = 64                               # per-box combined numerators (2 slices x 3 + w, tx, ty)
S_RBUF = 73                               # quotients of ratio_bound (<= 128)
S_IRR = 76                                # R irradiance set-up (14)
S_CK = 110                                # per caster: 4 fields x (s × V, V) (24, plain Bernstein)
NSLOTS = 134


@kernel
def _cross_const_affine(W, r0, ek, o0, left):
    """o = ek × r (left True) or r × ek for affine r (4 coefficients)."""
    for k in range(4):
        a0, a1, a2 = W[r0, k], W[r0 + 1, k], W[r0 + 2, k]
        if left:
            W[o0, k] = ek[1] * a2 - ek[2] * a1
            W[o0 + 1, k] = ek[2] * a0 - ek[0] * a2
            W[o0 + 2, k] = ek[0] * a1 - ek[1] * a0
        else:
            W[o0, k] = a1 * ek[2] - a2 * ek[1]
            W[o0 + 1, k] = a2 * ek[0] - a0 * ek[2]
            W[o0 + 2, k] = a0 * ek[1] - a1 * ek[0]


@kernel
def caster_unit(W, x0, P, N, Q, lo, hi):
    """x1, n1, d0, r = x1 - Q0 (eq 6–8) as affine polynomials on the box (slots S_X.., E2)."""
    for c in range(3):
        e1 = P[1, c] - P[0, c]
        e2 = P[2, c] - P[0, c]
        affine2(P[0, c], e1, e2, lo, hi, W[S_X + c])
        affine2(N[0, c], N[1, c] - N[0, c], N[2, c] - N[0, c], lo, hi, W[S_N + c])
        affine2(P[0, c] - x0[c], e1, e2, lo, hi, W[S_D + c])
        affine2(P[0, c] - Q[0, c], e1, e2, lo, hi, W[S_R + c])


@kernel
def _field_parts(W, v0, nv, nk, f0, m):
    """Per-caster parts of the numerators of one direction field V (slots v0..v0+2, scaled,
    extents (nv, nv)): K = s × V with s = x1 - P0 (slots S_R.., affine; K has extents
    nk = nv + 1) into f0..f0+2 and V itself into f0+3..f0+5, elevated to (m, m) and
    converted to plain Bernstein.  With r = x1 - Q0 = s + h, h = P0 - Q0, eq 9's numerators
    are linear in them (:func:`setup_tuple`), so the products are formed once per caster
    triangle, not once per (caster, receiver) tuple.  nv, nk, m are constants at the calls."""
    tmp = W[S_TMP]
    t3 = W[S_TMP + 2]
    for c in range(3):
        i = (c + 1) % 3
        j = (c + 2) % 3
        zero_fill(nk * nk, t3)
        mac2(W[S_R + i], 2, 2, W[v0 + j], nv, nv, t3, 1.0)
        mac2(W[S_R + j], 2, 2, W[v0 + i], nv, nv, t3, -1.0)
        elevate2(t3, nk, m, 1.0, W[f0 + c], tmp)
        to_bernstein2(W[f0 + c], m)
        elevate2(W[v0 + c], nv, m, 1.0, W[f0 + 3 + c], tmp)
        to_bernstein2(W[f0 + 3 + c], m)


@kernel
def _dot2(W, a0, na, b0, nb, out):
    """out = Σ_c W[a0+c]·W[b0+c] for 3-vectors of (u1, v1) polynomials, extents (na, na),
    (nb, nb) (constants at the calls)."""
    zero_fill((na + nb - 1) * (na + nb - 1), out)
    for c in range(3):
        mac2(W[a0 + c], na, na, W[b0 + c], nb, nb, out, 1.0)


@kernel
def setup_caster(W, refract, x0, P, N):
    """Per-caster-triangle polynomials on the unit box of (u1, v1): x1, n1, d0 (eq 6–8), the
    direction fields of eq 10 and their numerator parts (:func:`_field_parts`, slots S_CK..);
    for T also nndd, dn² (plain Bernstein).  They do not depend on the receiver triangle, so
    the batch builds them once per run of tuples that share the caster.  Scaled Bernstein
    products in (u1, v1) with constant extents (:func:`mac2`)."""
    lo = (0.0, 0.0)
    hi = (1.0, 1.0)
    for c in range(3):
        e1 = P[1, c] - P[0, c]
        e2 = P[2, c] - P[0, c]
        affine2(P[0, c], e1, e2, lo, hi, W[S_X + c])
        affine2(N[0, c], N[1, c] - N[0, c], N[2, c] - N[0, c], lo, hi, W[S_N + c])
        affine2(P[0, c] - x0[c], e1, e2, lo, hi, W[S_D + c])
        affine2(0.0, e1, e2, lo, hi, W[S_R + c])  # s = x1 - P0
    if not refract:
        # d̃ = (n·n) d - 2 (d·n) n (eq 10), extents (1,1,4,4); kept in S_V for the irradiance
        # (generic products, as before the per-caster split: R's bounds are unchanged bit for bit)
        tmp = W[S_TMP]
        e3 = dot_fields(W, S_N, E2, S_N, E2, W[S_NN], tmp)
        dot_fields(W, S_D, E2, S_N, E2, W[S_DN], tmp)
        for cc in range(3):
            ev = pmul(W[S_NN], e3, W[S_D + cc], E2, W[S_V + cc])
            pmul(W[S_DN], e3, W[S_N + cc], E2, tmp)
            axpy(coef_count(ev), -2.0, tmp, W[S_V + cc])
        _field_parts(W, S_V, 4, 5, S_CK, 5)
        return
    _dot2(W, S_N, 2, S_N, 2, W[S_NN])  # n·n (3, 3)
    _dot2(W, S_D, 2, S_N, 2, W[S_DN])  # d·n
    # refraction: fields P1 = (n·n) d - (d·n) n (4, 4), nndd n, dn² n, n (eq 10 with
    # √β -> aβ + b + ξ δ), all elevated to (7, 7)
    for cc in range(3):
        zero_fill(16, W[S_V + cc])
        mac2(W[S_NN], 3, 3, W[S_D + cc], 2, 2, W[S_V + cc], 1.0)
        mac2(W[S_DN], 3, 3, W[S_N + cc], 2, 2, W[S_V + cc], -1.0)
    _field_parts(W, S_V, 4, 5, S_CK, 7)
    _dot2(W, S_D, 2, S_D, 2, W[S_DD])
    zero_fill(25, W[S_NNDD])
    mac2(W[S_NN], 3, 3, W[S_DD], 3, 3, W[S_NNDD], 1.0)
    zero_fill(25, W[S_DN2])
    mac2(W[S_DN], 3, 3, W[S_DN], 3, 3, W[S_DN2], 1.0)
    for f in range(2):
        src = S_NNDD if f == 0 else S_DN2
        for cc in range(3):
            zero_fill(36, W[S_V + cc])
            mac2(W[src], 5, 5, W[S_N + cc], 2, 2, W[S_V + cc], 1.0)
        _field_parts(W, S_V, 6, 7, S_CK + 6 + 6 * f, 7)
    _field_parts(W, S_N, 2, 3, S_CK + 18, 7)
    to_bernstein2(W[S_NNDD], 5)
    to_bernstein2(W[S_DN2], 5)


@kernel
def setup_tuple(W, refract, x0, P, Q):
    """Per-tuple numerators of eq 9 on the unit box from the caster parts of
    :func:`setup_caster`: with r = x1 - Q0 = s + h (h = P0 - Q0),
    pu = V·(ek2 × r) = ek2·(s × V) + (ek2 × h)·V, pv = V·(r × ek1) = -ek1·(s × V) + (h × ek1)·V,
    q = (ek2 × ek1)·V: 15 coefficient rows per field instead of 9 polynomial products, an
    elevation and a basis conversion (both linear, so applied once per caster instead)."""
    ek1 = (Q[1, 0] - Q[0, 0], Q[1, 1] - Q[0, 1], Q[1, 2] - Q[0, 2])
    ek2 = (Q[2, 0] - Q[0, 0], Q[2, 1] - Q[0, 1], Q[2, 2] - Q[0, 2])
    h = (P[0, 0] - Q[0, 0], P[0, 1] - Q[0, 1], P[0, 2] - Q[0, 2])
    a = (ek2[1] * h[2] - ek2[2] * h[1], ek2[2] * h[0] - ek2[0] * h[2], ek2[0] * h[1] - ek2[1] * h[0])
    b = (h[1] * ek1[2] - h[2] * ek1[1], h[2] * ek1[0] - h[0] * ek1[2], h[0] * ek1[1] - h[1] * ek1[0])
    c0 = ek2[1] * ek1[2] - ek2[2] * ek1[1]
    c1 = ek2[2] * ek1[0] - ek2[0] * ek1[2]
    c2 = ek2[0] * ek1[1] - ek2[1] * ek1[0]
    c = W[S_TMP + 3]  # ek2 × ek1, also read by setup_reflect_irradiance
    c[0], c[1], c[2] = c0, c1, c2
    nf = 4 if refract else 1
    n = 49 if refract else 25
    for f in range(nf):
        k0 = S_CK + 6 * f
        o = S_TB + 3 * f if refract else S_PU
        pu = W[o]
        pv = W[o + 1]
        q = W[o + 2]
        K0, K1, K2 = W[k0], W[k0 + 1], W[k0 + 2]
        V0, V1, V2 = W[k0 + 3], W[k0 + 4], W[k0 + 5]
        # one output per loop, constants in scalars: the rows are all in W, so the vector
        # loops need a run-time overlap test per (input, output) pair; few enough here
        for k in range(n):
            pu[k] = ek2[0] * K0[k] + ek2[1] * K1[k] + ek2[2] * K2[k] + a[0] * V0[k] + a[1] * V1[k] + a[2] * V2[k]
        for k in range(n):
            pv[k] = -(ek1[0] * K0[k] + ek1[1] * K1[k] + ek1[2] * K2[k]) + b[0] * V0[k] + b[1] * V1[k] + b[2] * V2[k]
        for k in range(n):
            q[k] = c0 * V0[k] + c1 * V1[k] + c2 * V2[k]
    if not refract:
        # r, ek2 × r, r × ek1 (affine) for the lazily built reflection irradiance polynomials
        lo = (0.0, 0.0)
        hi = (1.0, 1.0)
        for cc in range(3):
            affine2(P[0, cc] - Q[0, cc], P[1, cc] - P[0, cc], P[2, cc] - P[0, cc], lo, hi, W[S_R + cc])
        _cross_const_affine(W, S_R, ek2, S_E2R, True)
        _cross_const_affine(W, S_R, ek1, S_RE1, False)


@kernel
def make_context(W, refract, irradiance, x0, P, N, Q):
    """Per-tuple polynomials on the unit box of (u1, v1) (slots S_PU.., S_TB..)."""
    setup_caster(W, refract, x0, P, N)
    setup_tuple(W, refract, x0, P, Q)
    if irradiance and not refract:
        setup_reflect_irradiance(W)


@kernel
def setup_reflect_irradiance(W):
    """R: det ∂(pu,pv,q) (eq 16 via det[[pu, pu_u, pu_v], [pv, ...], [q, ...]]) and
    num = (d0·ng) q³ on the unit box, plain Bernstein at degree 10; |d0|² at degree 2.
    Rebuilt from the scaled numerators (slots S_V.. hold d̃)."""
    tmp = W[S_TMP]
    # scaled pu (1,1,5,5), pv (1,1,5,5), q (1,1,4,4) in S_IRR..
    pu, pv, q = S_IRR, S_IRR + 1, S_IRR + 2
    ev = (1, 1, 4, 4)
    dot_fields(W, S_V, ev, S_E2R, E2, W[pu], tmp)
    dot_fields(W, S_V, ev, S_RE1, E2, W[pv], tmp)
    c = W[S_TMP + 3]
    dot_const(W, S_V, ev, c, W[q])
    e5 = (1, 1, 5, 5)
    e4 = ev
    a = S_IRR + 3
    eu5 = pderiv(W[pu], e5, 2, 1.0, W[a])      # pu_u (1,1,4,5)
    ev5 = pderiv(W[pu], e5, 3, 1.0, W[a + 1])  # pu_v (1,1,5,4)
    pderiv(W[pv], e5, 2, 1.0, W[a + 2])        # pv_u
    pderiv(W[pv], e5, 3, 1.0, W[a + 3])        # pv_v
    eu4 = pderiv(W[q], e4, 2, 1.0, W[a + 4])   # q_u (1,1,3,4)
    ev4 = pderiv(W[q], e4, 3, 1.0, W[a + 5])   # q_v (1,1,4,3)
    m1, m2, m3 = a + 6, a + 7, a + 8
    # pv_u q_v - pv_v q_u -> (1,1,7,7)
    e77 = pmul(W[a + 2], eu5, W[a + 5], ev4, W[m1])
    pmul(W[a + 3], ev5, W[a + 4], eu4, tmp)
    axpy(coef_count(e77), -1.0, tmp, W[m1])
    ed = pmul(W[pu], e5, W[m1], e77, W[S_DET])       # (1,1,11,11)
    # pu_u q_v - pu_v q_u
    pmul(W[a], eu5, W[a + 5], ev4, W[m2])
    pmul(W[a + 1], ev5, W[a + 4], eu4, tmp)
    axpy(coef_count(e77), -1.0, tmp, W[m2])
    pmul(W[pv], e5, W[m2], e77, tmp)
    axpy(coef_count(ed), -1.0, tmp, W[S_DET])
    # pu_u pv_v - pu_v pv_u -> (1,1,8,8)
    e88 = pmul(W[a], eu5, W[a + 3], ev5, W[m3])
    pmul(W[a + 1], ev5, W[a + 2], eu5, tmp)
    axpy(coef_count(e88), -1.0, tmp, W[m3])
    pmul(W[q], e4, W[m3], e88, tmp)
    axpy(coef_count(ed), 1.0, tmp, W[S_DET])
    to_bernstein(W[S_DET], ed)
    # num = (d0·ng) q³
    ng = W[S_TMP + 2]
    # ng = e1 x e2 from the affine x: e1 = x(1,0) - x(0,0), e2 = x(0,1) - x(0,0)
    e1 = (W[S_X, 2] - W[S_X, 0], W[S_X + 1, 2] - W[S_X + 1, 0], W[S_X + 2, 2] - W[S_X + 2, 0])
    e2 = (W[S_X, 1] - W[S_X, 0], W[S_X + 1, 1] - W[S_X + 1, 0], W[S_X + 2, 1] - W[S_X + 2, 0])
    ng[0] = e1[1] * e2[2] - e1[2] * e2[1]
    ng[1] = e1[2] * e2[0] - e1[0] * e2[2]
    ng[2] = e1[0] * e2[1] - e1[1] * e2[0]
    cosp = a + 9
    dot_const(W, S_D, E2, ng, W[cosp])
    q2 = a + 10
    e7 = pmul(W[q], e4, W[q], e4, W[q2])
    e10 = pmul(W[q2], e7, W[q], e4, W[m1])
    pmul(W[cosp], E2, W[m1], e10, W[S_NUM])
    to_bernstein(W[S_NUM], ed)
    e3 = dot_fields(W, S_D, E2, S_D, E2, W[S_DDB], tmp)
    to_bernstein(W[S_DDB], e3)


# ---------------------------------------------------------------------------------------
# per piece


@kernel
def box_orientation_mask(x0, P, N, lo, hi):
    """As the reference engine's _orientations: signs o of the shading normal turned to the light that occur on
    the box (the affine n·ng takes its extremes at the box corners)."""
    e1 = (P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2])
    e2 = (P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2])
    ng = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
    side = (x0[0] - P[0, 0]) * ng[0] + (x0[1] - P[0, 1]) * ng[1] + (x0[2] - P[0, 2]) * ng[2]
    if side == 0.0:
        return 0
    vlo = np.inf
    vhi = -np.inf
    for k in range(4):
        u = lo[0] if k < 2 else hi[0]
        v = lo[1] if k % 2 == 0 else hi[1]
        s = 0.0
        for c in range(3):
            s += (N[0, c] + u * (N[1, c] - N[0, c]) + v * (N[2, c] - N[0, c])) * ng[c]
        vlo = min(vlo, s)
        vhi = max(vhi, s)
    mask = 0
    sg = 1.0 if side > 0.0 else -1.0
    if vhi > 0.0:
        mask |= 1 if sg > 0.0 else 2
    if vlo < 0.0:
        mask |= 2 if sg > 0.0 else 1
    return mask


@kernel
def _bounds_from(W, pu, pv, q, n, UV, res):
    """uk, vk, w = 1 - uk - vk and UV bounds from coefficient arrays (one degree, n of them);
    res[0:8] as the reference piece_position before padding; returns False when the bound misses."""
    a, b, c, e = ratio_bound(W[pu], W[q], n, W[S_RBUF])
    ulo, uhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if ulo > uhi:
        return False
    a, b, c, e = ratio_bound(W[pv], W[q], n, W[S_RBUF])
    vlo, vhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if vlo > vhi or ulo + vlo > 1.0:
        return False
    t = W[S_REST + 8]
    for k in range(n):
        t[k] = W[q, k] - W[pu, k] - W[pv, k]
    a, b, c, e = ratio_bound(t, W[q], n, W[S_RBUF])
    wlo, whi = clip_hull(a, b, c, e, 0.0, 1.0)
    if wlo > whi:
        return False
    uhi = min(uhi, 1.0 - vlo - wlo)
    vhi = min(vhi, 1.0 - ulo - wlo)
    uvlo_x = min(UV[0, 0], UV[1, 0], UV[2, 0])
    uvhi_x = max(UV[0, 0], UV[1, 0], UV[2, 0])
    uvlo_y = min(UV[0, 1], UV[1, 1], UV[2, 1])
    uvhi_y = max(UV[0, 1], UV[1, 1], UV[2, 1])
    for k in range(n):
        t[k] = W[q, k] * UV[0, 0] + W[pu, k] * (UV[1, 0] - UV[0, 0]) + W[pv, k] * (UV[2, 0] - UV[0, 0])
    a, b, c, e = ratio_bound(t, W[q], n, W[S_RBUF])
    xlo, xhi = clip_hull(a, b, c, e, uvlo_x, uvhi_x)
    for k in range(n):
        t[k] = W[q, k] * UV[0, 1] + W[pu, k] * (UV[1, 1] - UV[0, 1]) + W[pv, k] * (UV[2, 1] - UV[0, 1])
    a, b, c, e = ratio_bound(t, W[q], n, W[S_RBUF])
    ylo, yhi = clip_hull(a, b, c, e, uvlo_y, uvhi_y)
    if xlo > xhi or ylo > yhi:
        return False
    res[0], res[1], res[2], res[3] = ulo, uhi, vlo, vhi
    res[4], res[5], res[6], res[7] = xlo, xhi, ylo, yhi
    return True


@kernel
def box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, out, res):
    """Position bound of the piece lo <= (u1, v1) <= hi (same result as the reference piece_position)
    from the per-tuple polynomials of :func:`_setup`."""
    if lo[0] + lo[1] > 1.0:
        return False
    mask = box_orientation_mask(x0, P, N, lo, hi)
    if mask == 0:
        return False
    tmp = W[S_TMP]
    bu0 = np.inf
    bu1 = -np.inf
    bv0 = np.inf
    bv1 = -np.inf
    X0 = np.inf
    X1 = -np.inf
    Y0 = np.inf
    Y1 = -np.inf
    if not refract:
        ep = (1, 1, 5, 5)
        n = 25
        restrict2(W[S_PU], ep, lo, hi, W[S_BOX], tmp, work)
        restrict2(W[S_PV], ep, lo, hi, W[S_BOX + 1], tmp, work)
        restrict2(W[S_Q], ep, lo, hi, W[S_BOX + 2], tmp, work)
        if not _bounds_from(W, S_BOX, S_BOX + 1, S_BOX + 2, n, UV, res):
            return False
        bu0, bu1, bv0, bv1 = res[0], res[1], res[2], res[3]
        X0, X1, Y0, Y1 = res[4], res[5], res[6], res[7]
    else:
        ep = (1, 1, 7, 7)
        n = 49
        if lo[0] == 0.0 and hi[0] == 1.0 and lo[1] == 0.0 and hi[1] == 1.0:
            B = S_TB  # the root: the unit-box polynomials themselves (nndd, dn² follow at S_TB + 12, 13)
        else:
            B = S_BOX
            for k in range(12):
                restrict2(W[S_TB + k], ep, lo, hi, W[S_BOX + k], tmp, work)
            e5 = (1, 1, 5, 5)
            restrict2(W[S_NNDD], e5, lo, hi, W[S_BOX + 12], tmp, work)
            restrict2(W[S_DN2], e5, lo, hi, W[S_BOX + 13], tmp, work)
        for variant in range(2):
            if not (mask >> variant) & 1:
                continue
            o = 1.0 if variant == 0 else -1.0
            er = ior_ratio(o, eta)
            e2 = er * er
            blo = np.inf
            bhi = -np.inf
            for k in range(25):
                bv = (1.0 - e2) * W[B + 12, k] + e2 * W[B + 13, k]
                blo = min(blo, bv)
                bhi = max(bhi, bv)
            if bhi <= 0.0:
                continue  # total internal reflection on the whole box
            a, b, dlo, dhi = sqrt_linearisation(blo, bhi)
            cc = b + dlo
            wx = dhi - dlo
            # slices ξ = 0 and ξ = 1 of pu, pv, q: 2n coefficients each (eq 10, 12)
            for f in range(3):
                dst = W[S_REST + f]
                p1 = W[B + f]
                pa = W[B + 3 + f]
                pb = W[B + 6 + f]
                pn = W[B + 9 + f]
                for k in range(n):
                    s0 = er * p1[k] - o * (a * ((1.0 - e2) * pa[k] + e2 * pb[k]) + cc * pn[k])
                    dst[k] = s0
                    dst[n + k] = s0 - o * wx * pn[k]
            if not _bounds_from(W, S_REST, S_REST + 1, S_REST + 2, 2 * n, UV, res):
                continue
            bu0, bu1, bv0, bv1 = min(bu0, res[0]), max(bu1, res[1]), min(bv0, res[2]), max(bv1, res[3])
            X0, X1, Y0, Y1 = min(X0, res[4]), max(X1, res[5]), min(Y0, res[6]), max(Y1, res[7])
        if bu0 > bu1:
            return False
    out[0] = bu0 - POS_PAD
    out[1] = bu1 + POS_PAD
    out[2] = bv0 - POS_PAD
    out[3] = bv1 + POS_PAD
    out[4] = X0 - POS_PAD
    out[5] = X1 + POS_PAD
    out[6] = Y0 - POS_PAD
    out[7] = Y1 + POS_PAD
    return True


@kernel
def box_irradiance_reflect(W, work, Q, lo, hi):
    """(Ē, E̲) for reflection on the box (eq 15–16), from the per-tuple det / num."""
    tmp = W[S_TMP]
    e = (1, 1, 11, 11)
    restrict2(W[S_DET], e, lo, hi, W[S_BOX], tmp, work)
    restrict2(W[S_NUM], e, lo, hi, W[S_BOX + 1], tmp, work)
    e3 = (1, 1, 3, 3)
    restrict2(W[S_DDB], e3, lo, hi, W[S_BOX + 2], tmp, work)
    dlo, dhi = coef_minmax(W[S_BOX + 2], 9)
    a, b, c, d = ratio_bound(W[S_BOX + 1], W[S_BOX], 121, W[S_RBUF])
    ek1 = (Q[1, 0] - Q[0, 0], Q[1, 1] - Q[0, 1], Q[1, 2] - Q[0, 2])
    ek2 = (Q[2, 0] - Q[0, 0], Q[2, 1] - Q[0, 1], Q[2, 2] - Q[0, 2])
    ak = math.sqrt((ek1[1] * ek2[2] - ek1[2] * ek2[1]) ** 2 + (ek1[2] * ek2[0] - ek1[0] * ek2[2]) ** 2
                   + (ek1[0] * ek2[1] - ek1[1] * ek2[0]) ** 2)
    upper = abs_upper(a, b, c, d)
    lower = abs_lower(a, b, c, d)
    if dlo <= 0.0:
        return np.inf, 0.0
    return upper * dlo ** -1.5 / ak * (1.0 + IRR_PAD), lower * dhi ** -1.5 / ak * (1.0 - IRR_PAD)
