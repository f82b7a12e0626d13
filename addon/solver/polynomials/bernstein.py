"""Tensor-product Bernstein polynomials in up to four variables (Fan et al. 2025, §4.1).

A polynomial is a C-contiguous float64 array of rank 4 whose shape is (n0+1, n1+1, n2+1, n3+1):
its Bernstein coefficients b_i of degree n = (n0, n1, n2, n3) on a box (eq 1, 2).  Unused
variables have degree 0 (extent 1).  The box itself is not stored: every function works on
the unit box of the local coordinates, and callers that differentiate pass the box widths.

Everything is Numba (``kernel``: cached, nopython) so that the per-piece bound code in
the bounds engines can call it without Python overhead.  Results are fresh arrays; inputs are never
modified.  The range property used throughout is

    min_i b_i(p) / b_i(q) <= p(x)/q(x) <= max_i b_i(p) / b_i(q)     (eq 3)

whenever all b_i(q) share one sign and are non-zero (Narkawicz et al. 2012); for a polynomial
(q = 1) it is min_i b_i <= p(x) <= max_i b_i.
"""

import math

import numpy as np

from ..runtime.jit import kernel

MAX_DEGREE = 96


def _binomials(n):
    table = np.zeros((n + 1, n + 1))
    for i in range(n + 1):
        table[i, 0] = 1.0
        for j in range(1, i + 1):
            table[i, j] = table[i - 1, j - 1] + table[i - 1, j]
    return table


BINOM = _binomials(MAX_DEGREE)


@kernel
def _split(shape, dim):
    pre = 1
    for d in range(dim):
        pre *= shape[d]
    post = 1
    for d in range(dim + 1, 4):
        post *= shape[d]
    return pre, shape[dim], post


@kernel
def with_extent(shape, dim, k):
    return (k if dim == 0 else shape[0], k if dim == 1 else shape[1], k if dim == 2 else shape[2], k if dim == 3 else shape[3])


@kernel
def constant(c):
    """The constant polynomial c (degree 0 in every variable)."""
    out = np.empty((1, 1, 1, 1))
    out[0, 0, 0, 0] = c
    return out


@kernel
def affine(c, g, lo, hi):
    """Bernstein form of c + sum_j g[j] x_j over the box lo <= x <= hi (global coordinates).

    Degree 1 in each variable with g[j] != 0, else 0; the coefficients of an affine function
    of degree 1 are its values at the box corners (eq 2 with n = 1)."""
    n0 = 2 if g[0] != 0.0 else 1
    n1 = 2 if g[1] != 0.0 else 1
    n2 = 2 if g[2] != 0.0 else 1
    n3 = 2 if g[3] != 0.0 else 1
    out = np.empty((n0, n1, n2, n3))
    for i0 in range(n0):
        for i1 in range(n1):
            for i2 in range(n2):
                for i3 in range(n3):
                    out[i0, i1, i2, i3] = (c + g[0] * (hi[0] if i0 else lo[0]) + g[1] * (hi[1] if i1 else lo[1])
                                           + g[2] * (hi[2] if i2 else lo[2]) + g[3] * (hi[3] if i3 else lo[3]))
    return out


@kernel
def elevate(a, shape):
    """Degree elevation to the extents in ``shape`` (each >= a's): b'_k = sum_i C(m,i)
    C(n-m,k-i) / C(n,k) b_i per variable (Farouki 2012), one variable at a time (the 4-D
    product with the constant 1 of degree n - m gives the same coefficients at many times the
    cost)."""
    out = a
    for dim in range(4):
        m1 = out.shape[dim]
        n1 = shape[dim]
        if n1 == m1:
            continue
        pre, _, post = _split(out.shape, dim)
        src = np.ascontiguousarray(out).reshape((pre, m1, post))
        res = np.zeros((pre, n1, post))
        m = m1 - 1
        n = n1 - 1
        r = n - m
        for k in range(n1):
            for i in range(max(0, k - r), min(m, k) + 1):
                w = BINOM[m, i] * BINOM[r, k - i] / BINOM[n, k]
                for p in range(pre):
                    for q in range(post):
                        res[p, k, q] += w * src[p, i, q]
        out = res.reshape(with_extent(out.shape, dim, n1))
    if out is a:
        return a.copy()
    return out


@kernel
def elevate_dim(a, dim, n):
    """Elevate variable ``dim`` to degree n (>= its current degree)."""
    s = a.shape
    return elevate(a, (n + 1 if dim == 0 else s[0], n + 1 if dim == 1 else s[1], n + 1 if dim == 2 else s[2],
                       n + 1 if dim == 3 else s[3]))


