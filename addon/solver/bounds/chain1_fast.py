"""Fast engine of the one-bounce bounds (Fan et al. 2025 §4.2–4.5, §6.1): same maths as the
reference piece functions in ``chain1.py``, without allocation in the per-tuple loop.

Representation: a polynomial is a flat slice of a per-thread workspace plus its extents
(e0, e1, e2, e3) = degree + 1 per variable.  Variable order here is (uk, vk, u1, v1) so that
the long (u1, v1) axes are the innermost loops; 2-variable polynomials have e0 = e1 = 1.
Products are formed in *scaled* Bernstein form c_i = b_i Π C(n_d, i_d), where the Bernstein
product (Farouki 2012) is a plain convolution; affine polynomials (degree 1) have c = b.  For
a rational bound p/q at one common degree the ratios c_i(p)/c_i(q) equal b_i(p)/b_i(q) (the
binomial factors cancel), so eq 3 is applied to scaled coefficients directly.

Per tuple, the polynomials whose coefficients do not depend on the box (everything of R; the
position numerators of T, which are linear in the √β approximation's coefficients a, b and
in ξ, eq 10–13) are built once on the unit box of (u1, v1) and restricted to each piece's box
by de Casteljau splits (the Bernstein coefficients of a polynomial on a sub-box, exact up to
rounding).  Those numerators are V·(ek2 × r), V·(r × ek1), V·(ek2 × ek1) for direction
fields V of the caster alone and r = x1 - Q0; the products V and s × V (s = x1 - P0) are
formed once per caster triangle (``_setup_caster``), and each tuple combines them linearly
with its receiver's edge vectors (``_setup_tuple``).  The implicit refraction irradiance bound (eq 17–19) depends on the piece's
(uk, vk) box, so it is built per piece in the 4-D box, as sums over monomials in the box's
(uk, vk) coordinates of 2-D products in (u1, v1) (``box_irradiance_refract``).

The final degrees equal the reference's generic degrees (R: position 4, irradiance 10;
T: position 6 per ξ slice, irradiance (10, 10, 3, 3) in (u1, v1, uk, vk)); where the reference
drops a degree because a gradient component happens to be 0, the bound here is the same
polynomial's coefficients at a higher degree, which lie in the hull of the lower-degree ones
(degree elevation is a convex combination), so it is at least as tight and still conservative.
"""

import math

import numpy as np

from ..runtime.jit import kernel
from ..polynomials.bernstein import BINOM, abs_lower, abs_upper, clip_hull, sqrt_linearisation
from .chain1 import IRR_PAD, MIN_WIDTH, N_STATS, P_BU0, P_DEPTH, P_EHI, P_ELO, P_U0, P_U1, P_V0, P_V1, PIECE_FIELDS, POS_PAD, push_children

# ---------------------------------------------------------------------------------------
# flat 4-D polynomial kernels (scaled Bernstein unless said otherwise)

MAXC = 128  # coefficients per workspace slot (largest: (1, 1, 11, 11) = 121); 128 keeps the slots
# of one workspace close together in cache (a 4-D polynomial of the T irradiance lives in scr)
N4 = 4 * 4 * 11 * 11  # coefficients of the final T irradiance polynomials (uk, vk, u1, v1)
SCR4 = 64  # offset of those two in scr


@kernel
def _size(e):
    return e[0] * e[1] * e[2] * e[3]


@kernel
def pmul(a, ea, b, eb, out):
    """out = a·b (scaled Bernstein: convolution); returns the extents of the product.  The
    operand with the longer last axis runs in the innermost loop."""
    if eb[3] >= ea[3]:
        return _pmul(a, ea, b, eb, out)
    return _pmul(b, eb, a, ea, out)


@kernel
def _pmul(a, ea, b, eb, out):
    eo = (ea[0] + eb[0] - 1, ea[1] + eb[1] - 1, ea[2] + eb[2] - 1, ea[3] + eb[3] - 1)
    n = eo[0] * eo[1] * eo[2] * eo[3]
    for k in range(n):
        out[k] = 0.0
    for i0 in range(ea[0]):
        for i1 in range(ea[1]):
            for i2 in range(ea[2]):
                for i3 in range(ea[3]):
                    av = a[((i0 * ea[1] + i1) * ea[2] + i2) * ea[3] + i3]
                    if av == 0.0:
                        continue
                    for j0 in range(eb[0]):
                        for j1 in range(eb[1]):
                            for j2 in range(eb[2]):
                                ob = (((i0 + j0) * eo[1] + i1 + j1) * eo[2] + i2 + j2) * eo[3] + i3
                                bb = ((j0 * eb[1] + j1) * eb[2] + j2) * eb[3]
                                for j3 in range(eb[3]):
                                    out[ob + j3] += av * b[bb + j3]
    return eo


@kernel
def pderiv(a, ea, dim, width, out):
    """∂/∂x_dim of scaled coefficients: c'_i = ((i+1) c_{i+1} - (n-i) c_i) / width, degree n-1."""
    m = ea[dim]
    if m == 1:
        for k in range(_size(ea)):
            out[k] = 0.0
        return ea
    n = m - 1
    pre = 1
    for d in range(dim):
        pre *= ea[d]
    post = 1
    for d in range(dim + 1, 4):
        post *= ea[d]
    f = 1.0 / width
    for p in range(pre):
        for i in range(n):
            src0 = (p * m + i) * post
            src1 = src0 + post
            dst = (p * n + i) * post
            for q in range(post):
                out[dst + q] = f * ((i + 1) * a[src1 + q] - (n - i) * a[src0 + q])
    return (n if dim == 0 else ea[0], n if dim == 1 else ea[1], n if dim == 2 else ea[2], n if dim == 3 else ea[3])


@kernel
def to_bernstein(a, ea):
    """Scaled -> plain Bernstein coefficients, in place."""
    for i0 in range(ea[0]):
        for i1 in range(ea[1]):
            for i2 in range(ea[2]):
                w = BINOM[ea[0] - 1, i0] * BINOM[ea[1] - 1, i1] * BINOM[ea[2] - 1, i2]
                base = ((i0 * ea[1] + i1) * ea[2] + i2) * ea[3]
                for i3 in range(ea[3]):
                    a[base + i3] /= w * BINOM[ea[3] - 1, i3]


