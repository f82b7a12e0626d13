"""Reference engine of the one-bounce Bernstein bounds (Fan et al. 2025): readable, allocating.

The production engine is ``addon.solver.bounds.one_bounce`` (same maths, no allocation per
piece); the tests run both and compare (tests/solver/test_bounds_validity.py,
test_bounds_bernstein.py).  :func:`batch` has the production driver's signature, so
``bound_one_bounce(..., engine=batch)`` gives this engine's pieces.

For a tuple (light x0, caster triangle 1, receiver triangle k) and a box U1 of the caster's
barycentrics (u1, v1), a *piece* gets

* the position bound (eq 4–5): a box of receiver barycentrics (uk, vk) and of receiver UV
  texture coordinates that contains the hit point of every admissible path x0 -> x1 -> xk
  with x1 in U1 (∩ the triangle) and xk on the receiver triangle;
* the irradiance bound (eq 14–15, §4.4): Ē >= dΩ0/dA_k of every such path (F, V <= 1 and
  I0 = 1 are left out as in the paper), i.e. >= ``path_irradiance(...).irradiance`` with
  the receiver normal given.

Rational formulation (§4.3): x1, n1 (eq 6–7) are affine in (u1, v1), d0 = x1 - x0 (eq 8),
the outgoing direction d̃ (eq 10) is polynomial for reflection; for refraction √β (eq 11)
is replaced by the on-the-fly linear approximation aβ + b plus a remainder variable ξ in
[0, 1] spanning the approximation error (eq 12–13), so the bound stays conservative.  The
receiver coordinates follow eq 9 with one shared denominator q = (d̃ × e_k2)·e_k1; the UV
coordinates are the same rational function with numerator uv0 q + Δuv1 pu + Δuv2 pv.

Irradiance: reflection uses the explicit Jacobian (eq 15–16): with uk = pu/q, vk = pv/q,
det ∂(uk,vk)/∂(u1,v1) = det[[pu, pu_u, pu_v], [pv, pv_u, pv_v], [q, q_u, q_v]] / q³, so

    dΩ0/dA_k = |d0·(e1×e2)| / |d0|³ · |q|³ / |det[...]| / |e_k1 × e_k2|,

bounded with eq 3 on the rational part times (min |d0|²)^(-3/2).  Refraction uses implicit
differentiation (eq 17–19) of the specular constraints F (for two vectors b tangent to the
caster, the intersection of both bounds) and G over the 4-D box U1 × (position bound), so no
√β approximation enters: |∂u1/∂uk| = |det ∂(F,G)/∂(uk,vk)| / |det ∂(F,G)/∂(u1,v1)|.
m = 1 solution per tuple is assumed when the bound is used per tuple (eq 21); a caller that
wants m > 1 multiplies Ẽ by m.

Subdivision (§6.1): the u1 box is split at the midpoint into four while the position bound's
area (in receiver barycentrics) is >= σ, the ratio Ē/E̲ is >= α and the depth is below the
limit; pieces whose position bound misses the receiver triangle are dropped (this is also
the effective-domain initialisation).  Degrees stay at most 13 per variable here, far below
the ~40 where the paper reduces degree, so no degree reduction is needed for one bounce.
"""

import math

import numpy as np

from addon.solver.bounds.layout import (IRR_PAD, MIN_WIDTH, P_BU0, P_DEPTH, P_EHI, P_ELO, P_U0, P_U1, P_V0, P_V1, POS_PAD, ior_ratio,
                                        push_children)
from addon.solver.runtime.jit import kernel, parallel_range
from addon.solver.polynomials.bernstein import (bound_of_coefficients, abs_lower, abs_upper, affine, affine_map, clip_hull,
                                     coef_range, deriv, elevate, lincomb, mul, rational_bound, sqrt_linearisation, sub)

@kernel(inline="always")
def _d3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@kernel(inline="always")
def _c3(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@kernel(inline="always")
def _n3(a):
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])