@kernel
def _common(a, b):
    shape = (max(a.shape[0], b.shape[0]), max(a.shape[1], b.shape[1]), max(a.shape[2], b.shape[2]), max(a.shape[3], b.shape[3]))
    return elevate(a, shape), elevate(b, shape)


@kernel
def _axpby(x, sa, y, sb):
    """sa·x + sb·y for arrays of one shape (explicit loop: 4-D array expressions are slow to compile)."""
    out = np.empty(x.shape)
    of = out.ravel()
    xf = x.ravel()
    yf = y.ravel()
    for i in range(of.shape[0]):
        of[i] = sa * xf[i] + sb * yf[i]
    return out


@kernel
def affine_map(a, s, c):
    """s·a + c for scalars s, c (adding c to every coefficient adds the constant c)."""
    out = np.empty(a.shape)
    of = out.ravel()
    af = a.ravel()
    for i in range(of.shape[0]):
        of[i] = s * af[i] + c
    return out


@kernel
def add(a, b):
    """Sum in Bernstein form (both elevated to the common degree)."""
    x, y = _common(a, b)
    return _axpby(x, 1.0, y, 1.0)


@kernel
def sub(a, b):
    """Difference in Bernstein form."""
    x, y = _common(a, b)
    return _axpby(x, 1.0, y, -1.0)


@kernel
def lincomb(a, sa, b, sb):
    """sa·a + sb·b for scalars sa, sb."""
    x, y = _common(a, b)
    return _axpby(x, sa, y, sb)


@kernel
def _scaled(a):
    """a's coefficients times the binomials C(n, i) of every variable (the power-like scaling
    under which the Bernstein product is a plain convolution)."""
    s0, s1, s2, s3 = a.shape
    out = np.empty(a.shape)
    for i0 in range(s0):
        for i1 in range(s1):
            w01 = BINOM[s0 - 1, i0] * BINOM[s1 - 1, i1]
            for i2 in range(s2):
                w = w01 * BINOM[s2 - 1, i2]
                for i3 in range(s3):
                    out[i0, i1, i2, i3] = a[i0, i1, i2, i3] * w * BINOM[s3 - 1, i3]
    return out


@kernel
def mul(a, b):
    """Product in Bernstein form: with scaled coefficients C(n,i) b_i the product is a
    convolution; dividing by C(n+m,k) returns to the Bernstein basis (Farouki 2012).  The
    convolution runs over the smaller factor's coefficients outside and the larger one's
    inside, whose last axis is contiguous in both arrays."""
    if a.size < b.size:
        a, b = b, a
    s0, s1, s2, s3 = a.shape
    t0, t1, t2, t3 = b.shape
    sa = _scaled(a)
    sb = _scaled(b)
    out = np.zeros((s0 + t0 - 1, s1 + t1 - 1, s2 + t2 - 1, s3 + t3 - 1))
    for j0 in range(t0):
        for j1 in range(t1):
            for j2 in range(t2):
                for j3 in range(t3):
                    w = sb[j0, j1, j2, j3]
                    if w == 0.0:
                        continue
                    for i0 in range(s0):
                        for i1 in range(s1):
                            for i2 in range(s2):
                                row = out[i0 + j0, i1 + j1, i2 + j2]
                                src = sa[i0, i1, i2]
                                for i3 in range(s3):
                                    row[i3 + j3] += w * src[i3]
    o0, o1, o2, o3 = out.shape
    for k0 in range(o0):
        for k1 in range(o1):
            w01 = BINOM[o0 - 1, k0] * BINOM[o1 - 1, k1]
            for k2 in range(o2):
                w = w01 * BINOM[o2 - 1, k2]
                for k3 in range(o3):
                    out[k0, k1, k2, k3] /= w * BINOM[o3 - 1, k3]
    return out


@kernel
def deriv(a, dim, width):
    """Partial derivative with respect to the global variable ``dim`` whose box has the
    given width: n (b_{i+1} - b_i) / width, degree n-1 (a constant gives 0)."""
    s0, s1, s2, s3 = a.shape
    m = a.shape[dim]
    if m == 1:
        return np.zeros((s0, s1, s2, s3))
    f = (m - 1) / width
    o0 = s0 - 1 if dim == 0 else s0
    o1 = s1 - 1 if dim == 1 else s1
    o2 = s2 - 1 if dim == 2 else s2
    o3 = s3 - 1 if dim == 3 else s3
    out = np.empty((o0, o1, o2, o3))
    j0 = 1 if dim == 0 else 0
    j1 = 1 if dim == 1 else 0
    j2 = 1 if dim == 2 else 0
    j3 = 1 if dim == 3 else 0
    for i0 in range(o0):
        for i1 in range(o1):
            for i2 in range(o2):
                for i3 in range(o3):
                    out[i0, i1, i2, i3] = f * (a[i0 + j0, i1 + j1, i2 + j2, i3 + j3] - a[i0, i1, i2, i3])
    return out