@kernel
def restrict(a, ea, dim, lo, hi, out, work):
    """Plain Bernstein coefficients of a (on the unit interval of variable ``dim``) restricted to
    [lo, hi] ⊆ [0, 1]: de Casteljau split at hi (left part), then at lo/hi (right part)."""
    m = ea[dim]
    pre = 1
    for d in range(dim):
        pre *= ea[d]
    post = 1
    for d in range(dim + 1, 4):
        post *= ea[d]
    n = pre * m * post
    if m == 1 or (lo == 0.0 and hi == 1.0):
        for k in range(n):
            out[k] = a[k]
        return
    t2 = lo / hi if hi > 0.0 else 0.0
    for p in range(pre):
        for q in range(post):
            base = p * m * post + q
            for i in range(m):
                work[i] = a[base + i * post]
            if hi < 1.0:  # left part of the split at hi: b'_r = first point of level r
                for r in range(1, m):
                    for i in range(m - 1, r - 1, -1):
                        work[i] = (1.0 - hi) * work[i - 1] + hi * work[i]
            if t2 > 0.0:  # right part of the split at t2: last point of level r
                for r in range(1, m):
                    for i in range(m - r):
                        work[i] = (1.0 - t2) * work[i] + t2 * work[i + 1]
            for i in range(m):
                out[base + i * post] = work[i]


@kernel
def restrict2(a, ea, lo, hi, out, tmp, work):
    """Restriction of a polynomial in (u1, v1) = variables 2, 3 to the box lo <= (u1, v1) <= hi."""
    restrict(a, ea, 2, lo[0], hi[0], tmp, work)
    restrict(tmp, ea, 3, lo[1], hi[1], out, work)


@kernel
def coef_minmax(a, n):
    lo = np.inf
    hi = -np.inf
    for k in range(n):
        lo = min(lo, a[k])
        hi = max(hi, a[k])
    return lo, hi


@kernel(error_model="numpy")
def _ratio_minmax(p, q, n, buf):
    """min and max of p[k] / q[k] over k < n (q has no zero: the callers checked its sign).
    The quotients go through ``buf`` so that the division loop is a plain vector loop (the
    numpy error model drops Python's zero-division test per quotient), and the min / max
    run in four independent chains; NaN quotients are skipped as min(acc, nan) = acc does."""
    for k in range(n):
        buf[k] = p[k] / q[k]
    lo0 = lo1 = lo2 = lo3 = np.inf
    hi0 = hi1 = hi2 = hi3 = -np.inf
    m = n - n % 4
    for k in range(0, m, 4):
        r0 = buf[k]
        r1 = buf[k + 1]
        r2 = buf[k + 2]
        r3 = buf[k + 3]
        lo0 = min(lo0, r0)
        lo1 = min(lo1, r1)
        lo2 = min(lo2, r2)
        lo3 = min(lo3, r3)
        hi0 = max(hi0, r0)
        hi1 = max(hi1, r1)
        hi2 = max(hi2, r2)
        hi3 = max(hi3, r3)
    for k in range(m, n):
        lo0 = min(lo0, buf[k])
        hi0 = max(hi0, buf[k])
    return min(min(lo0, lo1), min(lo2, lo3)), max(max(hi0, hi1), max(hi2, hi3))


@kernel
def _one_signed(a, n):
    """(all a[k] > 0, all a[k] < 0) over k < n, by counting (a branch-free loop)."""
    npos = 0
    nneg = 0
    for k in range(n):
        v = a[k]
        npos += 1 if v > 0.0 else 0
        nneg += 1 if v < 0.0 else 0
    return npos == n, nneg == n


@kernel
def ratio_bound(p, q, n, buf):
    """Fan et al. 2025 eq 3 and the two fallbacks of §4.1 on n coefficient pairs at one
    degree (the same cases as ``bernstein.rational_bound``): (lo1, hi1, lo2, hi2).
    ``buf`` is scratch of n entries."""
    pos, neg = _one_signed(q, n)
    if pos or neg:
        lo, hi = _ratio_minmax(p, q, n, buf)
        return lo, hi, np.inf, -np.inf
    pos, neg = _one_signed(p, n)
    if not (pos or neg):
        return -np.inf, np.inf, np.inf, -np.inf
    rlo, rhi = _ratio_minmax(q, p, n, buf)
    if rlo > 0.0 or rhi < 0.0:
        return 1.0 / rhi, 1.0 / rlo, np.inf, -np.inf
    a = 1.0 / rlo if rlo < 0.0 else -np.inf
    b = 1.0 / rhi if rhi > 0.0 else np.inf
    if rlo == 0.0:
        return b, np.inf, np.inf, -np.inf
    if rhi == 0.0:
        return -np.inf, a, np.inf, -np.inf
    return -np.inf, a, b, np.inf


# ---------------------------------------------------------------------------------------
# building blocks

E2 = (1, 1, 2, 2)  # affine in (u1, v1)


@kernel
def _affine2(c, gu, gv, lo, hi, out):
    """c + gu u1 + gv v1 on the box: degree 1, coefficients = corner values (variables 2, 3)."""
    out[0] = c + gu * lo[0] + gv * lo[1]
    out[1] = c + gu * lo[0] + gv * hi[1]
    out[2] = c + gu * hi[0] + gv * lo[1]
    out[3] = c + gu * hi[0] + gv * hi[1]


@kernel
def _axpy(n, s, x, out):
    for k in range(n):
        out[k] += s * x[k]


@kernel
def _scal(n, s, x, out):
    for k in range(n):
        out[k] = s * x[k]


@kernel
def _dotv(W, a0, ea, b0, eb, out, tmp):
    """out = Σ_c W[a0+c]·W[b0+c] (3-vectors of polynomials in slots); returns the extents."""
    eo = pmul(W[a0], ea, W[b0], eb, out)
    n = _size(eo)
    for c in range(1, 3):
        pmul(W[a0 + c], ea, W[b0 + c], eb, tmp)
        for k in range(n):
            out[k] += tmp[k]
    return eo


@kernel
def _dotc(W, a0, ea, c, out):
    """out = Σ_c W[a0+c] · c[c] for a constant 3-vector c."""
    n = _size(ea)
    for k in range(n):
        out[k] = c[0] * W[a0, k] + c[1] * W[a0 + 1, k] + c[2] * W[a0 + 2, k]


@kernel
def _cross_pp(W, a0, ea, b0, eb, o0, tmp):
    """W[o0..o0+2] = W[a0..] × W[b0..]; returns the extents."""
    eo = ea
    for c in range(3):
        i = (c + 1) % 3
        j = (c + 2) % 3
        eo = pmul(W[a0 + i], ea, W[b0 + j], eb, W[o0 + c])
        pmul(W[a0 + j], ea, W[b0 + i], eb, tmp)
        n = _size(eo)
        for k in range(n):
            W[o0 + c, k] -= tmp[k]
    return eo


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
def _caster_unit(W, x0, P, N, Q, lo, hi):
    """x1, n1, d0, r = x1 - Q0 (eq 6–8) as affine polynomials on the box (slots S_X.., E2)."""
    for c in range(3):
        e1 = P[1, c] - P[0, c]
        e2 = P[2, c] - P[0, c]
        _affine2(P[0, c], e1, e2, lo, hi, W[S_X + c])
        _affine2(N[0, c], N[1, c] - N[0, c], N[2, c] - N[0, c], lo, hi, W[S_N + c])
        _affine2(P[0, c] - x0[c], e1, e2, lo, hi, W[S_D + c])
        _affine2(P[0, c] - Q[0, c], e1, e2, lo, hi, W[S_R + c])


