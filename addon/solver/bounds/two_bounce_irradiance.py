"""Irradiance bounds of two-bounce chains (RR, RT, TR, TT) from a point light (Fan et al. 2025 §4.4).

For a piece — a box U1 of triangle 1's barycentrics (u1, v1) of a tuple (light x0, caster
triangle 1, caster triangle 2, receiver triangle k) — this module bounds the irradiance
dΩ0/dA_k (eq 14–15 with I0 = 1, F, V <= 1 left out as in the paper) of every admissible path
x0 -> x1 -> x2 -> xk with x1 in U1:

    dΩ0/dA_k = |d0·(e1×e2)| / |d0|³ · |det ∂(u1,v1)/∂(uk,vk)| / |e_k1 × e_k2|          (eq 15)

with the Jacobian taken explicitly, as the reciprocal of det ∂(uk,vk)/∂(u1,v1) (eq 16).

The explicit Jacobian is used rather than the Bernstein form of eq 16 (as for one bounce):
through two vertices uk is rational in (u1, v1) only after both √β are approximated, and the
remainder variables that keep the position bound conservative say nothing about derivatives.
Instead the exact forward map u1 -> x1 -> d̃1 (eq 10, exact √β1) -> u2 (eq 9 on triangle 2) ->
x2, n2 -> d̃2 (exact √β2) -> uk is evaluated in the affine arithmetic of ``affine`` with forward
differentiation (duals: value, ∂/∂u1, ∂/∂v1, each an affine form over the box), so eq 16's
determinant is enclosed up to O(box²) with its correlated terms cancelling; √ carries its
Chebyshev error in the remainder, so the bound is conservative:

* Ē = max |d0·(e1×e2)| / min |d0|³ / (min |det| · |e_k1 × e_k2|), E̲ with min/max swapped;
* Ē = inf (status UNBOUNDED_*, counted per reason) where the determinant's enclosure contains
  0 (focal points, caustic curves), where β of a refraction reaches 0 in the box (grazing
  refraction, the onset of total internal reflection) or where a ray can be parallel to the
  next plane.  At the last vertex such boxes get a second try with the implicit form (eq
  17–19, ``implicit_last_vertex``: u1 and uk independent over the box × the piece's receiver
  bound, no √);
* sub-boxes whose x1 lies outside triangle 1, whose ray meets a plane only backwards, whose u2
  or uk enclosure misses its triangle, or whose β < 0 everywhere (total internal reflection)
  hold no admissible path and are skipped (a piece with none gets Ē = E̲ = 0).

At vertex 2 the incoming direction is d̃1 itself rather than x2 - x1 (adjacent triangles of one
surface would take β2 to 0 with x2 - x1).  The piece is split (quadtree of at most ``irr_depth``
levels inside it) while the bound is unbounded or Ē/E̲ > ``irr_ratio``.  Orientation at each
vertex follows the side rules of addon/solver/CONTRACT.md (o = sign((source - x)·ng) · sign(ng·n),
η' = 1/η for o > 0, η otherwise); where the sign is not fixed over a box both orientations
are bounded and the larger Ē kept; the final bound is padded by IRR_PAD.
Tested in tests/solver/test_bounds_two_bounce.py (bounds bracket the geometry term of traced
paths; the implicit form brackets |det ∂u1/∂uk|).
"""

import math
import time

import numpy as np

from .affine import (ROUND, abs_range, aff_mul, aff_range, aff_sub, cross3, dual_add, dual_add_const, dual_affine,
                     dual_div, dual_mul, dual_range, dual_scale, dual_sqrt, dual_sub, vec_cross, vec_cross_const,
                     vec_dot, vec_dot_const)

from ..runtime.jit import kernel, run_chunks
from .layout import CHAIN_CODES, IRR_PAD, P_BU0, P_EHI, P_ELO, P_U0, P_U1, P_V0, P_V1, ior_ratio, orientation_mask, push_children

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
# The exact forward map in dual intervals.