@kernel
def _box4(lo, hi):
    """4-variable box (u1, v1) x [0, 1]² from the 2-variable piece box."""
    lo4 = np.zeros(4)
    hi4 = np.ones(4)
    lo4[0] = lo[0]
    lo4[1] = lo[1]
    hi4[0] = hi[0]
    hi4[1] = hi[1]
    return lo4, hi4


@kernel
def _vaffine(c, gu, gv, lo, hi):
    """3 Bernstein polynomials c + u gu + v gv (variables 0, 1) on the box."""
    g = np.zeros(4)
    g[0] = gu[0]
    g[1] = gv[0]
    a = affine(c[0], g, lo, hi)
    g[0] = gu[1]
    g[1] = gv[1]
    b = affine(c[1], g, lo, hi)
    g[0] = gu[2]
    g[1] = gv[2]
    d = affine(c[2], g, lo, hi)
    return a, b, d


@kernel
def _dot(a0, a1, a2, b0, b1, b2):
    return lincomb(lincomb(mul(a0, b0), 1.0, mul(a1, b1), 1.0), 1.0, mul(a2, b2), 1.0)


@kernel
def _dotc(a0, a1, a2, c):
    return lincomb(lincomb(a0, c[0], a1, c[1]), 1.0, a2, c[2])


@kernel
def _cross(a0, a1, a2, b0, b1, b2):
    return sub(mul(a1, b2), mul(a2, b1)), sub(mul(a2, b0), mul(a0, b2)), sub(mul(a0, b1), mul(a1, b0))


@kernel
def _crossc(a0, a1, a2, c):
    """a × c for a constant vector c."""
    return lincomb(a1, c[2], a2, -c[1]), lincomb(a2, c[0], a0, -c[2]), lincomb(a0, c[1], a1, -c[0])


@kernel
def _caster(x0, P, N, lo, hi):
    """x1, n1 (eq 6–7) and d0 = x1 - x0 (eq 8) as Bernstein polynomials on the box."""
    e1 = P[1] - P[0]
    e2 = P[2] - P[0]
    x = _vaffine(P[0], e1, e2, lo, hi)
    n = _vaffine(N[0], N[1] - N[0], N[2] - N[0], lo, hi)
    d = _vaffine(P[0] - x0, e1, e2, lo, hi)
    return x, n, d


@kernel
def _orientations(x0, P, N, lo, hi):
    """Which signs o of the shading normal turned to the incoming side (n_o = o n) occur on
    the box: bit 1 for +1, bit 2 for -1 (CONTRACT.md: s = sign((x0-x1)·ng), ng turned to n).
    Returns 0 when x0 lies in the caster's plane (no path)."""
    ng = _c3(P[1] - P[0], P[2] - P[0])
    side = _d3(x0 - P[0], ng)
    if side == 0.0:
        return 0
    n = _vaffine(N[0], N[1] - N[0], N[2] - N[0], lo, hi)
    lo_, hi_ = coef_range(_dotc(n[0], n[1], n[2], ng))
    mask = 0
    s = 1.0 if side > 0.0 else -1.0
    if hi_ > 0.0:
        mask |= 1 if s > 0.0 else 2
    if lo_ < 0.0:
        mask |= 2 if s > 0.0 else 1
    return mask