@kernel
def _field_parts(W, v0, nv, nk, f0, m):
    """Per-caster parts of the numerators of one direction field V (slots v0..v0+2, scaled,
    extents (nv, nv)): K = s × V with s = x1 - P0 (slots S_R.., affine; K has extents
    nk = nv + 1) into f0..f0+2 and V itself into f0+3..f0+5, elevated to (m, m) and
    converted to plain Bernstein.  With r = x1 - Q0 = s + h, h = P0 - Q0, eq 9's numerators
    are linear in them (:func:`_setup_tuple`), so the products are formed once per caster
    triangle, not once per (caster, receiver) tuple.  nv, nk, m are constants at the calls."""
    tmp = W[S_TMP]
    t3 = W[S_TMP + 2]
    for c in range(3):
        i = (c + 1) % 3
        j = (c + 2) % 3
        _zero(nk * nk, t3)
        _mac2(W[S_R + i], 2, 2, W[v0 + j], nv, nv, t3, 1.0)
        _mac2(W[S_R + j], 2, 2, W[v0 + i], nv, nv, t3, -1.0)
        _elevate2(t3, nk, m, 1.0, W[f0 + c], tmp)
        _to_bernstein2(W[f0 + c], m)
        _elevate2(W[v0 + c], nv, m, 1.0, W[f0 + 3 + c], tmp)
        _to_bernstein2(W[f0 + 3 + c], m)


@kernel
def _dot2(W, a0, na, b0, nb, out):
    """out = Σ_c W[a0+c]·W[b0+c] for 3-vectors of (u1, v1) polynomials, extents (na, na),
    (nb, nb) (constants at the calls)."""
    _zero((na + nb - 1) * (na + nb - 1), out)
    for c in range(3):
        _mac2(W[a0 + c], na, na, W[b0 + c], nb, nb, out, 1.0)


@kernel
def _setup_caster(W, refract, x0, P, N):
    """Per-caster-triangle polynomials on the unit box of (u1, v1): x1, n1, d0 (eq 6–8), the
    direction fields of eq 10 and their numerator parts (:func:`_field_parts`, slots S_CK..);
    for T also nndd, dn² (plain Bernstein).  They do not depend on the receiver triangle, so
    the batch builds them once per run of tuples that share the caster.  Scaled Bernstein
    products in (u1, v1) with constant extents (:func:`_mac2`)."""
    lo = (0.0, 0.0)
    hi = (1.0, 1.0)
    for c in range(3):
        e1 = P[1, c] - P[0, c]
        e2 = P[2, c] - P[0, c]
        _affine2(P[0, c], e1, e2, lo, hi, W[S_X + c])
        _affine2(N[0, c], N[1, c] - N[0, c], N[2, c] - N[0, c], lo, hi, W[S_N + c])
        _affine2(P[0, c] - x0[c], e1, e2, lo, hi, W[S_D + c])
        _affine2(0.0, e1, e2, lo, hi, W[S_R + c])  # s = x1 - P0
    if not refract:
        # d̃ = (n·n) d - 2 (d·n) n (eq 10), extents (1,1,4,4); kept in S_V for the irradiance
        # (generic products, as before the per-caster split: R's bounds are unchanged bit for bit)
        tmp = W[S_TMP]
        e3 = _dotv(W, S_N, E2, S_N, E2, W[S_NN], tmp)
        _dotv(W, S_D, E2, S_N, E2, W[S_DN], tmp)
        for cc in range(3):
            ev = pmul(W[S_NN], e3, W[S_D + cc], E2, W[S_V + cc])
            pmul(W[S_DN], e3, W[S_N + cc], E2, tmp)
            _axpy(_size(ev), -2.0, tmp, W[S_V + cc])
        _field_parts(W, S_V, 4, 5, S_CK, 5)
        return
    _dot2(W, S_N, 2, S_N, 2, W[S_NN])  # n·n (3, 3)
    _dot2(W, S_D, 2, S_N, 2, W[S_DN])  # d·n
    # refraction: fields P1 = (n·n) d - (d·n) n (4, 4), nndd n, dn² n, n (eq 10 with
    # √β -> aβ + b + ξ δ), all elevated to (7, 7)
    for cc in range(3):
        _zero(16, W[S_V + cc])
        _mac2(W[S_NN], 3, 3, W[S_D + cc], 2, 2, W[S_V + cc], 1.0)
        _mac2(W[S_DN], 3, 3, W[S_N + cc], 2, 2, W[S_V + cc], -1.0)
    _field_parts(W, S_V, 4, 5, S_CK, 7)
    _dot2(W, S_D, 2, S_D, 2, W[S_DD])
    _zero(25, W[S_NNDD])
    _mac2(W[S_NN], 3, 3, W[S_DD], 3, 3, W[S_NNDD], 1.0)
    _zero(25, W[S_DN2])
    _mac2(W[S_DN], 3, 3, W[S_DN], 3, 3, W[S_DN2], 1.0)
    for f in range(2):
        src = S_NNDD if f == 0 else S_DN2
        for cc in range(3):
            _zero(36, W[S_V + cc])
            _mac2(W[src], 5, 5, W[S_N + cc], 2, 2, W[S_V + cc], 1.0)
        _field_parts(W, S_V, 6, 7, S_CK + 6 + 6 * f, 7)
    _field_parts(W, S_N, 2, 3, S_CK + 18, 7)
    _to_bernstein2(W[S_NNDD], 5)
    _to_bernstein2(W[S_DN2], 5)


