"""Irradiance bounds of two-bounce chains (RR, RT, TR, TT) from a point light (Fan et al. 2025 §4.4).

For a piece — a box U1 of triangle 1's barycentrics (u1, v1) of a tuple (light x0, caster
triangle 1, caster triangle 2, receiver triangle k) — this module bounds the irradiance
dΩ0/dA_k (eq 14–15 with I0 = 1, F, V <= 1 left out as in the paper) of every admissible path
x0 -> x1 -> x2 -> xk with x1 in U1:

    dΩ0/dA_k = |d0·(e1×e2)| / |d0|³ · |det ∂(u1,v1)/∂(uk,vk)| / |e_k1 × e_k2|          (eq 15)

with the Jacobian taken explicitly, as the reciprocal of det ∂(uk,vk)/∂(u1,v1) (eq 16).

Why not the Bernstein form of eq 16 as in ``chain1``: through two vertices uk is rational in
(u1, v1) only after both square roots of the refractions are approximated; the remainder
variables that keep the *position* bound conservative (eq 12–13 and the degree reduction of
§6.1) say nothing about derivatives, and the paper's implicit form (eq 17–19) for the last
vertex needs x2 as independent variables too — a 6-variable determinant of degree ~20 per
variable, millions of Bernstein coefficients per piece.  Instead the exact forward map
u1 -> x1 -> d̃1 (eq 10, exact √β1) -> u2 (eq 9 on triangle 2) -> x2, n2 -> d̃2 (exact √β2) -> uk
(eq 9 on the receiver) is evaluated in *affine arithmetic* with forward differentiation: every
quantity carries its value and its two partial derivatives ∂/∂u1, ∂/∂v1, each as an affine form
c + a δu + b δv + [-r, r] over the box (δu, δv in [-1, 1]; Stolfi & de Figueiredo's affine
arithmetic, one shared pair of noise symbols).  Products keep the linear parts exactly and move
only second-order terms into r, so the derivatives — and eq 16's determinant built from them —
are enclosed up to O(box²): unlike plain interval arithmetic, the correlated terms of eq 9's
numerators and of the determinant's two products cancel as they do in the exact function.  No
approximation of √β is left unbounded (``_asqrt``: its Chebyshev affine form carries the error
in its remainder), so the bound is conservative:

* Ē = max |d0·(e1×e2)| / min |d0|³ / (min |det| · |e_k1 × e_k2|), E̲ with min/max swapped;
* Ē = inf (status UNBOUNDED_*, counted per reason) where the determinant's enclosure contains
  0 (focal points, caustic curves), where β of a refraction reaches 0 inside the box (grazing
  refraction or the onset of total internal reflection: √β has an unbounded derivative there)
  or where a ray can be parallel to the next plane.  At the last vertex such boxes get a second
  try with the paper's implicit form (eq 17–19, ``_implicit_last_vertex``: u1 and uk independent
  over the box × the piece's receiver bound, no √); it is valid but rarely finite there, because
  near grazing exit the receiver bound is wide (measured on the benchmark scenes: ball1280 TT
  unbounded pieces 253 -> 251, slab10k TT unchanged).  Most grazing boxes of the benchmarks are
  at vertex 1 with the light reaching the caster from inside the medium (a back face: V is
  ignored by the bounds, as in the paper);
* sub-boxes whose x1 lies outside triangle 1, whose ray meets a plane only backwards, whose u2
  enclosure misses triangle 2, whose uk enclosure misses the receiver triangle, or whose β < 0
  everywhere (total internal reflection) hold no admissible path and are skipped (a piece with
  none gets Ē = E̲ = 0).

At vertex 2 the incoming direction is d̃1 itself rather than x2 - x1 (the same direction for
every path, t > 0): for triangle 2 adjacent to triangle 1 on one surface, x2 - x1 can vanish
and would take β2 to 0 with it.  The enclosures shrink with the box, so the piece is split
(quadtree of at most ``irr_depth`` levels, inside the piece only) while the bound is unbounded
or Ē/E̲ > ``irr_ratio``.  Orientation at each vertex follows CONTRACT.md as in ``chain2``
(o = sign((source - x)·ng) · sign(ng·n), η' = 1/η for o > 0, η otherwise); where the sign is
not fixed over a box both orientations are bounded and the larger Ē kept.  Floating-point
rounding: every affine operation widens r by a relative ROUND, and the final bound is padded by
IRR_PAD.
"""

import math
import time

import numpy as np

from ..runtime.jit import kernel
from .chain1 import IRR_PAD, P_BU0, P_ELO, P_EHI, P_U0, P_U1, P_V0, P_V1, _eta_ratio, orientation_mask, push_children

NO_PATH = 0
BOUNDED = 1
UNBOUNDED = 2           # statuses >= UNBOUNDED: Ē = inf, for the reason they name
UNBOUNDED_GRAZING = 3   # β of a refraction reaches 0 in the box (√β has an unbounded derivative)
UNBOUNDED_PARALLEL = 4  # a ray can be parallel to the next triangle's plane
UNBOUNDED_FOCAL = 5     # det ∂(uk,vk)/∂(u1,v1) can vanish (a focal point or caustic curve)

EDGE_TOL = 1e-9      # barycentric slack before a sub-box is declared to miss a triangle
BETA_MIN = 1e-300    # β enclosure below this counts as reaching 0 (unbounded √ derivative)
N_IRR_STATS = 6      # sub-box evaluations, no-path leaves, then unbounded leaves by status 2..5 (index = status)


