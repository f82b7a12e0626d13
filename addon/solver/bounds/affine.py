"""Affine arithmetic with first-order derivatives over a box of (u1, v1) (Stolfi & de Figueiredo).

An affine form is a 4-tuple (c, a, b, r): x = c + a δu + b δv + e with δu, δv in [-1, 1]
(u1 = u_c + h_u δu, v1 = v_c + h_v δv) and |e| <= r.  A *dual* is (value, ∂/∂u1, ∂/∂v1), each
an affine form; a dual 3-vector is a tuple of three duals.  Products keep the linear parts
exactly and move only second-order terms into r, so correlated quantities (the numerator and
denominator of eq 9, the two products of eq 16's determinant) cancel as in the exact function;
every operation widens r by a relative ``ROUND`` for floating-point rounding, so the enclosures
are conservative.  ``aff_sqrt`` is the Chebyshev affine form of √ with its error in r.

Used by the two-bounce irradiance bound and the exact-map image boxes
(``two_bounce_irradiance``, ``two_bounce_image``); tested in tests/solver/test_bounds_two_bounce.py
(enclosures against dense evaluation).
"""

import math

import numpy as np

from ..runtime.jit import kernel


# --------------------------------------------------------------------------------------------
# Affine forms over the box: x = c + a δu + b δv + e with δu, δv in [-1, 1] (u1 = u_c + h_u δu,
# v1 = v_c + h_v δv) and |e| <= r, as 4-tuples (c, a, b, r).  Products keep the linear parts
# exact and put only second-order terms into r, so correlated quantities (x1 and d̃1, q and its
# numerator, the two products of a determinant) do not lose their correlation as in plain
# interval arithmetic.  ROUND widens r by a relative amount per operation for rounding.

ROUND = 4e-16


@kernel
def abs_range(lo, hi):
    """(min |x|, max |x|) over [lo, hi]."""
    if lo >= 0.0:
        return lo, hi
    if hi <= 0.0:
        return -hi, -lo
    return 0.0, max(-lo, hi)


@kernel
def aff_range(p):
    rad = abs(p[1]) + abs(p[2]) + p[3]
    return p[0] - rad, p[0] + rad


@kernel
def aff_add(p, q):
    c = p[0] + q[0]
    a = p[1] + q[1]
    b = p[2] + q[2]
    return (c, a, b, p[3] + q[3] + ROUND * (abs(c) + abs(a) + abs(b)))


@kernel
def aff_sub(p, q):
    c = p[0] - q[0]
    a = p[1] - q[1]
    b = p[2] - q[2]
    return (c, a, b, p[3] + q[3] + ROUND * (abs(c) + abs(a) + abs(b)))


@kernel
def aff_scale(p, k):
    return (p[0] * k, p[1] * k, p[2] * k, p[3] * abs(k) + ROUND * abs(k) * (abs(p[0]) + abs(p[1]) + abs(p[2])))


@kernel
def aff_mul(p, q):
    """Product; (a1 δu + b1 δv)(a2 δu + b2 δv) contributes its mean (a1a2 + b1b2)/2 to c and
    its half-range to r (δu², δv² in [0, 1], δu δv in [-1, 1])."""
    c1, a1, b1, r1 = p
    c2, a2, b2, r2 = q
    uu = a1 * a2
    vv = b1 * b2
    uv = a1 * b2 + a2 * b1
    c = c1 * c2 + 0.5 * (uu + vv)
    a = c1 * a2 + c2 * a1
    b = c1 * b2 + c2 * b1
    r = 0.5 * (abs(uu) + abs(vv)) + abs(uv) + abs(c1) * r2 + abs(c2) * r1 \
        + (abs(a1) + abs(b1)) * r2 + (abs(a2) + abs(b2)) * r1 + r1 * r2
    return (c, a, b, r + ROUND * (abs(c) + abs(a) + abs(b) + r + abs(c1 * c2)))


@kernel
def aff_recip(p):
    """1/x about c (|x| >= m > 0 on the box): 1/c - (x - c)/c² with the Taylor remainder
    <= rad²/m³."""
    c, a, b, r = p
    rad = abs(a) + abs(b) + r
    m = abs(c) - rad
    ic = 1.0 / c
    ic2 = ic * ic
    rem = r * ic2 + rad * rad / (m * m * m)
    return (ic, -a * ic2, -b * ic2, rem + ROUND * 4.0 * (abs(ic) + rad * ic2))