@kernel
def _setup_tuple(W, refract, x0, P, Q):
    """Per-tuple numerators of eq 9 on the unit box from the caster parts of
    :func:`_setup_caster`: with r = x1 - Q0 = s + h (h = P0 - Q0),
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
    c = W[S_TMP + 3]  # ek2 × ek1, also read by _setup_reflect_irradiance
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
            _affine2(P[0, cc] - Q[0, cc], P[1, cc] - P[0, cc], P[2, cc] - P[0, cc], lo, hi, W[S_R + cc])
        _cross_const_affine(W, S_R, ek2, S_E2R, True)
        _cross_const_affine(W, S_R, ek1, S_RE1, False)


@kernel
def make_context(W, refract, irradiance, x0, P, N, Q):
    """Per-tuple polynomials on the unit box of (u1, v1) (slots S_PU.., S_TB..)."""
    _setup_caster(W, refract, x0, P, N)
    _setup_tuple(W, refract, x0, P, Q)
    if irradiance and not refract:
        _setup_reflect_irradiance(W)


@kernel
def _setup_reflect_irradiance(W):
    """R: det ∂(pu,pv,q) (eq 16 via det[[pu, pu_u, pu_v], [pv, ...], [q, ...]]) and
    num = (d0·ng) q³ on the unit box, plain Bernstein at degree 10; |d0|² at degree 2.
    Rebuilt from the scaled numerators (slots S_V.. hold d̃)."""
    tmp = W[S_TMP]
    # scaled pu (1,1,5,5), pv (1,1,5,5), q (1,1,4,4) in S_IRR..
    pu, pv, q = S_IRR, S_IRR + 1, S_IRR + 2
    ev = (1, 1, 4, 4)
    _dotv(W, S_V, ev, S_E2R, E2, W[pu], tmp)
    _dotv(W, S_V, ev, S_RE1, E2, W[pv], tmp)
    c = W[S_TMP + 3]
    _dotc(W, S_V, ev, c, W[q])
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
    _axpy(_size(e77), -1.0, tmp, W[m1])
    ed = pmul(W[pu], e5, W[m1], e77, W[S_DET])       # (1,1,11,11)
    # pu_u q_v - pu_v q_u
    pmul(W[a], eu5, W[a + 5], ev4, W[m2])
    pmul(W[a + 1], ev5, W[a + 4], eu4, tmp)
    _axpy(_size(e77), -1.0, tmp, W[m2])
    pmul(W[pv], e5, W[m2], e77, tmp)
    _axpy(_size(ed), -1.0, tmp, W[S_DET])
    # pu_u pv_v - pu_v pv_u -> (1,1,8,8)
    e88 = pmul(W[a], eu5, W[a + 3], ev5, W[m3])
    pmul(W[a + 1], ev5, W[a + 2], eu5, tmp)
    _axpy(_size(e88), -1.0, tmp, W[m3])
    pmul(W[q], e4, W[m3], e88, tmp)
    _axpy(_size(ed), 1.0, tmp, W[S_DET])
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
    _dotc(W, S_D, E2, ng, W[cosp])
    q2 = a + 10
    e7 = pmul(W[q], e4, W[q], e4, W[q2])
    e10 = pmul(W[q2], e7, W[q], e4, W[m1])
    pmul(W[cosp], E2, W[m1], e10, W[S_NUM])
    to_bernstein(W[S_NUM], ed)
    e3 = _dotv(W, S_D, E2, S_D, E2, W[S_DDB], tmp)
    to_bernstein(W[S_DDB], e3)


# ---------------------------------------------------------------------------------------
# per piece


@kernel
def _orientation_mask(x0, P, N, lo, hi):
    """As chain1._orientations: signs o of the shading normal turned to the light that occur on
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
    res[0:8] as chain1.piece_position before padding; returns False when the bound misses."""
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
def _eta_ratio(o, eta):
    return 1.0 / eta if o > 0.0 else eta


@kernel
def box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, out, res):
    """Position bound of the piece lo <= (u1, v1) <= hi (same result as chain1.piece_position)
    from the per-tuple polynomials of :func:`_setup`."""
    if lo[0] + lo[1] > 1.0:
        return False
    mask = _orientation_mask(x0, P, N, lo, hi)
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
            er = _eta_ratio(o, eta)
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


# slots of the refraction irradiance workspace U (rows of UW coefficients: polynomials in
# (u1, v1) only, extents (1, 1, p, q) with p, q <= 11); 0..11 as S_X.. (for _caster_unit)
UW = 128
U_RR = 12                   # r = xc - x1, xc the receiver point at the (uk, vk) box corner (3)
U_C = 15                    # c = d0 × n (3)
U_COS, U_L0, U_G0, U_G3, U_G4 = 18, 19, 20, 21, 22
U_GU = 23                   # ∂G_β/∂u1, β = 0 (g0), 1 (g3), 2 (g4)
U_GV = 26                   # ∂G_β/∂v1
U_L00, U_L10, U_L01 = 29, 30, 31
U_A, U_A2, U_M = 32, 33, 34  # A = c·b, A², m = n × b (3)
U_B00, U_B10, U_B01 = 37, 38, 39
U_P = 40                    # l_α A² for |α| <= 1 (3)
U_R = 43                    # L0 × (the α coefficient of B²) (6)
U_T, U_TMP, U_TMP2 = 49, 50, 51
U_F = 52                    # f_α (6), α in the order 00, 10, 01, 20, 11, 02
U_FU = 58                   # ∂f_α/∂u1 (6)
U_FV = 64                   # ∂f_α/∂v1 (6)
U_DET = 70                  # det1 coefficient of σ^a τ^b, |(a, b)| <= 3 (10), order 00, 10, 01, 20, 11, 02, 30, 21, 12, 03
U_NK = 80                   # detk coefficient of 1, σ, τ (3)
U_NC = 83                   # cos × detk (3)
U_E = 86                    # elevated copies (3)
NU = 89


@kernel
def _mac2(a, p0, p1, b, q0, q1, out, s):
    """out += s·a·b for polynomials in (u1, v1) only (scaled Bernstein: a 2-D convolution);
    a has extents (p0, p1), b (q0, q1), out (p0 + q0 - 1, p1 + q1 - 1).  The operand with the
    longer rows runs in the innermost loop (the product is symmetric)."""
    if p1 > q1:
        _mac2_rows(b, q0, q1, a, p0, p1, out, s)
    else:
        _mac2_rows(a, p0, p1, b, q0, q1, out, s)


@kernel
def _mac2_rows(a, p0, p1, b, q0, q1, out, s):
    n1 = p1 + q1 - 1
    for i in range(p0):
        for j in range(q0):
            ob = (i + j) * n1
            bb = j * q1
            for k in range(p1):
                av = s * a[i * p1 + k]
                o = ob + k
                for m in range(q1):
                    out[o + m] += av * b[bb + m]


@kernel
def _zero(n, x):
    for k in range(n):
        x[k] = 0.0


@kernel
def _elevate2(a, n, m, s, out, tmp):
    """s times the degree elevation of scaled coefficients in (u1, v1), extents (n, n) ->
    (m, m): the product with the constant 1 of degree m - n (binomial weights), one axis at
    a time with the long rows innermost (a generic 4-axis elevation runs rows of length 1 on
    the last axis).  Callers pass n, m as constants, so the loops have fixed lengths."""
    k = m - n
    for t in range(n * m):
        tmp[t] = 0.0
    for i in range(n):
        for c in range(k + 1):
            w = s * BINOM[k, c]
            src = i * n
            dst = i * m + c
            for j in range(n):
                tmp[dst + j] += w * a[src + j]
    for t in range(m * m):
        out[t] = 0.0
    for i in range(n):
        for c in range(k + 1):
            w = BINOM[k, c]
            src = i * m
            dst = (i + c) * m
            for j in range(m):
                out[dst + j] += w * tmp[src + j]


@kernel
def _to_bernstein2(a, m):
    """Scaled -> plain Bernstein coefficients in (u1, v1), extents (m, m), in place."""
    for i in range(m):
        for j in range(m):
            a[i * m + j] /= BINOM[m - 1, i] * BINOM[m - 1, j]


@kernel
def _det_to_bernstein4(U, out, tmp):
    """out (extents (4, 4, 11, 11), order (uk, vk, u1, v1)) = Σ_{a+b<=3} σ^a τ^b D_ab, D_ab =
    U[U_DET..] (extents 9 - a - b in (u1, v1), elevated to 11), in the degree-(3, 3)
    Bernstein basis of the (uk, vk) box.  σ^a = Σ_i C(i, a)/C(3, a) B_i^3(σ), so with
    m_a = D_a / C(3, a) placed in slab a the coefficients c_i = Σ_a C(i, a) m_a are three
    rounds of Pascal-triangle sums (6 slab additions per axis, no multiplications), in place.
    Slab (a, b) starts at (4 a + b)·121; extents are written as constants (fixed-length loops)."""
    third = 1.0 / 3.0
    ninth = 1.0 / 9.0
    _elevate2(U[U_DET], 9, 11, 1.0, out[0:121], tmp)              # (0, 0)
    _elevate2(U[U_DET + 1], 8, 11, third, out[484:605], tmp)      # (1, 0)
    _elevate2(U[U_DET + 2], 8, 11, third, out[121:242], tmp)      # (0, 1)
    _elevate2(U[U_DET + 3], 7, 11, third, out[968:1089], tmp)     # (2, 0)
    _elevate2(U[U_DET + 4], 7, 11, ninth, out[605:726], tmp)      # (1, 1)
    _elevate2(U[U_DET + 5], 7, 11, third, out[242:363], tmp)      # (0, 2)
    _elevate2(U[U_DET + 6], 6, 11, 1.0, out[1452:1573], tmp)      # (3, 0)
    _elevate2(U[U_DET + 7], 6, 11, ninth, out[1089:1210], tmp)    # (2, 1)
    _elevate2(U[U_DET + 8], 6, 11, ninth, out[726:847], tmp)      # (1, 2)
    _elevate2(U[U_DET + 9], 6, 11, 1.0, out[363:484], tmp)        # (0, 3)
    for slab in (7, 10, 11, 13, 14, 15):                         # a + b > 3
        for k in range(slab * 121, slab * 121 + 121):
            out[k] = 0.0
    for j in range(4):  # along uk (slab index a -> i) for each vk slab
        for r in range(3):
            for i in range(3, r, -1):
                d = (i * 4 + j) * 121
                e = ((i - 1) * 4 + j) * 121
                for k in range(121):
                    out[d + k] += out[e + k]
    for i in range(4):  # along vk
        for r in range(3):
            for j in range(3, r, -1):
                d = (i * 4 + j) * 121
                e = d - 121
                for k in range(121):
                    out[d + k] += out[e + k]


@kernel
def _num_to_bernstein4(U, kscale, out, tmp):
    """out (extents (4, 4, 11, 11)) = kscale (N00 + σ N10 + τ N01), N = U[U_NC..] elevated to
    (11, 11), in the degree-(3, 3) Bernstein basis of (uk, vk): σ = Σ_i (i/3) B_i^3(σ)."""
    e0 = U[U_E]
    e1 = U[U_E + 1]
    e2 = U[U_E + 2]
    _elevate2(U[U_NC], 9, 11, kscale, e0, tmp)
    _elevate2(U[U_NC + 1], 8, 11, kscale, e1, tmp)
    _elevate2(U[U_NC + 2], 8, 11, kscale, e2, tmp)
    for i in range(4):
        wi = i / 3.0
        for j in range(4):
            wj = j / 3.0
            base = (i * 4 + j) * 121
            for k in range(121):
                out[base + k] = e0[k] + wi * e1[k] + wj * e2[k]


@kernel
def _det_alpha0(U, ia, ig):
    """det1 terms of f_α, |α| = 0 (extents 7): f_α,u1 g_β,v1 - f_α,v1 g_β,u1 for β = 0 (g0,
    extents 4) into γ = α (slot ig) and β = σ, τ (g3, g4, extents 3) into γ = α + β (slots 1,
    2).  The extents are written as constants so that each _mac2 is compiled for its fixed
    loop lengths (about 2x faster than the generic loops on these 3..7-long rows)."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    _mac2(fu, 6, 7, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    _mac2(fv, 7, 6, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        _mac2(fu, 6, 7, U[U_GV + 1 + k], 3, 2, U[U_DET + 1 + k], 1.0)
        _mac2(fv, 7, 6, U[U_GU + 1 + k], 2, 3, U[U_DET + 1 + k], -1.0)