@kernel
def _direction(refract, o, eta_ratio, n, d, lo, hi):
    """Outgoing direction d̃ (eq 10).  Refraction: √β (eq 11) -> aβ + b + δ_lo + ξ (δ_hi - δ_lo)
    with ξ the variable 2 on [0, 1] (eq 12–13).  ok = False when β < 0 on the whole box (TIR)."""
    nn = _dot(n[0], n[1], n[2], n[0], n[1], n[2])
    dn = _dot(d[0], d[1], d[2], n[0], n[1], n[2])
    if not refract:
        return True, (lincomb(mul(nn, d[0]), 1.0, mul(dn, n[0]), -2.0), lincomb(mul(nn, d[1]), 1.0, mul(dn, n[1]), -2.0),
                      lincomb(mul(nn, d[2]), 1.0, mul(dn, n[2]), -2.0))
    e2 = eta_ratio * eta_ratio
    dd = _dot(d[0], d[1], d[2], d[0], d[1], d[2])
    beta = lincomb(mul(nn, dd), 1.0 - e2, mul(dn, dn), e2)
    blo, bhi = coef_range(beta)
    if bhi <= 0.0:
        return False, (beta, beta, beta)
    a, b, dlo, dhi = sqrt_linearisation(blo, bhi)
    g = np.zeros(4)
    g[2] = dhi - dlo
    xi = affine(b + dlo, g, lo, hi)  # ξ on [0, 1]: variable 2 of the box
    root = lincomb(beta, a, xi, 1.0)
    rn = (mul(root, n[0]), mul(root, n[1]), mul(root, n[2]))
    return True, (lincomb(lincomb(mul(nn, d[0]), 1.0, mul(dn, n[0]), -1.0), eta_ratio, rn[0], -o),
                  lincomb(lincomb(mul(nn, d[1]), 1.0, mul(dn, n[1]), -1.0), eta_ratio, rn[1], -o),
                  lincomb(lincomb(mul(nn, d[2]), 1.0, mul(dn, n[2]), -1.0), eta_ratio, rn[2], -o))


@kernel
def _receiver_numerators(x, dt, Q):
    """pu, pv, q of eq 9 for the receiver triangle Q: uk = pu/q, vk = pv/q."""
    ek1 = Q[1] - Q[0]
    ek2 = Q[2] - Q[0]
    r = (affine_map(x[0], 1.0, -Q[0, 0]), affine_map(x[1], 1.0, -Q[0, 1]), affine_map(x[2], 1.0, -Q[0, 2]))
    c = _crossc(dt[0], dt[1], dt[2], ek2)
    pu = _dot(c[0], c[1], c[2], r[0], r[1], r[2])
    q = _dotc(c[0], c[1], c[2], ek1)
    rk = _crossc(r[0], r[1], r[2], ek1)
    pv = _dot(rk[0], rk[1], rk[2], dt[0], dt[1], dt[2])
    return pu, pv, q






@kernel
def flat_coefficients(pu, pv, q):
    """pu, pv and q elevated to their common degree, as flat coefficient arrays (one
    elevation for every receiver bound of ``receiver_box``)."""
    shape = (max(pu.shape[0], pv.shape[0], q.shape[0]), max(pu.shape[1], pv.shape[1], q.shape[1]),
             max(pu.shape[2], pv.shape[2], q.shape[2]), max(pu.shape[3], pv.shape[3], q.shape[3]))
    return elevate(pu, shape).ravel(), elevate(pv, shape).ravel(), elevate(q, shape).ravel()


@kernel
def barycentric_box(pu, pv, q, res):
    """Bound (eq 3) of the receiver barycentrics uk = pu/q, vk = pv/q from flat coefficient
    arrays of one degree (one or several coefficient sets laid end to end), clipped to the
    triangle: uk, vk and 1 - uk - vk each in [0, 1].  Writes res[0:4] = (uk_lo, uk_hi, vk_lo,
    vk_hi); returns False when the bound misses the triangle."""
    a, b, c, e = bound_of_coefficients(pu, q)
    ulo, uhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if ulo > uhi:
        return False
    a, b, c, e = bound_of_coefficients(pv, q)
    vlo, vhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if vlo > vhi or ulo + vlo > 1.0:
        return False
    num = np.empty(pu.shape[0])
    for i in range(pu.shape[0]):
        num[i] = q[i] - pu[i] - pv[i]
    a, b, c, e = bound_of_coefficients(num, q)
    wlo, whi = clip_hull(a, b, c, e, 0.0, 1.0)
    if wlo > whi:
        return False
    res[0] = ulo
    res[1] = min(uhi, 1.0 - vlo - wlo)
    res[2] = vlo
    res[3] = min(vhi, 1.0 - ulo - wlo)
    return True


