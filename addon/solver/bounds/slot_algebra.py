"""Flat 4-D polynomials in a per-thread workspace: the algebra of the one-bounce bounds engine.

A polynomial is a flat slice of a workspace row plus its extents (e0, e1, e2, e3) = degree + 1
per variable, variable order (uk, vk, u1, v1) so that the long (u1, v1) axes are the innermost
loops (2-variable polynomials have e0 = e1 = 1).  Products are formed in *scaled* Bernstein
form c_i = b_i Π C(n_d, i_d), where the Bernstein product (Farouki 2012) is a plain
convolution; affine polynomials (degree 1) have c = b.  For a rational bound p/q at one common
degree the ratios c_i(p)/c_i(q) equal b_i(p)/b_i(q) (the binomial factors cancel), so Fan et
al. 2025 eq 3 applies to scaled coefficients directly (``ratio_bound``).  Sub-box restriction
is de Casteljau's split (exact up to rounding).  No allocation: callers pass the workspace.

Tested through the one-bounce engine (tests/solver/test_bounds_validity.py,
tests/solver/test_bounds_bernstein.py against the reference engine and dense sampling).
"""


import numpy as np

from ..runtime.jit import kernel
from ..polynomials.bernstein import BINOM


# ---------------------------------------------------------------------------------------
# flat 4-D polynomial kernels (scaled Bernstein unless said otherwise)

MAXC = 128  # coefficients per workspace slot (largest: (1, 1, 11, 11) = 121); 128 keeps the slots
# of one workspace close together in cache (a 4-D polynomial of the T irradiance lives in scr)
N4 = 4 * 4 * 11 * 11  # coefficients of the final T irradiance polynomials (uk, vk, u1, v1)
SCR4 = 64  # offset of those two in scr


@kernel
def coef_count(e):
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
        for k in range(coef_count(ea)):
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
def affine2(c, gu, gv, lo, hi, out):
    """c + gu u1 + gv v1 on the box: degree 1, coefficients = corner values (variables 2, 3)."""
    out[0] = c + gu * lo[0] + gv * lo[1]
    out[1] = c + gu * lo[0] + gv * hi[1]
    out[2] = c + gu * hi[0] + gv * lo[1]
    out[3] = c + gu * hi[0] + gv * hi[1]


@kernel
def axpy(n, s, x, out):
    for k in range(n):
        out[k] += s * x[k]


@kernel
def scal(n, s, x, out):
    for k in range(n):
        out[k] = s * x[k]


@kernel
def dot_fields(W, a0, ea, b0, eb, out, tmp):
    """out = Σ_c W[a0+c]·W[b0+c] (3-vectors of polynomials in slots); returns the extents."""
    eo = pmul(W[a0], ea, W[b0], eb, out)
    n = coef_count(eo)
    for c in range(1, 3):
        pmul(W[a0 + c], ea, W[b0 + c], eb, tmp)
        for k in range(n):
            out[k] += tmp[k]
    return eo


@kernel
def dot_const(W, a0, ea, c, out):
    """out = Σ_c W[a0+c] · c[c] for a constant 3-vector c."""
    n = coef_count(ea)
    for k in range(n):
        out[k] = c[0] * W[a0, k] + c[1] * W[a0 + 1, k] + c[2] * W[a0 + 2, k]


@kernel
def cross_fields(W, a0, ea, b0, eb, o0, tmp):
    """W[o0..o0+2] = W[a0..] × W[b0..]; returns the extents."""
    eo = ea
    for c in range(3):
        i = (c + 1) % 3
        j = (c + 2) % 3
        eo = pmul(W[a0 + i], ea, W[b0 + j], eb, W[o0 + c])
        pmul(W[a0 + j], ea, W[b0 + i], eb, tmp)
        n = coef_count(eo)
        for k in range(n):
            W[o0 + c, k] -= tmp[k]
    return eo


# 2-D products in (u1, v1) (the refraction irradiance rows)

@kernel
def mac2(a, p0, p1, b, q0, q1, out, s):
    """out += s·a·b for polynomials in (u1, v1) only (scaled Bernstein: a 2-D convolution);
    a has extents (p0, p1), b (q0, q1), out (p0 + q0 - 1, p1 + q1 - 1).  The operand with the
    longer rows runs in the innermost loop (the product is symmetric)."""
    if p1 > q1:
        mac2_rows(b, q0, q1, a, p0, p1, out, s)
    else:
        mac2_rows(a, p0, p1, b, q0, q1, out, s)


@kernel
def mac2_rows(a, p0, p1, b, q0, q1, out, s):
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
def zero_fill(n, x):
    for k in range(n):
        x[k] = 0.0


@kernel
def elevate2(a, n, m, s, out, tmp):
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
def to_bernstein2(a, m):
    """Scaled -> plain Bernstein coefficients in (u1, v1), extents (m, m), in place."""
    for i in range(m):
        for j in range(m):
            a[i * m + j] /= BINOM[m - 1, i] * BINOM[m - 1, j]