@kernel
def _det_alpha1(U, ia, ig, ig1):
    """As _det_alpha0 for |α| = 1 (extents 6): γ = α in slot ig, γ = α + σ, α + τ in slots
    ig1, ig1 + 1."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    _mac2(fu, 5, 6, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    _mac2(fv, 6, 5, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        _mac2(fu, 5, 6, U[U_GV + 1 + k], 3, 2, U[U_DET + ig1 + k], 1.0)
        _mac2(fv, 6, 5, U[U_GU + 1 + k], 2, 3, U[U_DET + ig1 + k], -1.0)


@kernel
def _det_alpha2(U, ia, ig, ig1):
    """As _det_alpha0 for |α| = 2 (extents 5)."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    _mac2(fu, 4, 5, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    _mac2(fv, 5, 4, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        _mac2(fu, 4, 5, U[U_GV + 1 + k], 3, 2, U[U_DET + ig1 + k], 1.0)
        _mac2(fv, 5, 4, U[U_GU + 1 + k], 2, 3, U[U_DET + ig1 + k], -1.0)


@kernel
def box_irradiance_refract(W, U, scr, x0, P, N, Q, eta, lo, hi, pos):
    """(Ē, E̲) for refraction (eq 17–19) on the 4-D box (uk, vk) × (u1, v1), as
    chain1.piece_irradiance_refract: the same polynomials det ∂(F, G)/∂(u1, v1) and
    (d0·ng) det ∂(F, G)/∂(uk, vk), bounded by eq 3 at the same final degree (3, 3, 10, 10) in
    (uk, vk, u1, v1), so the same bound up to rounding.

    Built without 4-D products: with σ, τ in [0, 1] the coordinates of the (uk, vk) box,
    d1 = xk - x1 = r + σ E1 + τ E2 (r = xc - x1 affine in (u1, v1), E1, E2 the box's edge
    vectors), so G = (d0×n)·d1 = g0 + σ g3 + τ g4 is affine and F = |d1|² A² - η² |d0|² B²
    (A = (d0×n)·b, B = d1·(n×b)) is quadratic in (σ, τ), with (u1, v1)-polynomial
    coefficients f_α.  The determinants are then sums over σ^a τ^b (total degree <= 3 for
    det1, <= 1 for detk) of 2-D products (about 5x fewer operations than the tensor 4-D
    products, whose (uk, vk) extents (3, 3) ignore the total degree), converted to the 4-D
    Bernstein basis at the end (σ^a = Σ_i C(i, a)/C(3, a) B_i^3(σ)).  Coefficients stay in
    scaled form: eq 3 takes coefficient ratios at one degree, where the binomial factors
    cancel."""
    lo4 = scr[20:24]
    hi4 = scr[24:28]
    hi_v = scr[32:34]
    lo_v = scr[34:36]
    lo4[2], hi4[2], lo4[3], hi4[3] = lo[0], hi[0], lo[1], hi[1]
    for k in range(2):
        a, b = pos[2 * k], pos[2 * k + 1]
        if b - a < MIN_WIDTH:
            a, b = 0.5 * (a + b) - 0.5 * MIN_WIDTH, 0.5 * (a + b) + 0.5 * MIN_WIDTH
        lo4[k], hi4[k] = a, b
    mask = _orientation_mask(x0, P, N, lo, hi)
    if mask == 0:
        return 0.0, 0.0
    e1 = (P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2])
    e2 = (P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2])
    ek1 = (Q[1, 0] - Q[0, 0], Q[1, 1] - Q[0, 1], Q[1, 2] - Q[0, 2])
    ek2 = (Q[2, 0] - Q[0, 0], Q[2, 1] - Q[0, 1], Q[2, 2] - Q[0, 2])
    ws = hi4[0] - lo4[0]
    wt = hi4[1] - lo4[1]
    w2 = hi[0] - lo[0]
    w3 = hi[1] - lo[1]
    E1 = (ws * ek1[0], ws * ek1[1], ws * ek1[2])
    E2v = (wt * ek2[0], wt * ek2[1], wt * ek2[2])
    xc = (Q[0, 0] + lo4[0] * ek1[0] + lo4[1] * ek2[0], Q[0, 1] + lo4[0] * ek1[1] + lo4[1] * ek2[1],
          Q[0, 2] + lo4[0] * ek1[2] + lo4[1] * ek2[2])
    _caster_unit(U, x0, P, N, Q, lo, hi)  # x, n, d on the (u1, v1) box (affine)
    tmp = U[U_TMP]
    for c in range(3):
        for k in range(4):
            U[U_RR + c, k] = xc[c] - U[S_X + c, k]
    ng = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
    _dotc(U, S_D, E2, ng, U[U_COS])                        # d0·ng (2,2)
    e3 = _dotv(U, S_D, E2, S_D, E2, U[U_L0], tmp)           # |d0|² (3,3)
    for k in range(9):
        U[U_TMP2, k] = U[U_L0, k]
    to_bernstein(U[U_TMP2], e3)
    dlo, dhi = coef_minmax(U[U_TMP2], 9)
    if dlo <= 0.0:
        return np.inf, 0.0
    ec = _cross_pp(U, S_D, E2, S_N, E2, U_C, tmp)           # c = d0 × n (3,3)
    _dotv(U, U_C, ec, U_RR, E2, U[U_G0], tmp)              # g0 = c·r (4,4)
    _dotc(U, U_C, ec, E1, U[U_G3])                         # g3 = c·E1 (3,3)
    _dotc(U, U_C, ec, E2v, U[U_G4])                        # g4 = c·E2
    e44 = (1, 1, 4, 4)
    pderiv(U[U_G0], e44, 2, w2, U[U_GU])
    pderiv(U[U_G0], e44, 3, w3, U[U_GV])
    pderiv(U[U_G3], ec, 2, w2, U[U_GU + 1])
    pderiv(U[U_G3], ec, 3, w3, U[U_GV + 1])
    pderiv(U[U_G4], ec, 2, w2, U[U_GU + 2])
    pderiv(U[U_G4], ec, 3, w3, U[U_GV + 2])
    # |d1|² = l00 + σ l10 + τ l01 + σ² |E1|² + στ 2 E1·E2 + τ² |E2|²
    _dotv(U, U_RR, E2, U_RR, E2, U[U_L00], tmp)
    _dotc(U, U_RR, E2, (2.0 * E1[0], 2.0 * E1[1], 2.0 * E1[2]), U[U_L10])
    _dotc(U, U_RR, E2, (2.0 * E2v[0], 2.0 * E2v[1], 2.0 * E2v[2]), U[U_L01])
    l20 = E1[0] * E1[0] + E1[1] * E1[1] + E1[2] * E1[2]
    l11 = 2.0 * (E1[0] * E2v[0] + E1[1] * E2v[1] + E1[2] * E2v[2])
    l02 = E2v[0] * E2v[0] + E2v[1] * E2v[1] + E2v[2] * E2v[2]
    # t1, t2: unit tangents of the caster (as chain1)
    l = math.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    t1 = (e1[0] / l, e1[1] / l, e1[2] / l)
    t2 = (ng[1] * t1[2] - ng[2] * t1[1], ng[2] * t1[0] - ng[0] * t1[2], ng[0] * t1[1] - ng[1] * t1[0])
    l = math.sqrt(t2[0] ** 2 + t2[1] ** 2 + t2[2] ** 2)
    t2 = (t2[0] / l, t2[1] / l, t2[2] / l)
    ak = math.sqrt((ek1[1] * ek2[2] - ek1[2] * ek2[1]) ** 2 + (ek1[2] * ek2[0] - ek1[0] * ek2[2]) ** 2
                   + (ek1[0] * ek2[1] - ek1[1] * ek2[0]) ** 2)
    DET1 = scr[SCR4:SCR4 + N4]
    NUM = scr[SCR4 + N4:SCR4 + 2 * N4]
    nfin = N4
    kscale = 1.0 / (ws * wt)  # detk in (uk, vk) units: ∂/∂uk = (1/ws) ∂/∂σ, ∂/∂vk = (1/wt) ∂/∂τ
    best_hi = 0.0
    best_lo = np.inf
    for variant in range(2):
        hi_v[variant] = np.inf
        lo_v[variant] = 0.0
    for bi in range(2):
        bb = t1 if bi == 0 else t2
        _dotc(U, U_C, ec, bb, U[U_A])                      # A (3,3)
        _zero(25, U[U_A2])
        _mac2(U[U_A], 3, 3, U[U_A], 3, 3, U[U_A2], 1.0)    # A² (5,5)
        for k in range(4):                                 # m = n × b (affine)
            n0, n1, n2 = U[S_N, k], U[S_N + 1, k], U[S_N + 2, k]
            U[U_M, k] = n1 * bb[2] - n2 * bb[1]
            U[U_M + 1, k] = n2 * bb[0] - n0 * bb[2]
            U[U_M + 2, k] = n0 * bb[1] - n1 * bb[0]
        _dotv(U, U_RR, E2, U_M, E2, U[U_B00], tmp)         # B = b00 + σ b10 + τ b01
        _dotc(U, U_M, E2, E1, U[U_B10])
        _dotc(U, U_M, E2, E2v, U[U_B01])
        # l_α A² (|α| <= 1)
        _zero(49, U[U_P])
        _mac2(U[U_L00], 3, 3, U[U_A2], 5, 5, U[U_P], 1.0)          # (7,7)
        _zero(36, U[U_P + 1])
        _mac2(U[U_L10], 2, 2, U[U_A2], 5, 5, U[U_P + 1], 1.0)      # (6,6)
        _zero(36, U[U_P + 2])
        _mac2(U[U_L01], 2, 2, U[U_A2], 5, 5, U[U_P + 2], 1.0)
        # |d0|² × (coefficients of B²): b00², 2 b00 b10, 2 b00 b01, b10², 2 b10 b01, b01²
        _zero(25, U[U_T])
        _mac2(U[U_L0], 3, 3, U[U_B00], 3, 3, U[U_T], 1.0)          # L0 b00 (5,5)
        _zero(49, U[U_R])
        _mac2(U[U_T], 5, 5, U[U_B00], 3, 3, U[U_R], 1.0)           # (7,7)
        _zero(36, U[U_R + 1])
        _mac2(U[U_T], 5, 5, U[U_B10], 2, 2, U[U_R + 1], 2.0)       # (6,6)
        _zero(36, U[U_R + 2])
        _mac2(U[U_T], 5, 5, U[U_B01], 2, 2, U[U_R + 2], 2.0)
        for t in range(3):
            _zero(9, U[U_TMP2])
            x = U_B10 if t < 2 else U_B01
            y = U_B10 if t == 0 else U_B01
            _mac2(U[x], 2, 2, U[y], 2, 2, U[U_TMP2], 1.0 if t != 1 else 2.0)   # (3,3)
            _zero(25, U[U_R + 3 + t])
            _mac2(U[U_L0], 3, 3, U[U_TMP2], 3, 3, U[U_R + 3 + t], 1.0)       # (5,5)
        for variant in range(2):
            if not (mask >> variant) & 1:
                continue
            o = 1.0 if variant == 0 else -1.0
            eta_f = 1.0 / _eta_ratio(o, eta)
            s = -eta_f * eta_f
            # f_α = l_α A² - η² L0 (B²)_α, extents 7 - |α|; their u1 / v1 derivatives
            for ia in range(6):
                da = 0 if ia == 0 else (1 if ia < 3 else 2)
                na = 7 - da
                fa = U[U_F + ia]
                ra = U[U_R + ia]
                if ia < 3:
                    pa = U[U_P + ia]
                    for k in range(na * na):
                        fa[k] = pa[k] + s * ra[k]
                else:
                    lc = l20 if ia == 3 else (l11 if ia == 4 else l02)
                    a2 = U[U_A2]
                    for k in range(25):
                        fa[k] = lc * a2[k] + s * ra[k]
                pderiv(fa, (1, 1, na, na), 2, w2, U[U_FU + ia])
                pderiv(fa, (1, 1, na, na), 3, w3, U[U_FV + ia])
            # det1 = F_u1 G_v1 - F_v1 G_u1 = Σ_γ σ^γa τ^γb Σ_{α+β=γ} (f_α,u1 g_β,v1 - f_α,v1 g_β,u1)
            for ig in range(10):
                dg = 0 if ig == 0 else (1 if ig < 3 else (2 if ig < 6 else 3))
                _zero((9 - dg) * (9 - dg), U[U_DET + ig])
            _det_alpha0(U, 0, 0)
            _det_alpha1(U, 1, 1, 3)
            _det_alpha1(U, 2, 2, 4)
            for ba in range(3):
                _det_alpha2(U, 3 + ba, 3 + ba, 6 + ba)
            # F_σ G_τ - F_τ G_σ with F_σ = f10 + 2σ f20 + τ f11, F_τ = f01 + σ f11 + 2τ f02, G_σ = g3, G_τ = g4
            # (sizes written out as constants: the kernels are then compiled for fixed loop lengths)
            _zero(64, U[U_NK])
            _mac2(U[U_F + 1], 6, 6, U[U_G4], 3, 3, U[U_NK], 1.0)    # f10 g4 - f01 g3 (8, 8)
            _mac2(U[U_F + 2], 6, 6, U[U_G3], 3, 3, U[U_NK], -1.0)
            _zero(81, U[U_NC])
            _mac2(U[U_COS], 2, 2, U[U_NK], 8, 8, U[U_NC], 1.0)
            _zero(49, U[U_NK + 1])
            _mac2(U[U_F + 3], 5, 5, U[U_G4], 3, 3, U[U_NK + 1], 2.0)    # σ: 2 f20 g4 - f11 g3 (7, 7)
            _mac2(U[U_F + 4], 5, 5, U[U_G3], 3, 3, U[U_NK + 1], -1.0)
            _zero(64, U[U_NC + 1])
            _mac2(U[U_COS], 2, 2, U[U_NK + 1], 7, 7, U[U_NC + 1], 1.0)
            _zero(49, U[U_NK + 2])
            _mac2(U[U_F + 4], 5, 5, U[U_G4], 3, 3, U[U_NK + 2], 1.0)    # τ: f11 g4 - 2 f02 g3
            _mac2(U[U_F + 5], 5, 5, U[U_G3], 3, 3, U[U_NK + 2], -2.0)
            _zero(64, U[U_NC + 2])
            _mac2(U[U_COS], 2, 2, U[U_NK + 2], 7, 7, U[U_NC + 2], 1.0)
            _det_to_bernstein4(U, DET1, tmp)
            _num_to_bernstein4(U, kscale, NUM, tmp)
            a, b2, c, d = ratio_bound(NUM, DET1, nfin, scr[SCR4 + 2 * N4:SCR4 + 3 * N4])
            hi_v[variant] = min(hi_v[variant], abs_upper(a, b2, c, d))
            lo_v[variant] = max(lo_v[variant], abs_lower(a, b2, c, d))
    for variant in range(2):
        if not (mask >> variant) & 1:
            continue
        best_hi = max(best_hi, hi_v[variant])
        best_lo = min(best_lo, lo_v[variant])
    if best_lo == np.inf:
        best_lo = 0.0
    return best_hi * dlo ** -1.5 / ak * (1.0 + IRR_PAD), best_lo * dhi ** -1.5 / ak * (1.0 - IRR_PAD)