@kernel
def receiver_box(pu, pv, q, UV, res):
    """``barycentric_box`` in res[0:4] and the bound of the receiver's UV coordinates in
    res[4:8] (x_lo, x_hi, y_lo, y_hi), clipped to the hull of the corner UVs.  Every bounded
    coordinate is affine in (uk, vk), so its numerator's coefficients are the same combination
    of pu, pv and q.  Returns False when the bound misses."""
    if not barycentric_box(pu, pv, q, res):
        return False
    num = np.empty(pu.shape[0])
    for axis in range(2):
        c0 = UV[0, axis]
        c1 = UV[1, axis] - UV[0, axis]
        c2 = UV[2, axis] - UV[0, axis]
        for i in range(pu.shape[0]):
            num[i] = c0 * q[i] + c1 * pu[i] + c2 * pv[i]
        a, b, c, e = bound_of_coefficients(num, q)
        lo, hi = clip_hull(a, b, c, e, min(UV[0, axis], UV[1, axis], UV[2, axis]), max(UV[0, axis], UV[1, axis], UV[2, axis]))
        if lo > hi:
            return False
        res[4 + 2 * axis] = lo
        res[5 + 2 * axis] = hi
    return True




@kernel
def piece_position(refract, x0, P, N, Q, UV, eta, lo, hi, out):
    """Position bound (eq 4–5, 9; refraction with eq 12–13) of the piece lo <= (u1, v1) <= hi.

    Writes out[0:4] = (uk_lo, uk_hi, vk_lo, vk_hi) (receiver barycentrics, clipped to the
    triangle's [0, 1] ranges) and out[4:8] = (x_lo, x_hi, y_lo, y_hi) in the receiver's UV
    space, padded outwards by POS_PAD.  Returns False when no admissible path of the piece
    can reach the receiver triangle (the bound misses it)."""
    if lo[0] + lo[1] > 1.0:
        return False
    lo4, hi4 = _box4(lo, hi)
    mask = _orientations(x0, P, N, lo4, hi4)
    if mask == 0:
        return False
    x, n, d = _caster(x0, P, N, lo4, hi4)
    bu0 = np.inf
    bu1 = -np.inf
    bv0 = np.inf
    bv1 = -np.inf
    X0 = np.inf
    X1 = -np.inf
    Y0 = np.inf
    Y1 = -np.inf
    res = np.zeros(8)
    for variant in range(2):
        if not (mask >> variant) & 1:
            continue
        o = 1.0 if variant == 0 else -1.0
        if not refract and variant == 1 and (mask & 1):
            continue  # reflection does not depend on the normal's sign
        ok, dt = _direction(refract, o, ior_ratio(o, eta), n, d, lo4, hi4)
        if not ok:
            continue
        pu, pv, q = _receiver_numerators(x, dt, Q)
        fpu, fpv, fq = flat_coefficients(pu, pv, q)
        if not receiver_box(fpu, fpv, fq, UV, res):
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
def _light_factor(P, d, sign_hi):
    """Bounds of |d0·(e1×e2)| and of |d0|^-3 over the box (dΩ0/du1dv1 = product, eq 15)."""
    ng = _c3(P[1] - P[0], P[2] - P[0])
    cos_poly = _dotc(d[0], d[1], d[2], ng)
    dd = _dot(d[0], d[1], d[2], d[0], d[1], d[2])
    lo, hi = coef_range(dd)
    return cos_poly, lo, hi