@kernel
def scatter_dual(refract, o, eta_ratio, n, d):
    """Outgoing direction d̃ (eq 10) of incoming d at unnormalised normal n (orientation o),
    with the exact √β (eq 11).  Returns (status, d̃): NO_PATH (total internal reflection on
    the whole box), BOUNDED, or UNBOUNDED_GRAZING (β reaches 0: d̃'s values are enclosed, its
    derivatives are not)."""
    nn = vec_dot(n, n)
    dn = vec_dot(d, n)
    if not refract:
        two_dn = dual_scale(dn, 2.0)
        return BOUNDED, (dual_sub(dual_mul(nn, d[0]), dual_mul(two_dn, n[0])), dual_sub(dual_mul(nn, d[1]), dual_mul(two_dn, n[1])),
                         dual_sub(dual_mul(nn, d[2]), dual_mul(two_dn, n[2])))
    e2 = eta_ratio * eta_ratio
    dd = vec_dot(d, d)
    beta = dual_add(dual_scale(dual_mul(nn, dd), 1.0 - e2), dual_scale(dual_mul(dn, dn), e2))
    blo, bhi = dual_range(beta)
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
        root = dual_scale(dual_sqrt(beta), -o)
        status = BOUNDED
    out0 = dual_add(dual_scale(dual_sub(dual_mul(nn, d[0]), dual_mul(dn, n[0])), eta_ratio), dual_mul(root, n[0]))
    out1 = dual_add(dual_scale(dual_sub(dual_mul(nn, d[1]), dual_mul(dn, n[1])), eta_ratio), dual_mul(root, n[1]))
    out2 = dual_add(dual_scale(dual_sub(dual_mul(nn, d[2]), dual_mul(dn, n[2])), eta_ratio), dual_mul(root, n[2]))
    return status, (out0, out1, out2)


@kernel
def hit_dual(x, dt, Q):
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
    ng = cross3(e1, e2)
    # forward only: t = ((Q0 - x)·ng) / (d̃·ng) must be positive somewhere on the box
    hlo, hhi = dual_range(vec_dot_const((dual_add_const(x[0], -Q[0, 0]), dual_add_const(x[1], -Q[0, 1]), dual_add_const(x[2], -Q[0, 2])), ng))  # -(numerator)
    glo, ghi = dual_range(vec_dot_const(dt, ng))
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
    Y = (dual_add_const(x[0], -Xc[0]), dual_add_const(x[1], -Xc[1]), dual_add_const(x[2], -Xc[2]))
    c = vec_cross_const(dt, e2)
    pu = vec_dot(c, Y)
    q = vec_dot_const(c, e1)
    rk = vec_cross_const(Y, e1)
    pv = vec_dot(rk, dt)
    ok, u = dual_div(pu, q)
    if not ok:
        return UNBOUNDED_PARALLEL, pu, pv
    ok, v = dual_div(pv, q)
    if not ok:
        return UNBOUNDED_PARALLEL, pu, pv
    u = dual_add_const(u, uc)
    v = dual_add_const(v, vc)
    ulo, uhi = dual_range(u)
    vlo, vhi = dual_range(v)
    if ulo > 1.0 + EDGE_TOL or uhi < -EDGE_TOL or vlo > 1.0 + EDGE_TOL or vhi < -EDGE_TOL or ulo + vlo > 1.0 + EDGE_TOL:
        return NO_PATH, u, v
    return BOUNDED, u, v


@kernel
def _jacobian_abs_det(uk, vk):
    """Enclosure (min, max) of |det ∂(uk,vk)/∂(u1,v1)| (eq 16) over the box: the determinant
    of the derivative forms in affine arithmetic.  (0, inf) when it may vanish."""
    det = aff_sub(aff_mul(uk[1], vk[2]), aff_mul(uk[2], vk[1]))
    lo, hi = aff_range(det)
    if lo > 0.0:
        return lo, hi
    if hi < 0.0:
        return -hi, -lo
    return 0.0, np.inf