# ---------------------------------------------------------------------------------------
# the quadtree per tuple


@kernel
def _irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos):
    if refract:
        return box_irradiance_refract(W, U, scr, x0, P, N, Q, eta, lo, hi, pos)
    return box_irradiance_reflect(W, work, Q, lo, hi)


@kernel
def refine_irradiance(W, U, work, scr, rstack, refract, x0, P, N, Q, UV, eta, lo, hi, levels, stats):
    """Ē, E̲ of a piece whose own Ē is infinite, as the max / min over a quadtree of sub-boxes
    of its (u1, v1) box (at most ``levels`` deep, splitting only sub-boxes that are still
    unbounded).  Each sub-box uses its own position bound as the (uk, vk) box of the implicit
    bound (eq 17–19) and is skipped when that bound misses the receiver (no path there), so
    the result bounds every path of the piece (eq 21 over a finer partition); it stays
    infinite when a sub-box at the last level is still unbounded (a focal point, or the
    0/0 of the implicit form at normal incidence).  The piece itself is unchanged."""
    slo = scr[36:38]
    shi = scr[38:40]
    spos = scr[40:48]
    res = scr[48:56]
    top = 0
    ehi = 0.0
    elo = np.inf
    found = False
    top = push_children(rstack, top, lo, hi, 0)
    while top > 0:
        top -= 1
        slo[0], shi[0], slo[1], shi[1] = rstack[top, 0], rstack[top, 1], rstack[top, 2], rstack[top, 3]
        level = int(rstack[top, 4])
        stats[0] += 1
        if not box_position(W, work, refract, x0, P, N, UV, eta, slo, shi, spos, res):
            continue
        stats[1] += 1
        h, l = _irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, slo, shi, spos)
        if not h < np.inf:
            if level >= levels:
                return np.inf, 0.0
            top = push_children(rstack, top, slo, shi, level)
            continue
        found = True
        ehi = max(ehi, h)
        elo = min(elo, l)
    if not found:
        return 0.0, 0.0
    return ehi, elo