@kernel
def piece_irradiance_reflect(x0, P, N, Q, lo, hi):
    """(Ē, E̲) of dΩ0/dA_k over the piece for reflection: explicit Jacobian (eq 15–16).

    Ē = inf when the Jacobian's Bernstein coefficients change sign (focal points)."""
    lo4, hi4 = _box4(lo, hi)
    x, n, d = _caster(x0, P, N, lo4, hi4)
    ok, dt = _direction(False, 1.0, 1.0, n, d, lo4, hi4)
    pu, pv, q = _receiver_numerators(x, dt, Q)
    wu = hi[0] - lo[0]
    wv = hi[1] - lo[1]
    pu_u = deriv(pu, 0, wu)
    pu_v = deriv(pu, 1, wv)
    pv_u = deriv(pv, 0, wu)
    pv_v = deriv(pv, 1, wv)
    q_u = deriv(q, 0, wu)
    q_v = deriv(q, 1, wv)
    det = lincomb(lincomb(mul(pu, sub(mul(pv_u, q_v), mul(pv_v, q_u))), 1.0,
                          mul(pv, sub(mul(pu_u, q_v), mul(pu_v, q_u))), -1.0), 1.0,
                  mul(q, sub(mul(pu_u, pv_v), mul(pu_v, pv_u))), 1.0)
    cos_poly, dlo, dhi = _light_factor(P, d, True)
    num = mul(cos_poly, mul(q, mul(q, q)))
    a, b, c, e = rational_bound(num, det)
    ak = _n3(_c3(Q[1] - Q[0], Q[2] - Q[0]))
    upper = abs_upper(a, b, c, e)
    lower = abs_lower(a, b, c, e)
    if dlo <= 0.0:
        return np.inf, 0.0
    return upper * dlo ** -1.5 / ak * (1.0 + IRR_PAD), lower * dhi ** -1.5 / ak * (1.0 - IRR_PAD)


@kernel
def piece_irradiance_refract(x0, P, N, Q, eta, lo, hi, pos):
    """(Ē, E̲) of dΩ0/dA_k over the piece for refraction at x1: implicit differentiation of
    the specular constraints (eq 17–19) over the 4-D box (u1, v1) × (uk, vk) in ``pos``.

    F = |d1|² ((d0×n)·b)² - η² |d0|² ((d1×n)·b)², η = η_t/η_i, G = (d0×n)·d1; two vectors b
    tangent to the caster are used and the smaller upper bound kept (the paper's
    intersection of bounds, with b chosen so that neither is parallel to the normal)."""
    lo4, hi4 = _box4(lo, hi)
    for k in range(2):  # (uk, vk) box, at least MIN_WIDTH wide so derivatives stay well-conditioned
        a, b = pos[2 * k], pos[2 * k + 1]
        if b - a < MIN_WIDTH:
            a, b = 0.5 * (a + b) - 0.5 * MIN_WIDTH, 0.5 * (a + b) + 0.5 * MIN_WIDTH
        lo4[2 + k], hi4[2 + k] = a, b
    mask = _orientations(x0, P, N, lo4, hi4)
    if mask == 0:
        return 0.0, 0.0
    e1 = P[1] - P[0]
    e2 = P[2] - P[0]
    x, n, d = _caster(x0, P, N, lo4, hi4)
    ek1 = Q[1] - Q[0]
    ek2 = Q[2] - Q[0]
    g = np.zeros(4)
    comps = []
    for i in range(3):
        g[0], g[1], g[2], g[3] = -e1[i], -e2[i], ek1[i], ek2[i]
        comps.append(affine(Q[0, i] - P[0, i], g, lo4, hi4))
    d1 = (comps[0], comps[1], comps[2])
    cos_poly, dlo, dhi = _light_factor(P, d, True)
    if dlo <= 0.0:
        return np.inf, 0.0
    ng = _c3(e1, e2)
    t1 = e1 / _n3(e1)
    t2 = _c3(ng, t1)
    t2 = t2 / _n3(t2)
    d0n = _cross(d[0], d[1], d[2], n[0], n[1], n[2])
    d1n = _cross(d1[0], d1[1], d1[2], n[0], n[1], n[2])
    l0 = _dot(d[0], d[1], d[2], d[0], d[1], d[2])
    l1 = _dot(d1[0], d1[1], d1[2], d1[0], d1[1], d1[2])
    G = _dot(d0n[0], d0n[1], d0n[2], d1[0], d1[1], d1[2])
    w = hi4 - lo4
    G1 = deriv(G, 0, w[0])
    G2 = deriv(G, 1, w[1])
    G3 = deriv(G, 2, w[2])
    G4 = deriv(G, 3, w[3])
    ak = _n3(_c3(ek1, ek2))
    best_hi = 0.0
    best_lo = np.inf
    for variant in range(2):
        if not (mask >> variant) & 1:
            continue
        o = 1.0 if variant == 0 else -1.0
        eta_f = 1.0 / ior_ratio(o, eta)
        hi_v = np.inf
        lo_v = 0.0
        for bi in range(2):
            b = t1 if bi == 0 else t2
            A = _dotc(d0n[0], d0n[1], d0n[2], b)
            B = _dotc(d1n[0], d1n[1], d1n[2], b)
            F = lincomb(mul(l1, mul(A, A)), 1.0, mul(l0, mul(B, B)), -eta_f * eta_f)
            F1 = deriv(F, 0, w[0])
            F2 = deriv(F, 1, w[1])
            F3 = deriv(F, 2, w[2])
            F4 = deriv(F, 3, w[3])
            det1 = sub(mul(F1, G2), mul(F2, G1))
            detk = sub(mul(F3, G4), mul(F4, G3))
            a, bb, c, e = rational_bound(mul(cos_poly, detk), det1)
            hi_v = min(hi_v, abs_upper(a, bb, c, e))
            lo_v = max(lo_v, abs_lower(a, bb, c, e))
        best_hi = max(best_hi, hi_v)
        best_lo = min(best_lo, lo_v)
    if best_lo == np.inf:
        best_lo = 0.0
    return best_hi * dlo ** -1.5 / ak * (1.0 + IRR_PAD), best_lo * dhi ** -1.5 / ak * (1.0 - IRR_PAD)