@kernel
def implicit_last_vertex(d1, n2, x2, Q, rbox, eta_f, b):
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
    d2 = (dual_sub(xk0, x2[0]), dual_sub(xk1, x2[1]), dual_sub(xk2, x2[2]))
    p = vec_cross(d1, n2)
    A = vec_dot_const(p, b)
    B = vec_dot_const(vec_cross(d2, n2), b)
    l1 = vec_dot(d1, d1)
    l2 = vec_dot(d2, d2)
    e2 = eta_f * eta_f
    F = dual_sub(dual_mul(l2, dual_mul(A, A)), dual_scale(dual_mul(l1, dual_mul(B, B)), e2))
    G = vec_dot(p, d2)
    det_u1 = aff_sub(aff_mul(F[1], G[2]), aff_mul(F[2], G[1]))
    lo1, hi1 = aff_range(det_u1)
    lo1, hi1 = abs_range(lo1, hi1)
    if not (lo1 > 0.0):
        return 0.0, np.inf
    # ∇_d2 F (value forms only)
    nb = vec_cross_const(n2, b)
    two_a2 = dual_scale(dual_mul(A, A), 2.0)
    k = dual_scale(dual_mul(l1, B), 2.0 * e2)
    g0 = dual_sub(dual_mul(two_a2, d2[0]), dual_mul(k, nb[0]))
    g1 = dual_sub(dual_mul(two_a2, d2[1]), dual_mul(k, nb[1]))
    g2 = dual_sub(dual_mul(two_a2, d2[2]), dual_mul(k, nb[2]))
    grad = (g0, g1, g2)
    f_uk = vec_dot_const(grad, ek1)[0]
    f_vk = vec_dot_const(grad, ek2)[0]
    g_uk = vec_dot_const(p, ek1)[0]
    g_vk = vec_dot_const(p, ek2)[0]
    lok, hik = aff_range(aff_sub(aff_mul(f_uk, g_vk), aff_mul(f_vk, g_uk)))
    lok, hik = abs_range(lok, hik)
    if not math.isfinite(hik):
        return 0.0, np.inf
    return lok / hi1, hik / lo1


@kernel
def vertex_one_dual(x0, P1, N1, box):
    """x1 and n1 on triangle 1 over the box of (u1, v1), d0 = x1 - x0 (dual forms), triangle
    1's geometric normal and its orientation mask (``layout.orientation_mask``)."""
    e1 = P1[1] - P1[0]
    e2 = P1[2] - P1[0]
    ng1 = cross3(e1, e2)
    m1 = N1[1] - N1[0]
    m2 = N1[2] - N1[0]
    x1 = (dual_affine(P1[0, 0], e1[0], e2[0], box), dual_affine(P1[0, 1], e1[1], e2[1], box), dual_affine(P1[0, 2], e1[2], e2[2], box))
    n1 = (dual_affine(N1[0, 0], m1[0], m2[0], box), dual_affine(N1[0, 1], m1[1], m2[1], box), dual_affine(N1[0, 2], m1[2], m2[2], box))
    d0 = (dual_add_const(x1[0], -x0[0]), dual_add_const(x1[1], -x0[1]), dual_add_const(x1[2], -x0[2]))
    side1 = (x0[0] - P1[0, 0]) * ng1[0] + (x0[1] - P1[0, 1]) * ng1[1] + (x0[2] - P1[0, 2]) * ng1[2]
    nlo, nhi = dual_range(vec_dot_const(n1, ng1))
    return x1, n1, d0, ng1, orientation_mask(side1, side1, nlo, nhi)