@kernel
def subdivide(a, dim, t):
    """de Casteljau split of variable ``dim`` at local parameter t (0.5: midpoint): returns
    the Bernstein coefficients of the two halves, each on its own unit box."""
    pre, m1, post = _split(a.shape, dim)
    src = np.ascontiguousarray(a).reshape((pre, m1, post))
    left = np.empty((pre, m1, post))
    right = np.empty((pre, m1, post))
    work = np.empty(m1)
    for p in range(pre):
        for q in range(post):
            for i in range(m1):
                work[i] = src[p, i, q]
            left[p, 0, q] = work[0]
            right[p, m1 - 1, q] = work[m1 - 1]
            for r in range(1, m1):
                for i in range(m1 - r):
                    work[i] = (1.0 - t) * work[i] + t * work[i + 1]
                left[p, r, q] = work[0]
                right[p, m1 - 1 - r, q] = work[m1 - 1 - r]
    return left.reshape(a.shape), right.reshape(a.shape)


@kernel
def power_to_bernstein(a):
    """Power-basis coefficients a[i] of x^i (tensor, on the unit box) -> Bernstein
    coefficients of the same degree: b_i = sum_{j<=i} C(i,j)/C(n,j) a_j in each variable."""
    out = a.copy()
    for dim in range(4):
        pre, m1, post = _split(out.shape, dim)
        n = m1 - 1
        if n == 0:
            continue
        src = out.reshape((pre, m1, post))
        res = np.zeros((pre, m1, post))
        for i in range(m1):
            for j in range(i + 1):
                w = BINOM[i, j] / BINOM[n, j]
                for p in range(pre):
                    for q in range(post):
                        res[p, i, q] += w * src[p, j, q]
        out = res.reshape(out.shape)
    return out


@kernel
def evaluate(a, x0, x1, x2, x3):
    """Value at local coordinates (x0..x3) in [0,1] (de Casteljau-free: explicit basis sum)."""
    s0, s1, s2, s3 = a.shape
    total = 0.0
    for i0 in range(s0):
        w0 = BINOM[s0 - 1, i0] * x0 ** i0 * (1.0 - x0) ** (s0 - 1 - i0)
        for i1 in range(s1):
            w1 = w0 * BINOM[s1 - 1, i1] * x1 ** i1 * (1.0 - x1) ** (s1 - 1 - i1)
            for i2 in range(s2):
                w2 = w1 * BINOM[s2 - 1, i2] * x2 ** i2 * (1.0 - x2) ** (s2 - 1 - i2)
                for i3 in range(s3):
                    total += w2 * BINOM[s3 - 1, i3] * x3 ** i3 * (1.0 - x3) ** (s3 - 1 - i3) * a[i0, i1, i2, i3]
    return total


@kernel
def coef_range(a):
    """(min, max) of the coefficients: a bound of the polynomial's range over the box (eq 3, q = 1)."""
    lo = np.inf
    hi = -np.inf
    for v in a.ravel():
        lo = min(lo, v)
        hi = max(hi, v)
    return lo, hi


@kernel
def _ratio_range(p, q):
    """(ok, min, max) of p_i/q_i when every q_i has one strict sign, else ok = False."""
    pos = True
    neg = True
    for v in q.ravel():
        if not v > 0.0:
            pos = False
        if not v < 0.0:
            neg = False
    if not (pos or neg):
        return False, -np.inf, np.inf
    lo = np.inf
    hi = -np.inf
    pf = p.ravel()
    qf = q.ravel()
    for i in range(pf.shape[0]):
        r = pf[i] / qf[i]
        lo = min(lo, r)
        hi = max(hi, r)
    return True, lo, hi