@kernel
def tuple_pieces(refract, x0, P, N, Q, UV, eta, max_depth, sigma, alpha, irradiance, out, stats):
    """Subdivide the caster domain of one tuple (§6.1 stopping rules) into pieces.

    Writes up to out.shape[0] piece rows (layout P_*) and returns their number; the
    quadtree only splits while the rows still fit, so every admissible path is always
    inside some written piece (a full buffer stops subdivision, counted in stats[3])."""
    cap = out.shape[0]
    size = 4 * (max_depth + 2)
    stack = np.empty((size, 5))
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0.0, 1.0, 0.0, 1.0, 0.0
    top = 1
    count = 0
    lo = np.zeros(2)
    hi = np.zeros(2)
    pos = np.zeros(8)
    while top > 0:
        top -= 1
        lo[0], hi[0], lo[1], hi[1] = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        depth = int(stack[top, 4])
        stats[0] += 1
        if not piece_position(refract, x0, P, N, Q, UV, eta, lo, hi, pos):
            continue
        can_split = depth < max_depth and count + top + 4 <= cap
        area = (pos[1] - pos[0]) * (pos[3] - pos[2])
        ehi = np.inf
        elo = 0.0
        split = False
        if area >= sigma and can_split:
            if irradiance:
                stats[1] += 1
                if refract:
                    ehi, elo = piece_irradiance_refract(x0, P, N, Q, eta, lo, hi, pos)
                else:
                    ehi, elo = piece_irradiance_reflect(x0, P, N, Q, lo, hi)
                split = not (elo > 0.0 and ehi < alpha * elo)
            else:
                split = True
        elif irradiance:
            stats[1] += 1
            if refract:
                ehi, elo = piece_irradiance_refract(x0, P, N, Q, eta, lo, hi, pos)
            else:
                ehi, elo = piece_irradiance_reflect(x0, P, N, Q, lo, hi)
        if split:
            top = push_children(stack, top, lo, hi, depth)
            continue
        if depth < max_depth and area >= sigma and not can_split:
            stats[3] += 1
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


@parallel_range("pairs")
def _batch(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, out, counts, stats, first, last):
    for t in range(first, last):
        c = pairs[t, 0]
        r = pairs[t, 1]
        counts[t] = tuple_pieces(refract, x0[c], P[c], N[c], Q[r], UV[r], eta, max_depth, sigma, alpha, irradiance,
                                 out[t], stats[t])


def batch(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts, stats, chunk):
    """``one_bounce.batch``'s signature (x0: a light point per caster); irr_refine and chunk are
    not used by this engine."""
    _batch(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, out, counts, stats)