# --------------------------------------------------------------------------------------------
# Affine forms over the box: x = c + a δu + b δv + e with δu, δv in [-1, 1] (u1 = u_c + h_u δu,
# v1 = v_c + h_v δv) and |e| <= r, as 4-tuples (c, a, b, r).  Products keep the linear parts
# exact and put only second-order terms into r, so correlated quantities (x1 and d̃1, q and its
# numerator, the two products of a determinant) do not lose their correlation as in plain
# interval arithmetic.  ROUND widens r by a relative amount per operation for rounding.

ROUND = 4e-16


@kernel
def _iabs_range(lo, hi):
    """(min |x|, max |x|) over [lo, hi]."""
    if lo >= 0.0:
        return lo, hi
    if hi <= 0.0:
        return -hi, -lo
    return 0.0, max(-lo, hi)


@kernel
def _arange(p):
    rad = abs(p[1]) + abs(p[2]) + p[3]
    return p[0] - rad, p[0] + rad


@kernel
def _aadd(p, q):
    c = p[0] + q[0]
    a = p[1] + q[1]
    b = p[2] + q[2]
    return (c, a, b, p[3] + q[3] + ROUND * (abs(c) + abs(a) + abs(b)))


@kernel
def _asub(p, q):
    c = p[0] - q[0]
    a = p[1] - q[1]
    b = p[2] - q[2]
    return (c, a, b, p[3] + q[3] + ROUND * (abs(c) + abs(a) + abs(b)))


@kernel
def _ascale(p, k):
    return (p[0] * k, p[1] * k, p[2] * k, p[3] * abs(k) + ROUND * abs(k) * (abs(p[0]) + abs(p[1]) + abs(p[2])))


@kernel
def _amul(p, q):
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
def _arecip(p):
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
def _asqrt(p):
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
def _daffine(c0, gu, gv, box):
    """c0 + gu u1 + gv v1 on box = (u_lo, u_hi, v_lo, v_hi)."""
    hu = 0.5 * (box[1] - box[0])
    hv = 0.5 * (box[3] - box[2])
    c = c0 + gu * (box[0] + hu) + gv * (box[2] + hv)
    return ((c, gu * hu, gv * hv, ROUND * 4.0 * (abs(c) + abs(gu * hu) + abs(gv * hv))), (gu, 0.0, 0.0, 0.0), (gv, 0.0, 0.0, 0.0))


@kernel
def _dadd(x, y):
    return (_aadd(x[0], y[0]), _aadd(x[1], y[1]), _aadd(x[2], y[2]))


@kernel
def _dsub(x, y):
    return (_asub(x[0], y[0]), _asub(x[1], y[1]), _asub(x[2], y[2]))


@kernel
def _dscale(x, k):
    return (_ascale(x[0], k), _ascale(x[1], k), _ascale(x[2], k))


@kernel
def _daddc(x, k):
    v = x[0]
    c = v[0] + k
    return ((c, v[1], v[2], v[3] + ROUND * abs(c)), x[1], x[2])


@kernel
def _dmul(x, y):
    return (_amul(x[0], y[0]), _aadd(_amul(x[1], y[0]), _amul(x[0], y[1])), _aadd(_amul(x[2], y[0]), _amul(x[0], y[2])))


@kernel
def _drange(x):
    return _arange(x[0])


@kernel
def _ddiv(x, y):
    """x / y; ok = False when y's range contains 0.  ∂(x/y) = (∂x - (x/y) ∂y) / y."""
    lo, hi = _arange(y[0])
    if not (lo > 0.0 or hi < 0.0):
        return False, x
    r = _arecip(y[0])
    q = _amul(x[0], r)
    return True, (q, _amul(_asub(x[1], _amul(q, y[1])), r), _amul(_asub(x[2], _amul(q, y[2])), r))


@kernel
def _dsqrt(x):
    """√x for x > 0 on the whole box; ∂√x = ∂x / (2√x)."""
    s = _asqrt(x[0])
    r = _ascale(_arecip(s), 0.5)
    return (s, _amul(x[1], r), _amul(x[2], r))


# 3-vectors of duals -----------------------------------------------------------------------

@kernel
def _vdot(a, b):
    return _dadd(_dadd(_dmul(a[0], b[0]), _dmul(a[1], b[1])), _dmul(a[2], b[2]))


@kernel
def _vdotc(a, k):
    return _dadd(_dadd(_dscale(a[0], k[0]), _dscale(a[1], k[1])), _dscale(a[2], k[2]))


@kernel
def _vcrossc(a, k):
    """a × k for a constant vector k."""
    return (_dsub(_dscale(a[1], k[2]), _dscale(a[2], k[1])),
            _dsub(_dscale(a[2], k[0]), _dscale(a[0], k[2])),
            _dsub(_dscale(a[0], k[1]), _dscale(a[1], k[0])))


@kernel
def _vcross(a, b):
    return (_dsub(_dmul(a[1], b[2]), _dmul(a[2], b[1])), _dsub(_dmul(a[2], b[0]), _dmul(a[0], b[2])),
            _dsub(_dmul(a[0], b[1]), _dmul(a[1], b[0])))