@kernel
def rational_bound(p, q):
    """Range of p/q over the box as a union of two intervals (lo1, hi1, lo2, hi2); an empty
    interval has lo > hi.  Fan et al. 2025 eq 3 and the two fallbacks of §4.1:

    * all b_i(q) of one strict sign: [min b_i(p)/b_i(q), max ...] (second interval empty);
    * else, all b_i(p) of one strict sign (the reciprocal case): q/p in [r_lo, r_hi], so
      p/q lies in [1/r_hi, 1/r_lo] if 0 is outside [r_lo, r_hi], else in
      (-inf, 1/r_lo] U [1/r_hi, +inf) (two intervals);
    * neither: the universal set (-inf, +inf) (grazing angles, focal points).
    p and q are first elevated to a common degree.
    """
    pp, qq = _common(p, q)
    return bound_of_coefficients(pp, qq)


@kernel
def bound_of_coefficients(pp, qq):
    """The three cases of ``rational_bound`` on coefficient arrays of one shape."""
    ok, lo, hi = _ratio_range(pp, qq)
    if ok:
        return lo, hi, np.inf, -np.inf
    ok, rlo, rhi = _ratio_range(qq, pp)
    if not ok:
        return -np.inf, np.inf, np.inf, -np.inf
    if rlo > 0.0 or rhi < 0.0:
        return 1.0 / rhi, 1.0 / rlo, np.inf, -np.inf
    a = 1.0 / rlo if rlo < 0.0 else -np.inf  # 1/r for r in [r_lo, 0)
    b = 1.0 / rhi if rhi > 0.0 else np.inf   # 1/r for r in (0, r_hi]
    if rlo == 0.0:
        return b, np.inf, np.inf, -np.inf
    if rhi == 0.0:
        return -np.inf, a, np.inf, -np.inf
    return -np.inf, a, b, np.inf


@kernel
def clip_hull(lo1, hi1, lo2, hi2, a, b):
    """Hull of ([lo1,hi1] U [lo2,hi2]) ∩ [a, b]; (lo, hi) with lo > hi when empty."""
    lo = np.inf
    hi = -np.inf
    x, y = max(lo1, a), min(hi1, b)
    if x <= y:
        lo, hi = min(lo, x), max(hi, y)
    x, y = max(lo2, a), min(hi2, b)
    if x <= y:
        lo, hi = min(lo, x), max(hi, y)
    return lo, hi


@kernel
def abs_upper(lo1, hi1, lo2, hi2):
    """max |f| over the rational bound's union of intervals (inf when unbounded)."""
    m = 0.0
    if lo1 <= hi1:
        m = max(m, abs(lo1), abs(hi1))
    if lo2 <= hi2:
        m = max(m, abs(lo2), abs(hi2))
    return m


@kernel
def abs_lower(lo1, hi1, lo2, hi2):
    """min |f| over the rational bound (0 when an interval contains 0)."""
    m = np.inf
    for lo, hi in ((lo1, hi1), (lo2, hi2)):
        if lo <= hi:
            if lo <= 0.0 <= hi:
                return 0.0
            m = min(m, min(abs(lo), abs(hi)))
    return m if m < np.inf else 0.0


def binomial(n, k):
    """C(n, k) as a float (n <= MAX_DEGREE)."""
    return float(BINOM[n, k]) if 0 <= k <= n else 0.0


@kernel
def sqrt_linearisation(beta_lo, beta_hi):
    """Linear approximation r(β) = a β + b of √β on [β_lo, β_hi] (β_lo >= 0) and the bound
    [δ_lo, δ_hi] of the error δ = √β - r(β) there (Fan et al. 2025 eq 12–13).

    r is the chord of √β shifted by half the largest gap: √β is concave, so the gap
    √β - chord is 0 at both ends and largest where (√β)' equals the chord slope s,
    i.e. at √β* = 1/(2s); with g = √β* - chord(β*) the error is in [-g/2, g/2].  The
    returned interval is widened by a few ulps of √β_hi so the enclosure survives rounding.
    Returns (a, b, δ_lo, δ_hi)."""
    lo = max(beta_lo, 0.0)
    hi = max(beta_hi, lo)
    sl = math.sqrt(lo)
    sh = math.sqrt(hi)
    pad = 4e-16 * (sh + 1e-300) + 1e-300
    if hi - lo <= 1e-300 or sh - sl <= 0.0:
        return 0.0, sh, -pad - (sh - sl), pad
    s = (sh - sl) / (hi - lo)
    root = 0.5 / s  # √β* (between sl and sh by concavity)
    root = min(max(root, sl), sh)
    gap = root - (sl + s * (root * root - lo))
    gap = max(gap, 0.0)
    a = s
    b = sl - s * lo + 0.5 * gap
    return a, b, -0.5 * gap - pad, 0.5 * gap + pad