@kernel
def aff_sqrt(p):
    """√x (x >= lo > 0 on the box) by its Chebyshev (min-range) affine approximation on
    [lo, hi] (Stolfi & de Figueiredo): the chord slope α = 1/(√lo + √hi); √ is concave, so
    √x - (√lo + α (x - lo)) lies in [0, δ], δ = (√hi - √lo)² / (4 (√lo + √hi)).  Unlike the
    Taylor form about the centre (remainder rad²/(8 lo^1.5)) the error stays below √hi/4 as lo
    approaches 0, near total internal reflection."""
    c, a, b, r = p
    rad = abs(a) + abs(b) + r
    lo = c - rad
    sl = math.sqrt(lo)
    sh = math.sqrt(c + rad)
    alpha = 1.0 / (sl + sh)
    delta = (sh - sl) * (sh - sl) * 0.25 * alpha
    c2 = sl + alpha * (c - lo) + 0.5 * delta  # the chord at x = c, lifted by half the gap
    return (c2, alpha * a, alpha * b, alpha * r + 0.5 * delta + ROUND * 8.0 * (sh + abs(c2)))


# --------------------------------------------------------------------------------------------
# First-order "dual" affine forms: (value, ∂/∂u1, ∂/∂v1), each an affine form over the box.
# The derivative forms keep their own linear variation over the box, so the Jacobian entries
# are enclosed to second order in the box size.

@kernel
def dual_affine(c0, gu, gv, box):
    """c0 + gu u1 + gv v1 on box = (u_lo, u_hi, v_lo, v_hi)."""
    hu = 0.5 * (box[1] - box[0])
    hv = 0.5 * (box[3] - box[2])
    c = c0 + gu * (box[0] + hu) + gv * (box[2] + hv)
    return ((c, gu * hu, gv * hv, ROUND * 4.0 * (abs(c) + abs(gu * hu) + abs(gv * hv))), (gu, 0.0, 0.0, 0.0), (gv, 0.0, 0.0, 0.0))


@kernel
def dual_add(x, y):
    return (aff_add(x[0], y[0]), aff_add(x[1], y[1]), aff_add(x[2], y[2]))


@kernel
def dual_sub(x, y):
    return (aff_sub(x[0], y[0]), aff_sub(x[1], y[1]), aff_sub(x[2], y[2]))


@kernel
def dual_scale(x, k):
    return (aff_scale(x[0], k), aff_scale(x[1], k), aff_scale(x[2], k))


@kernel
def dual_add_const(x, k):
    v = x[0]
    c = v[0] + k
    return ((c, v[1], v[2], v[3] + ROUND * abs(c)), x[1], x[2])


@kernel
def dual_mul(x, y):
    return (aff_mul(x[0], y[0]), aff_add(aff_mul(x[1], y[0]), aff_mul(x[0], y[1])), aff_add(aff_mul(x[2], y[0]), aff_mul(x[0], y[2])))


@kernel
def dual_range(x):
    return aff_range(x[0])


@kernel
def dual_div(x, y):
    """x / y; ok = False when y's range contains 0.  ∂(x/y) = (∂x - (x/y) ∂y) / y."""
    lo, hi = aff_range(y[0])
    if not (lo > 0.0 or hi < 0.0):
        return False, x
    r = aff_recip(y[0])
    q = aff_mul(x[0], r)
    return True, (q, aff_mul(aff_sub(x[1], aff_mul(q, y[1])), r), aff_mul(aff_sub(x[2], aff_mul(q, y[2])), r))


@kernel
def dual_sqrt(x):
    """√x for x > 0 on the whole box; ∂√x = ∂x / (2√x)."""
    s = aff_sqrt(x[0])
    r = aff_scale(aff_recip(s), 0.5)
    return (s, aff_mul(x[1], r), aff_mul(x[2], r))


# 3-vectors of duals -----------------------------------------------------------------------

@kernel
def vec_dot(a, b):
    return dual_add(dual_add(dual_mul(a[0], b[0]), dual_mul(a[1], b[1])), dual_mul(a[2], b[2]))


@kernel
def vec_dot_const(a, k):
    return dual_add(dual_add(dual_scale(a[0], k[0]), dual_scale(a[1], k[1])), dual_scale(a[2], k[2]))


@kernel
def vec_cross_const(a, k):
    """a × k for a constant vector k."""
    return (dual_sub(dual_scale(a[1], k[2]), dual_scale(a[2], k[1])),
            dual_sub(dual_scale(a[2], k[0]), dual_scale(a[0], k[2])),
            dual_sub(dual_scale(a[0], k[1]), dual_scale(a[1], k[0])))


@kernel
def vec_cross(a, b):
    return (dual_sub(dual_mul(a[1], b[2]), dual_mul(a[2], b[1])), dual_sub(dual_mul(a[2], b[0]), dual_mul(a[0], b[2])),
            dual_sub(dual_mul(a[0], b[1]), dual_mul(a[1], b[0])))


@kernel
def cross3(a, b):
    """a × b of two float 3-vectors as a new array."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