@kernel
def _c3(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


# --------------------------------------------------------------------------------------------
# The exact forward map in dual intervals.

@kernel
def _scatter(refract, o, eta_ratio, n, d):
    """Outgoing direction d̃ (eq 10) of incoming d at unnormalised normal n (orientation o),
    with the exact √β (eq 11).  Returns (status, d̃): NO_PATH (total internal reflection on
    the whole box), BOUNDED, or UNBOUNDED_GRAZING (β reaches 0: d̃'s values are enclosed, its
    derivatives are not)."""
    nn = _vdot(n, n)
    dn = _vdot(d, n)
    if not refract:
        two_dn = _dscale(dn, 2.0)
        return BOUNDED, (_dsub(_dmul(nn, d[0]), _dmul(two_dn, n[0])), _dsub(_dmul(nn, d[1]), _dmul(two_dn, n[1])),
                         _dsub(_dmul(nn, d[2]), _dmul(two_dn, n[2])))
    e2 = eta_ratio * eta_ratio
    dd = _vdot(d, d)
    beta = _dadd(_dscale(_dmul(nn, dd), 1.0 - e2), _dscale(_dmul(dn, dn), e2))
    blo, bhi = _drange(beta)
    if bhi <= 0.0:
        return NO_PATH, d  # total internal reflection on the whole box
    if blo <= BETA_MIN:
        # √β's derivative is unbounded; its value is not: [√max(blo, 0), √bhi].  d̃'s values stay
        # enclosed (the pair search needs them), its derivative forms are not (infinite radius)
        slo = math.sqrt(max(blo, 0.0))
        shi = math.sqrt(bhi)
        unknown = (0.0, 0.0, 0.0, np.inf)
        root = ((-o * 0.5 * (slo + shi), 0.0, 0.0, 0.5 * (shi - slo) * (1.0 + 4.0 * ROUND) + ROUND * shi), unknown, unknown)
        status = UNBOUNDED_GRAZING
    else:
        root = _dscale(_dsqrt(beta), -o)
        status = BOUNDED
    out0 = _dadd(_dscale(_dsub(_dmul(nn, d[0]), _dmul(dn, n[0])), eta_ratio), _dmul(root, n[0]))
    out1 = _dadd(_dscale(_dsub(_dmul(nn, d[1]), _dmul(dn, n[1])), eta_ratio), _dmul(root, n[1]))
    out2 = _dadd(_dscale(_dsub(_dmul(nn, d[2]), _dmul(dn, n[2])), eta_ratio), _dmul(root, n[2]))
    return status, (out0, out1, out2)


@kernel
def _hit(x, dt, Q):
    """Barycentrics (u, v) on triangle Q of the line x + t d̃ (eq 9).  Returns (status, u, v);
    NO_PATH when the enclosures miss the triangle, UNBOUNDED when the line can be parallel to
    the plane.

    Eq 9 (u = ((d̃×e2)·r)/q, v = ((r×e1)·d̃)/q, q = (d̃×e2)·e1, r = x - Q0) is rewritten about
    the centre ray's hit point X_c = Q0 + u_c e1 + v_c e2 (any point of a line gives the same
    u, v): u = u_c + ((d̃×e2)·Y)/q, v = v_c + ((Y×e1)·d̃)/q with Y = x - X_c.  Same function;
    but the numerators are small near the centre, so their derivative enclosures do not carry
    the large u_c ∂q terms that cancel in the original form (interval dependency)."""
    e1 = Q[1] - Q[0]
    e2 = Q[2] - Q[0]
    ng = _c3(e1, e2)
    # forward only: t = ((Q0 - x)·ng) / (d̃·ng) must be positive somewhere on the box
    hlo, hhi = _drange(_vdotc((_daddc(x[0], -Q[0, 0]), _daddc(x[1], -Q[0, 1]), _daddc(x[2], -Q[0, 2])), ng))  # -(numerator)
    glo, ghi = _drange(_vdotc(dt, ng))
    if (hlo >= 0.0 and glo > 0.0) or (hhi <= 0.0 and ghi < 0.0):
        return NO_PATH, x[0], x[1]
    xc0, xc1, xc2 = x[0][0][0], x[1][0][0], x[2][0][0]
    dc0, dc1, dc2 = dt[0][0][0], dt[1][0][0], dt[2][0][0]
    den = dc0 * ng[0] + dc1 * ng[1] + dc2 * ng[2]
    if den == 0.0 or not math.isfinite(den):
        return UNBOUNDED_PARALLEL, x[0], x[1]
    tc = ((Q[0, 0] - xc0) * ng[0] + (Q[0, 1] - xc1) * ng[1] + (Q[0, 2] - xc2) * ng[2]) / den
    Xc = np.array([xc0 + tc * dc0, xc1 + tc * dc1, xc2 + tc * dc2])
    # barycentrics of X_c (exact up to rounding: the same (u, v) rules as below)
    w = Xc - Q[0]
    g11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]
    g12 = e1[0] * e2[0] + e1[1] * e2[1] + e1[2] * e2[2]
    g22 = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2]
    b1 = w[0] * e1[0] + w[1] * e1[1] + w[2] * e1[2]
    b2 = w[0] * e2[0] + w[1] * e2[1] + w[2] * e2[2]
    gd = g11 * g22 - g12 * g12
    if gd <= 0.0:
        return UNBOUNDED_PARALLEL, x[0], x[1]
    uc = (g22 * b1 - g12 * b2) / gd
    vc = (g11 * b2 - g12 * b1) / gd
    Xc = Q[0] + uc * e1 + vc * e2  # on the plane exactly as far as rounding allows
    Y = (_daddc(x[0], -Xc[0]), _daddc(x[1], -Xc[1]), _daddc(x[2], -Xc[2]))
    c = _vcrossc(dt, e2)
    pu = _vdot(c, Y)
    q = _vdotc(c, e1)
    rk = _vcrossc(Y, e1)
    pv = _vdot(rk, dt)
    ok, u = _ddiv(pu, q)
    if not ok:
        return UNBOUNDED_PARALLEL, pu, pv
    ok, v = _ddiv(pv, q)
    if not ok:
        return UNBOUNDED_PARALLEL, pu, pv
    u = _daddc(u, uc)
    v = _daddc(v, vc)
    ulo, uhi = _drange(u)
    vlo, vhi = _drange(v)
    if ulo > 1.0 + EDGE_TOL or uhi < -EDGE_TOL or vlo > 1.0 + EDGE_TOL or vhi < -EDGE_TOL or ulo + vlo > 1.0 + EDGE_TOL:
        return NO_PATH, u, v
    return BOUNDED, u, v