@kernel
def first_bounce_rays(refract1, x0, P1, N1, eta, box, xlo, xhi, dlo, dhi):
    """Value enclosures of x1 (xlo, xhi) and of the outgoing direction d̃1 (dlo, dhi; union
    over the orientations present, unnormalised) over the box of triangle 1's (u1, v1), for
    the pair search (``tuples``, §6.1).  Returns the bit mask of the orientations that send
    light out (0: none — x0 in the plane, or total internal reflection on the whole box)."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return 0
    x1, n1, d0, ng1, mask1 = vertex_one_dual(x0, P1, N1, box)
    for i in range(3):
        xlo[i], xhi[i] = dual_range(x1[i])
        dlo[i] = np.inf
        dhi[i] = -np.inf
    bits = 0
    for k1 in range(2):
        if not (mask1 >> k1) & 1:
            continue
        if not refract1 and k1 == 1 and (mask1 & 1):
            continue
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = scatter_dual(refract1, o1, ior_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        bits |= 1 << k1
        for i in range(3):
            a, b = dual_range(dt1[i])
            dlo[i] = min(dlo[i], a)
            dhi[i] = max(dhi[i], b)
    return bits


@kernel
def _first_hit_status(refract1, x0, P1, N1, P2, eta, box, bits):
    """NO_PATH when no light leaving the box of triangle 1 (orientations ``bits``) meets
    triangle 2 forwards, else the status of the first orientation that may (eq 9)."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return NO_PATH
    x1, n1, d0, ng1, mask1 = vertex_one_dual(x0, P1, N1, box)
    for k1 in range(2):
        if not (bits >> k1) & 1 or not (mask1 >> k1) & 1:
            continue
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = scatter_dual(refract1, o1, ior_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        st, u2, v2 = hit_dual(x1, dt1, P2)
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
    """Steps 1–2 of the two-bounce position bound (vertex 1 -> 2) for orientation o1 at vertex 1: u2 and v2 on
    triangle 2 over the box of (u1, v1) as forms c + g_u u1 + g_v v1 + g_xi ξ (ξ in [0, 1], one
    remainder variable each; ``_linear_form``), from the exact map x1 -> d̃1 (eq 10, exact √β)
    -> (u2, v2) (eq 9) in affine arithmetic.  Returns False when no light of the box reaches
    triangle 2; stats[2] += 1 per constant form (the line can be parallel to triangle 2, or the
    remainder is wider than the triangle)."""
    x1, n1, d0, ng1, mask1 = vertex_one_dual(x0, P1, N1, box)
    st, dt1 = scatter_dual(refract1, o1, ior_ratio(o1, eta), n1, d0)
    if st == NO_PATH:
        return False
    st, u2, v2 = hit_dual(x1, dt1, P2)
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
    implicit form (eq 17–19, ``implicit_last_vertex``, two tangent vectors b, the smaller
    bound kept) is used instead."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return NO_PATH, 0.0, 0.0
    x1, n1, d0, ng1, mask1 = vertex_one_dual(x0, P1, N1, box)
    # light factor |d0·(e1×e2)| / |d0|³ (value enclosures only)
    clo, chi = dual_range(vec_dot_const(d0, ng1))
    clo, chi = abs_range(clo, chi)
    dlo, dhi = dual_range(vec_dot(d0, d0))
    if dlo <= 0.0:
        return UNBOUNDED, np.inf, 0.0
    light_hi = chi / dlo ** 1.5
    light_lo = clo / dhi ** 1.5
    ak = math.sqrt(np.sum(cross3(Q[1] - Q[0], Q[2] - Q[0]) ** 2))
    ng2 = cross3(P2[1] - P2[0], P2[2] - P2[0])
    f1 = P2[1] - P2[0]
    f2 = P2[2] - P2[0]
    # two unit tangents of triangle 2 for the implicit bound's vectors b (eq 17)
    tb1 = f1 / math.sqrt(np.sum(f1 * f1))
    tb2 = cross3(ng2, tb1)
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
        st, dt1 = scatter_dual(refract1, o1, ior_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        # grazing at vertex 1: Ē = inf if a path can get through, but d̃1's values are still
        # enclosed, so the rest of the path can still prove the box empty
        grazing1 = st == UNBOUNDED_GRAZING
        st, u2, v2 = hit_dual(x1, dt1, P2)
        if st >= UNBOUNDED:
            return st, np.inf, 0.0
        if st == NO_PATH:
            continue
        x2 = (dual_add_const(dual_add(dual_scale(u2, f1[0]), dual_scale(v2, f2[0])), P2[0, 0]),
              dual_add_const(dual_add(dual_scale(u2, f1[1]), dual_scale(v2, f2[1])), P2[0, 1]),
              dual_add_const(dual_add(dual_scale(u2, f1[2]), dual_scale(v2, f2[2])), P2[0, 2]))
        n2 = (dual_add_const(dual_add(dual_scale(u2, g1[0]), dual_scale(v2, g2[0])), N2[0, 0]),
              dual_add_const(dual_add(dual_scale(u2, g1[1]), dual_scale(v2, g2[1])), N2[0, 1]),
              dual_add_const(dual_add(dual_scale(u2, g1[2]), dual_scale(v2, g2[2])), N2[0, 2]))
        # The incoming direction at x2 is d̃1 itself (d1 = x2 - x1 = t d̃1, t > 0 for every
        # path; eq 10 is homogeneous in d, so the scale does not matter).  Using d̃1 instead
        # of x2 - x1 keeps the forms well conditioned when x2 comes close to x1 (adjacent
        # triangles of one surface), where |d1| -> 0 would make β2 vanish with it.
        d1 = dt1
        slo, shi = dual_range(vec_dot_const(d1, ng2))  # side of x1: (x1 - x2)·ng2 = -t d̃1·ng2
        nlo2, nhi2 = dual_range(vec_dot_const(n2, ng2))
        mask2 = orientation_mask(-shi, -slo, nlo2, nhi2)
        for k2 in range(2):
            if not (mask2 >> k2) & 1:
                continue
            if not refract2 and k2 == 1 and (mask2 & 1):
                continue
            o2 = 1.0 if k2 == 0 else -1.0
            st, dt2 = scatter_dual(refract2, o2, ior_ratio(o2, eta), n2, d1)
            if st == NO_PATH:
                continue
            if st == BOUNDED:
                st, uk, vk = hit_dual(x2, dt2, Q)
                if st == NO_PATH:
                    continue
            elif hit_dual(x2, dt2, Q)[0] == NO_PATH:  # grazing: d̃2's values are enclosed all the same
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
            eta_f = 1.0 / ior_ratio(o2, eta) if refract2 else 1.0
            rhi = np.inf
            rlo = 0.0
            for bi in range(2):
                b = tb1 if bi == 0 else tb2
                a_lo, a_hi = implicit_last_vertex(d1, n2, x2, Q, rbox, eta_f, b)
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

    chain_code as ``layout.CHAIN_CODES`` (bit 0: vertex 1 refracts, bit 1: vertex 2 refracts).
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
def reach_chunk(chain_code, x0, P, N, Q, eta, pairs, mask, reach, start, stop):
    """reach[t, r] of ``receivers_reached`` for pairs start..stop-1, with light point x0[t] and IOR
    eta[t] of pair t, and only for the receivers with mask[t, r] (the others stay unreached)."""
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
            if not mask[t, r]:
                continue
            box[0], box[1], box[2], box[3] = 0.0, 1.0, 0.0, 1.0
            st, bh, bl = sub_box_irradiance(refract1, refract2, x0[t], P[a], N[a], P[b], N[b], Q[r], eta[t], box, rbox)
            if st == NO_PATH:
                continue
            if cells == 1:
                grid[0, 0] = True
                continue
            for i in range(cells):
                for j in range(cells - i):
                    box[0], box[1], box[2], box[3] = i * h, (i + 1) * h, j * h, (j + 1) * h
                    st, bh, bl = sub_box_irradiance(refract1, refract2, x0[t], P[a], N[a], P[b], N[b], Q[r], eta[t], box, rbox)
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

    ``two_bounce.bound_two_bounce`` starts and prunes its position quadtree with it (a box lives
    for a receiver while ``box_reached``): it removes the (pair, receiver) tuples whose
    position bound cannot see the emptiness — neighbouring triangles of one surface, whose
    x2 - x1 relaxation spans the whole receiver (slab10k TT: 55 % of the position tuples proven
    empty on the whole triangle, 63 % with depth 1).  depth 2 is ``bound_two_bounce``'s default
    (slab10k reach + bounds 13.7 s against 14.8 s at depth 1)."""
    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    receiver_P = np.ascontiguousarray(receiver_P, dtype=np.float64)
    cells = 1 << int(depth)
    reach = np.zeros((pairs.shape[0], receiver_P.shape[0], cells, cells), dtype=np.bool_)
    if reach.size:
        n = pairs.shape[0]
        points = np.array(np.broadcast_to(np.asarray(light, dtype=np.float64).reshape(3), (n, 3)))
        mask = np.ones((n, receiver_P.shape[0]), dtype=np.bool_)
        run_chunks(reach_chunk, (CHAIN_CODES[chain], points, np.ascontiguousarray(caster_P, dtype=np.float64),
                                 np.ascontiguousarray(caster_N, dtype=np.float64), receiver_P, np.full(n, float(eta)), pairs,
                                 mask, reach), n)
    return reach


@kernel
def irradiance_chunk(chain_code, x0, P, N, Q, eta, piece_pair, piece_receiver, pieces, irr_depth, irr_ratio, stats,
                      start, stop):
    """Ē, E̲ of pieces start..stop-1 (``bound_irradiance_two``), piece i lit from x0[i] through IOR
    eta[i]; on ``jit.run_chunks`` threads, which compile in a fraction of a ``parallel=True``
    loop's time."""
    lo = np.empty(2)
    hi = np.empty(2)
    rbox = np.empty(4)
    for i in range(start, stop):
        a = piece_pair[i, 0]
        b = piece_pair[i, 1]
        lo[0], hi[0], lo[1], hi[1] = pieces[i, P_U0], pieces[i, P_U1], pieces[i, P_V0], pieces[i, P_V1]
        for k in range(4):
            rbox[k] = pieces[i, P_BU0 + k]
        eh, el = piece_irradiance_two(chain_code, x0[i], P[a], N[a], P[b], N[b], Q[piece_receiver[i]], eta[i], lo, hi, rbox,
                                      irr_depth, irr_ratio, stats[i])
        pieces[i, P_EHI] = eh
        pieces[i, P_ELO] = el


def bound_irradiance_two(bounds, light, caster_P, caster_N, receiver_P, eta=1.5, irr_depth=2, irr_ratio=2.0):
    """Fill Ē and E̲ (columns P_EHI, P_ELO) of every piece of a ``two_bounce.TwoBounceBounds`` in
    place (Fan et al. 2025 eq 14–16, module doc) and add the counts to its report.

    irr_depth: most quadtree levels inside a piece for the irradiance bound (0: the piece as
    it is); irr_ratio: split while Ē/E̲ exceeds it.  Returns ``bounds``."""
    t0 = time.perf_counter()
    tuples = bounds.tuples
    pair = np.ascontiguousarray(tuples[bounds.piece_tuple, :2], dtype=np.int64)
    receiver = np.ascontiguousarray(tuples[bounds.piece_tuple, 2], dtype=np.int64)
    stats = np.zeros((bounds.pieces.shape[0], N_IRR_STATS), dtype=np.int64)
    if bounds.pieces.shape[0]:
        n = bounds.pieces.shape[0]
        points = np.array(np.broadcast_to(np.asarray(light, dtype=np.float64).reshape(3), (n, 3)))
        run_chunks(irradiance_chunk, (CHAIN_CODES[bounds.chain], points,
                                       np.ascontiguousarray(caster_P, dtype=np.float64),
                                       np.ascontiguousarray(caster_N, dtype=np.float64),
                                       np.ascontiguousarray(receiver_P, dtype=np.float64), np.full(n, float(eta)), pair, receiver,
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