@kernel
def tuple_pieces_fast(W, U, work, scr, stack, rstack, refract, x0, P, N, Q, UV, eta, max_depth, sigma, alpha, irradiance,
                      irr_refine, out, stats):
    """chain1.tuple_pieces with the fast engine: same stopping rules (§6.1), same piece rows.

    The root's position bound is computed before the per-tuple polynomials of the irradiance
    so that a tuple whose caustic misses the receiver triangle costs one position bound.
    The caller has built the caster's polynomials (:func:`_setup_caster`) in W."""
    cap = out.shape[0]
    _setup_tuple(W, refract, x0, P, Q)
    have_irr = False
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0.0, 1.0, 0.0, 1.0, 0.0
    top = 1
    count = 0
    lo = scr[0:2]
    hi = scr[2:4]
    pos = scr[4:12]
    res = scr[12:20]
    while top > 0:
        top -= 1
        lo[0], hi[0], lo[1], hi[1] = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        depth = int(stack[top, 4])
        stats[0] += 1
        if not box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, pos, res):
            continue
        if irradiance and not refract and not have_irr:
            _setup_reflect_irradiance(W)
            have_irr = True
        can_split = depth < max_depth and count + top + 4 <= cap
        area = (pos[1] - pos[0]) * (pos[3] - pos[2])
        ehi = np.inf
        elo = 0.0
        split = False
        if area >= sigma and can_split:
            if irradiance:
                stats[1] += 1
                ehi, elo = _irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
                split = not (elo > 0.0 and ehi < alpha * elo)
            else:
                split = True
        elif irradiance:
            stats[1] += 1
            ehi, elo = _irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
        if split:
            top = push_children(stack, top, lo, hi, depth)
            continue
        if depth < max_depth and area >= sigma and not can_split:
            stats[3] += 1
        if irradiance and not ehi < np.inf and irr_refine > 0:
            ehi, elo = refine_irradiance(W, U, work, scr, rstack, refract, x0, P, N, Q, UV, eta, lo, hi, irr_refine, stats)
        if irradiance and not ehi < np.inf:
            stats[2] += 1
        row = out[count]
        row[P_U0], row[P_U1], row[P_V0], row[P_V1] = lo[0], hi[0], lo[1], hi[1]
        for k in range(8):
            row[P_BU0 + k] = pos[k]
        row[P_EHI] = ehi
        row[P_ELO] = elo
        row[P_DEPTH] = depth
        count += 1
    return count