@kernel
def _jacobian_abs_det(uk, vk):
    """Enclosure (min, max) of |det ∂(uk,vk)/∂(u1,v1)| (eq 16) over the box: the determinant
    of the derivative forms in affine arithmetic.  (0, inf) when it may vanish."""
    det = _asub(_amul(uk[1], vk[2]), _amul(uk[2], vk[1]))
    lo, hi = _arange(det)
    if lo > 0.0:
        return lo, hi
    if hi < 0.0:
        return -hi, -lo
    return 0.0, np.inf


@kernel
def _implicit_last_vertex(d1, n2, x2, Q, rbox, eta_f, b):
    """|det ∂(u1,v1)/∂(uk,vk)| enclosure (lo, hi) by implicit differentiation of the specular
    constraint at the last vertex x2 (eq 17–19), over the box of (u1, v1) times the receiver
    box rbox = (uk_lo, uk_hi, vk_lo, vk_hi):

        F = |d2|² ((d1×n)·b)² - η² |d1|² ((d2×n)·b)²,   G = (d1×n)·d2,   d2 = xk - x2,

    with d1 the incoming direction (d̃1), n = n2, η = η_t/η_i (1 for a reflection, which
    satisfies F = G = 0 too).  On the path family F = G = 0, so |∂u1/∂uk| = |det ∂(F,G)/∂(uk,vk)|
    / |det ∂(F,G)/∂(u1,v1)| (eq 19); u1 and uk are independent variables of the 4-D box (the
    paper's superset).  No square root enters, so grazing refraction is bounded.  ∂/∂(u1,v1)
    are the dual parts; (uk, vk) enter xk as an interval (affine remainder), and
    ∂F/∂uk = ∇_d2 F · e_k1 with ∇_d2 F = 2 A² d2 - 2 η² |d1|² B (n × b), ∂G/∂uk = (d1×n)·e_k1.
    Returns (0, inf) when det ∂(F,G)/∂(u1,v1) may vanish."""
    ek1 = Q[1] - Q[0]
    ek2 = Q[2] - Q[0]
    hu = 0.5 * (rbox[1] - rbox[0])
    hv = 0.5 * (rbox[3] - rbox[2])
    uc = rbox[0] + hu
    vc = rbox[2] + hv
    zero = (0.0, 0.0, 0.0, 0.0)
    xk0 = ((Q[0, 0] + uc * ek1[0] + vc * ek2[0], 0.0, 0.0, abs(ek1[0]) * hu + abs(ek2[0]) * hv), zero, zero)
    xk1 = ((Q[0, 1] + uc * ek1[1] + vc * ek2[1], 0.0, 0.0, abs(ek1[1]) * hu + abs(ek2[1]) * hv), zero, zero)
    xk2 = ((Q[0, 2] + uc * ek1[2] + vc * ek2[2], 0.0, 0.0, abs(ek1[2]) * hu + abs(ek2[2]) * hv), zero, zero)
    d2 = (_dsub(xk0, x2[0]), _dsub(xk1, x2[1]), _dsub(xk2, x2[2]))
    p = _vcross(d1, n2)
    A = _vdotc(p, b)
    B = _vdotc(_vcross(d2, n2), b)
    l1 = _vdot(d1, d1)
    l2 = _vdot(d2, d2)
    e2 = eta_f * eta_f
    F = _dsub(_dmul(l2, _dmul(A, A)), _dscale(_dmul(l1, _dmul(B, B)), e2))
    G = _vdot(p, d2)
    det_u1 = _asub(_amul(F[1], G[2]), _amul(F[2], G[1]))
    lo1, hi1 = _arange(det_u1)
    lo1, hi1 = _iabs_range(lo1, hi1)
    if not (lo1 > 0.0):
        return 0.0, np.inf
    # ∇_d2 F (value forms only)
    nb = _vcrossc(n2, b)
    two_a2 = _dscale(_dmul(A, A), 2.0)
    k = _dscale(_dmul(l1, B), 2.0 * e2)
    g0 = _dsub(_dmul(two_a2, d2[0]), _dmul(k, nb[0]))
    g1 = _dsub(_dmul(two_a2, d2[1]), _dmul(k, nb[1]))
    g2 = _dsub(_dmul(two_a2, d2[2]), _dmul(k, nb[2]))
    grad = (g0, g1, g2)
    f_uk = _vdotc(grad, ek1)[0]
    f_vk = _vdotc(grad, ek2)[0]
    g_uk = _vdotc(p, ek1)[0]
    g_vk = _vdotc(p, ek2)[0]
    lok, hik = _arange(_asub(_amul(f_uk, g_vk), _amul(f_vk, g_uk)))
    lok, hik = _iabs_range(lok, hik)
    if not math.isfinite(hik):
        return 0.0, np.inf
    return lok / hi1, hik / lo1


@kernel
def _vertex_one(x0, P1, N1, box):
    """x1 and n1 on triangle 1 over the box of (u1, v1), d0 = x1 - x0 (dual forms), triangle
    1's geometric normal and its orientation mask (``chain1.orientation_mask``)."""
    e1 = P1[1] - P1[0]
    e2 = P1[2] - P1[0]
    ng1 = _c3(e1, e2)
    m1 = N1[1] - N1[0]
    m2 = N1[2] - N1[0]
    x1 = (_daffine(P1[0, 0], e1[0], e2[0], box), _daffine(P1[0, 1], e1[1], e2[1], box), _daffine(P1[0, 2], e1[2], e2[2], box))
    n1 = (_daffine(N1[0, 0], m1[0], m2[0], box), _daffine(N1[0, 1], m1[1], m2[1], box), _daffine(N1[0, 2], m1[2], m2[2], box))
    d0 = (_daddc(x1[0], -x0[0]), _daddc(x1[1], -x0[1]), _daddc(x1[2], -x0[2]))
    side1 = (x0[0] - P1[0, 0]) * ng1[0] + (x0[1] - P1[0, 1]) * ng1[1] + (x0[2] - P1[0, 2]) * ng1[2]
    nlo, nhi = _drange(_vdotc(n1, ng1))
    return x1, n1, d0, ng1, orientation_mask(side1, side1, nlo, nhi)


@kernel
def first_bounce_rays(refract1, x0, P1, N1, eta, box, xlo, xhi, dlo, dhi):
    """Value enclosures of x1 (xlo, xhi) and of the outgoing direction d̃1 (dlo, dhi; union
    over the orientations present, unnormalised) over the box of triangle 1's (u1, v1), for
    the pair search (``tuples``, §6.1).  Returns the bit mask of the orientations that send
    light out (0: none — x0 in the plane, or total internal reflection on the whole box)."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return 0
    x1, n1, d0, ng1, mask1 = _vertex_one(x0, P1, N1, box)
    for i in range(3):
        xlo[i], xhi[i] = _drange(x1[i])
        dlo[i] = np.inf
        dhi[i] = -np.inf
    bits = 0
    for k1 in range(2):
        if not (mask1 >> k1) & 1:
            continue
        if not refract1 and k1 == 1 and (mask1 & 1):
            continue
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = _scatter(refract1, o1, _eta_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        bits |= 1 << k1
        for i in range(3):
            a, b = _drange(dt1[i])
            dlo[i] = min(dlo[i], a)
            dhi[i] = max(dhi[i], b)
    return bits


@kernel
def _first_hit_status(refract1, x0, P1, N1, P2, eta, box, bits):
    """NO_PATH when no light leaving the box of triangle 1 (orientations ``bits``) meets
    triangle 2 forwards, else the status of the first orientation that may (eq 9)."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return NO_PATH
    x1, n1, d0, ng1, mask1 = _vertex_one(x0, P1, N1, box)
    for k1 in range(2):
        if not (bits >> k1) & 1 or not (mask1 >> k1) & 1:
            continue
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = _scatter(refract1, o1, _eta_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        st, u2, v2 = _hit(x1, dt1, P2)
        if st != NO_PATH:
            return st
    return NO_PATH


@kernel
def first_bounce_reaches(refract1, x0, P1, N1, P2, eta, box, bits, depth):
    """Whether light leaving the box of triangle 1 (orientations ``bits`` of
    ``first_bounce_rays``) can reach triangle 2: False only where every outgoing ray meets
    triangle 2's plane backwards or outside the triangle (eq 9 in affine arithmetic), on the
    box or, where that does not decide, on the sub-boxes of a quadtree at most ``depth`` levels
    deeper (affine enclosures tighten quadratically as boxes shrink)."""
    stack = np.empty((3 * depth + 4, 5))
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = box[0], box[1], box[2], box[3], 0.0
    top = 1
    sub = np.empty(4)
    lo = np.empty(2)
    hi = np.empty(2)
    while top > 0:
        top -= 1
        for k in range(4):
            sub[k] = stack[top, k]
        level = int(stack[top, 4])
        if _first_hit_status(refract1, x0, P1, N1, P2, eta, sub, bits) == NO_PATH:
            continue
        if level >= depth:
            return True
        lo[0], hi[0], lo[1], hi[1] = sub[0], sub[1], sub[2], sub[3]
        top = push_children(stack, top, lo, hi, level)
    return False


@kernel
def _linear_form(val, box, form):
    """The affine value form val = (c, a, b, r) over the box (u1 = u_c + h_u δu, ...) as
    form[0:4] = (c0, g_u, g_v, g_xi) in global (u1, v1) and a remainder ξ in [0, 1], clipped to
    the triangle's [0, 1]: the constant form [lo, hi] ∩ [0, 1] when the remainder is wider than
    that.  Returns False for the constant form."""
    hu = 0.5 * (box[1] - box[0])
    hv = 0.5 * (box[3] - box[2])
    c, a, b, r = val
    lo = max(c - abs(a) - abs(b) - r, 0.0)
    hi = min(c + abs(a) + abs(b) + r, 1.0)
    if hu > 0.0 and hv > 0.0 and 2.0 * r < hi - lo:
        gu = a / hu
        gv = b / hv
        form[0] = c - gu * (box[0] + hu) - gv * (box[2] + hv) - r
        form[1] = gu
        form[2] = gv
        # rounding of the change of variables: the form is evaluated in global coordinates
        form[3] = 2.0 * r + 8.0 * ROUND * (abs(c) + abs(a) + abs(b) + abs(form[0]))
        form[0] -= 4.0 * ROUND * (abs(c) + abs(a) + abs(b) + abs(form[0]))
        return True
    form[0] = lo
    form[1] = 0.0
    form[2] = 0.0
    form[3] = max(hi - lo, 0.0)
    return False


@kernel
def first_bounce_forms(refract1, o1, x0, P1, N1, P2, eta, box, fu, fv, stats):
    """Step 1–2 of ``chain2`` (vertex 1 -> 2) for orientation o1 at vertex 1: u2 and v2 on
    triangle 2 over the box of (u1, v1) as forms c + g_u u1 + g_v v1 + g_xi ξ (ξ in [0, 1], one
    remainder variable each; ``_linear_form``), from the exact map x1 -> d̃1 (eq 10, exact √β)
    -> (u2, v2) (eq 9) in affine arithmetic.  Returns False when no light of the box reaches
    triangle 2; stats[2] += 1 per constant form (the line can be parallel to triangle 2, or the
    remainder is wider than the triangle)."""
    x1, n1, d0, ng1, mask1 = _vertex_one(x0, P1, N1, box)
    st, dt1 = _scatter(refract1, o1, _eta_ratio(o1, eta), n1, d0)
    if st == NO_PATH:
        return False
    st, u2, v2 = _hit(x1, dt1, P2)
    if st == NO_PATH:
        return False
    if st != BOUNDED:  # the line can be parallel to triangle 2: all of it
        fu[0], fu[1], fu[2], fu[3] = 0.0, 0.0, 0.0, 1.0
        fv[0], fv[1], fv[2], fv[3] = 0.0, 0.0, 0.0, 1.0
        stats[2] += 2
        return True
    if not _linear_form(u2[0], box, fu):
        stats[2] += 1
    if not _linear_form(v2[0], box, fv):
        stats[2] += 1
    return True


@kernel
def sub_box_irradiance(refract1, refract2, x0, P1, N1, P2, N2, Q, eta, box, rbox):
    """Bound dΩ0/dA_k (eq 15–16) over the box (u_lo, u_hi, v_lo, v_hi) of triangle 1's
    barycentrics; rbox (uk_lo, uk_hi, vk_lo, vk_hi) encloses the receiver barycentrics of its
    paths (the piece's position bound).  Returns (status, Ē, E̲): NO_PATH (no admissible path
    in the box reaches the receiver triangle), BOUNDED, or a status >= UNBOUNDED (Ē = inf).

    The last vertex uses the explicit Jacobian (eq 16); where that cannot be bounded because
    β2 reaches 0 (grazing refraction) or the last ray can be parallel to the receiver, the
    implicit form (eq 17–19, ``_implicit_last_vertex``, two tangent vectors b, the smaller
    bound kept) is used instead."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return NO_PATH, 0.0, 0.0
    x1, n1, d0, ng1, mask1 = _vertex_one(x0, P1, N1, box)
    # light factor |d0·(e1×e2)| / |d0|³ (value enclosures only)
    clo, chi = _drange(_vdotc(d0, ng1))
    clo, chi = _iabs_range(clo, chi)
    dlo, dhi = _drange(_vdot(d0, d0))
    if dlo <= 0.0:
        return UNBOUNDED, np.inf, 0.0
    light_hi = chi / dlo ** 1.5
    light_lo = clo / dhi ** 1.5
    ak = math.sqrt(np.sum(_c3(Q[1] - Q[0], Q[2] - Q[0]) ** 2))
    ng2 = _c3(P2[1] - P2[0], P2[2] - P2[0])
    f1 = P2[1] - P2[0]
    f2 = P2[2] - P2[0]
    # two unit tangents of triangle 2 for the implicit bound's vectors b (eq 17)
    tb1 = f1 / math.sqrt(np.sum(f1 * f1))
    tb2 = _c3(ng2, tb1)
    tb2 = tb2 / math.sqrt(np.sum(tb2 * tb2))
    g1 = N2[1] - N2[0]
    g2 = N2[2] - N2[0]
    status = NO_PATH
    e_hi = 0.0
    e_lo = np.inf
    for k1 in range(2):
        if not (mask1 >> k1) & 1:
            continue
        if not refract1 and k1 == 1 and (mask1 & 1):
            continue  # reflection does not depend on the orientation
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = _scatter(refract1, o1, _eta_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        # grazing at vertex 1: Ē = inf if a path can get through, but d̃1's values are still
        # enclosed, so the rest of the path can still prove the box empty
        grazing1 = st == UNBOUNDED_GRAZING
        st, u2, v2 = _hit(x1, dt1, P2)
        if st >= UNBOUNDED:
            return st, np.inf, 0.0
        if st == NO_PATH:
            continue
        x2 = (_daddc(_dadd(_dscale(u2, f1[0]), _dscale(v2, f2[0])), P2[0, 0]),
              _daddc(_dadd(_dscale(u2, f1[1]), _dscale(v2, f2[1])), P2[0, 1]),
              _daddc(_dadd(_dscale(u2, f1[2]), _dscale(v2, f2[2])), P2[0, 2]))
        n2 = (_daddc(_dadd(_dscale(u2, g1[0]), _dscale(v2, g2[0])), N2[0, 0]),
              _daddc(_dadd(_dscale(u2, g1[1]), _dscale(v2, g2[1])), N2[0, 1]),
              _daddc(_dadd(_dscale(u2, g1[2]), _dscale(v2, g2[2])), N2[0, 2]))
        # The incoming direction at x2 is d̃1 itself (d1 = x2 - x1 = t d̃1, t > 0 for every
        # path; eq 10 is homogeneous in d, so the scale does not matter).  Using d̃1 instead
        # of x2 - x1 keeps the forms well conditioned when x2 comes close to x1 (adjacent
        # triangles of one surface), where |d1| -> 0 would make β2 vanish with it.
        d1 = dt1
        slo, shi = _drange(_vdotc(d1, ng2))  # side of x1: (x1 - x2)·ng2 = -t d̃1·ng2
        nlo2, nhi2 = _drange(_vdotc(n2, ng2))
        mask2 = orientation_mask(-shi, -slo, nlo2, nhi2)
        for k2 in range(2):
            if not (mask2 >> k2) & 1:
                continue
            if not refract2 and k2 == 1 and (mask2 & 1):
                continue
            o2 = 1.0 if k2 == 0 else -1.0
            st, dt2 = _scatter(refract2, o2, _eta_ratio(o2, eta), n2, d1)
            if st == NO_PATH:
                continue
            if st == BOUNDED:
                st, uk, vk = _hit(x2, dt2, Q)
                if st == NO_PATH:
                    continue
            elif _hit(x2, dt2, Q)[0] == NO_PATH:  # grazing: d̃2's values are enclosed all the same
                continue
            if grazing1:
                return UNBOUNDED_GRAZING, np.inf, 0.0
            if st == BOUNDED:
                # det ∂(uk, vk)/∂(u1, v1) (eq 16)
                jlo, jhi = _jacobian_abs_det(uk, vk)
                if not (jlo > 0.0):
                    return UNBOUNDED_FOCAL, np.inf, 0.0
                status = BOUNDED
                e_hi = max(e_hi, light_hi / (jlo * ak))
                e_lo = min(e_lo, light_lo / (jhi * ak))
                continue
            if st != UNBOUNDED_GRAZING and st != UNBOUNDED_PARALLEL:
                return st, np.inf, 0.0
            # implicit differentiation at the last vertex (eq 17–19)
            eta_f = 1.0 / _eta_ratio(o2, eta) if refract2 else 1.0
            rhi = np.inf
            rlo = 0.0
            for bi in range(2):
                b = tb1 if bi == 0 else tb2
                a_lo, a_hi = _implicit_last_vertex(d1, n2, x2, Q, rbox, eta_f, b)
                rhi = min(rhi, a_hi)
                rlo = max(rlo, a_lo)
            if not math.isfinite(rhi):
                return st, np.inf, 0.0
            status = BOUNDED
            e_hi = max(e_hi, light_hi * rhi / ak)
            e_lo = min(e_lo, light_lo * rlo / ak)
    if status == NO_PATH:
        return NO_PATH, 0.0, 0.0
    if not math.isfinite(e_hi):
        return UNBOUNDED, np.inf, 0.0
    return BOUNDED, e_hi, e_lo


@kernel
def piece_irradiance_two(chain_code, x0, P1, N1, P2, N2, Q, eta, lo, hi, rbox, irr_depth, irr_ratio, stats):
    """(Ē, E̲) of dΩ0/dA_k over the piece lo <= (u1, v1) <= hi of the tuple (triangle 1,
    triangle 2, receiver Q) (eq 15–16 in affine arithmetic, module doc); rbox = the piece's
    receiver barycentric bound (uk_lo, uk_hi, vk_lo, vk_hi), used by the implicit fallback.

    chain_code as ``chain2.CHAIN_CODES`` (bit 0: vertex 1 refracts, bit 1: vertex 2 refracts).
    The piece is split into a quadtree of at most irr_depth levels while a sub-box is
    unbounded or its Ē/E̲ > irr_ratio; Ē is the largest of the leaves', E̲ the smallest.
    stats[0] += sub-box evaluations, stats[1] += leaves without a path, stats[s] += 1 for the
    unbounded leaf's status s (2..5) when Ē = inf."""
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    size = 3 * irr_depth + 4
    stack = np.empty((size, 5))
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = lo[0], hi[0], lo[1], hi[1], 0.0
    top = 1
    box = np.empty(4)
    sub_lo = np.empty(2)
    sub_hi = np.empty(2)
    e_hi = 0.0
    e_lo = np.inf
    while top > 0:
        top -= 1
        for k in range(4):
            box[k] = stack[top, k]
        level = int(stack[top, 4])
        stats[0] += 1
        st, bh, bl = sub_box_irradiance(refract1, refract2, x0, P1, N1, P2, N2, Q, eta, box, rbox)
        if st == NO_PATH:
            stats[1] += 1
            continue
        if level < irr_depth and (st >= UNBOUNDED or bh > irr_ratio * bl):
            sub_lo[0], sub_hi[0], sub_lo[1], sub_hi[1] = box[0], box[1], box[2], box[3]
            top = push_children(stack, top, sub_lo, sub_hi, level)
            continue
        if st >= UNBOUNDED:
            stats[st] += 1
            return np.inf, 0.0
        e_hi = max(e_hi, bh)
        e_lo = min(e_lo, bl)
    if e_lo == np.inf:  # no admissible path anywhere in the piece
        return 0.0, 0.0
    return e_hi * (1.0 + IRR_PAD), e_lo * (1.0 - IRR_PAD)


@kernel
def _reach_chunk(chain_code, x0, P, N, Q, eta, pairs, reach, start, stop):
    """reach[t, r] for pairs start..stop-1 (``receivers_reached``)."""
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    box = np.empty(4)
    rbox = np.empty(4)
    rbox[0], rbox[1], rbox[2], rbox[3] = 0.0, 1.0, 0.0, 1.0
    cells = reach.shape[2]
    h = 1.0 / cells
    for t in range(start, stop):
        a = pairs[t, 0]
        b = pairs[t, 1]
        for r in range(Q.shape[0]):
            grid = reach[t, r]
            grid[:, :] = False
            box[0], box[1], box[2], box[3] = 0.0, 1.0, 0.0, 1.0
            st, bh, bl = sub_box_irradiance(refract1, refract2, x0, P[a], N[a], P[b], N[b], Q[r], eta, box, rbox)
            if st == NO_PATH:
                continue
            if cells == 1:
                grid[0, 0] = True
                continue
            for i in range(cells):
                for j in range(cells - i):  # the cells with u + v < 1 somewhere
                    box[0], box[1], box[2], box[3] = i * h, (i + 1) * h, j * h, (j + 1) * h
                    st, bh, bl = sub_box_irradiance(refract1, refract2, x0, P[a], N[a], P[b], N[b], Q[r], eta, box, rbox)
                    grid[i, j] = st != NO_PATH


@kernel
def box_reached(grid, lo, hi):
    """Whether any cell of a ``receivers_reached`` grid (cells x cells over [0, 1]²) that
    overlaps the box lo <= (u1, v1) <= hi was reached."""
    cells = grid.shape[0]
    i0 = min(cells - 1, int(math.floor(lo[0] * cells)))
    i1 = max(i0 + 1, int(math.ceil(hi[0] * cells)))
    j0 = min(cells - 1, int(math.floor(lo[1] * cells)))
    j1 = max(j0 + 1, int(math.ceil(hi[1] * cells)))
    for i in range(i0, min(i1, cells)):
        for j in range(j0, min(j1, cells)):
            if grid[i, j]:
                return True
    return False


def receivers_reached(chain, light, caster_P, caster_N, receiver_P, pairs, eta=1.5, depth=2):
    """(pairs, receivers, 2^depth, 2^depth) bool: cell [i, j] of triangle 1's barycentric grid
    (u1 in [i, i+1]/2^depth, v1 in [j, j+1]/2^depth) is False where ``sub_box_irradiance``
    proves that no admissible path x0 -> triangle 1 -> triangle 2 -> receiver starts in it
    (backward rays, u2 outside triangle 2, uk outside the receiver, total internal reflection);
    every cell is False when triangle 1 as a whole is proven empty.  Conservative: a cell
    holding a path is always True.

    ``chain2.bound_two_bounce`` starts and prunes its position quadtree with it (a box lives
    for a receiver while ``box_reached``): it removes the (pair, receiver) tuples whose
    position bound cannot see the emptiness — neighbouring triangles of one surface, whose
    x2 - x1 relaxation spans the whole receiver (slab10k TT: 55 % of the position tuples proven
    empty on the whole triangle, 63 % with depth 1).  depth 2 is ``bound_two_bounce``'s default
    (slab10k reach + bounds 13.7 s against 14.8 s at depth 1)."""
    from ..runtime.jit import run_chunks
    from .chain2 import CHAIN_CODES

    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    receiver_P = np.ascontiguousarray(receiver_P, dtype=np.float64)
    cells = 1 << int(depth)
    reach = np.zeros((pairs.shape[0], receiver_P.shape[0], cells, cells), dtype=np.bool_)
    if reach.size:
        run_chunks(_reach_chunk, (CHAIN_CODES[chain], np.ascontiguousarray(light, dtype=np.float64).reshape(3),
                                  np.ascontiguousarray(caster_P, dtype=np.float64),
                                  np.ascontiguousarray(caster_N, dtype=np.float64), receiver_P, float(eta), pairs,
                                  reach), pairs.shape[0])
    return reach


@kernel
def _irradiance_chunk(chain_code, x0, P, N, Q, eta, piece_pair, piece_receiver, pieces, irr_depth, irr_ratio, stats,
                      start, stop):
    """Ē, E̲ of pieces start..stop-1 (``bound_irradiance_two``; on ``jit.run_chunks`` threads,
    which compile in a fraction of a ``parallel=True`` loop's time)."""
    lo = np.empty(2)
    hi = np.empty(2)
    rbox = np.empty(4)
    for i in range(start, stop):
        a = piece_pair[i, 0]
        b = piece_pair[i, 1]
        lo[0], hi[0], lo[1], hi[1] = pieces[i, P_U0], pieces[i, P_U1], pieces[i, P_V0], pieces[i, P_V1]
        for k in range(4):
            rbox[k] = pieces[i, P_BU0 + k]
        eh, el = piece_irradiance_two(chain_code, x0, P[a], N[a], P[b], N[b], Q[piece_receiver[i]], eta, lo, hi, rbox,
                                      irr_depth, irr_ratio, stats[i])
        pieces[i, P_EHI] = eh
        pieces[i, P_ELO] = el


def bound_irradiance_two(bounds, light, caster_P, caster_N, receiver_P, eta=1.5, irr_depth=2, irr_ratio=2.0):
    """Fill Ē and E̲ (columns P_EHI, P_ELO) of every piece of a ``chain2.TwoBounceBounds`` in
    place (Fan et al. 2025 eq 14–16, module doc) and add the counts to its report.

    irr_depth: most quadtree levels inside a piece for the irradiance bound (0: the piece as
    it is); irr_ratio: split while Ē/E̲ exceeds it.  Returns ``bounds``."""
    from ..runtime.jit import run_chunks
    from .chain2 import CHAIN_CODES

    t0 = time.perf_counter()
    tuples = bounds.tuples
    pair = np.ascontiguousarray(tuples[bounds.piece_tuple, :2], dtype=np.int64)
    receiver = np.ascontiguousarray(tuples[bounds.piece_tuple, 2], dtype=np.int64)
    stats = np.zeros((bounds.pieces.shape[0], N_IRR_STATS), dtype=np.int64)
    if bounds.pieces.shape[0]:
        run_chunks(_irradiance_chunk, (CHAIN_CODES[bounds.chain], np.ascontiguousarray(light, dtype=np.float64).reshape(3),
                                       np.ascontiguousarray(caster_P, dtype=np.float64),
                                       np.ascontiguousarray(caster_N, dtype=np.float64),
                                       np.ascontiguousarray(receiver_P, dtype=np.float64), float(eta), pair, receiver,
                                       bounds.pieces, int(irr_depth), float(irr_ratio), stats), bounds.pieces.shape[0])
    total = stats.sum(axis=0)
    ehi = bounds.pieces[:, P_EHI]
    bounds.report.update({
        "irradiance_evaluations": int(total[0]), "unbounded_pieces": int((~np.isfinite(ehi)).sum()),
        "unbounded_by_reason": {"other": int(total[UNBOUNDED]), "grazing": int(total[UNBOUNDED_GRAZING]),
                                "parallel": int(total[UNBOUNDED_PARALLEL]), "focal": int(total[UNBOUNDED_FOCAL])},
        "no_path_pieces": int((ehi == 0.0).sum()), "irr_depth": int(irr_depth), "irr_ratio": float(irr_ratio),
    })
    bounds.report.setdefault("seconds", {})["irradiance"] = time.perf_counter() - t0
    return bounds