@kernel
def workspace():
    return np.zeros((NSLOTS, MAXC)), np.zeros(16), np.zeros(SCR4 + 3 * N4), np.zeros((NU, UW))


@kernel
def _batch_chunk(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts, stats,
                 start, stop):
    """Tuples start..stop-1 on one workspace (``batch_fast``)."""
    W, work, scr, U = workspace()
    stack = np.empty((4 * (max_depth + 2), 5))
    rstack = np.empty((4 * (irr_refine + 2), 5))
    last = -1
    for t in range(start, stop):
        c = pairs[t, 0]
        r = pairs[t, 1]
        if c != last:  # pairs are usually grouped by caster: its polynomials are reused
            _setup_caster(W, refract, x0, P[c], N[c])
            last = c
        counts[t] = tuple_pieces_fast(W, U, work, scr, stack, rstack, refract, x0, P[c], N[c], Q[r], UV[r], eta, max_depth, sigma,
                                      alpha, irradiance, irr_refine, out[t], stats[t])


def batch_fast(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts, stats, chunk):
    """Every (caster, receiver) tuple of ``pairs`` in chunks of ``chunk`` tuples, one workspace
    per chunk, on ``jit.run_chunks`` threads (``_batch_chunk`` releases the GIL; a
    ``parallel=True`` loop over the chunks took seconds longer to compile on a cold bake)."""
    from ..runtime.jit import run_chunks

    n = pairs.shape[0]
    run_chunks(_batch_chunk, (refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts,
                              stats), n, max(1, -(-n // max(1, int(chunk)))))


@kernel
def eval_box(refract, x0, P, N, Q, UV, eta, lo, hi, pos):
    """One box of one tuple, for tests: writes the position bound into pos[0:8] and returns
    (inside, Ē, E̲) as chain1.piece_position / piece_irradiance_* would."""
    W, work, scr, U = workspace()
    make_context(W, refract, False, x0, P, N, Q)
    res = np.zeros(8)
    if not box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, pos, res):
        return False, 0.0, 0.0
    if not refract:
        _setup_reflect_irradiance(W)
    ehi, elo = _irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
    return True, ehi, elo
