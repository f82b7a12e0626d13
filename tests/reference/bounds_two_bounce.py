"""Reference engine of the two-bounce position bounds (RR, RT, TR, TT; Fan et al. 2025): readable, allocating.

The production engine is ``addon.solver.bounds.two_bounce_position`` (the same steps without
allocation per box); tests/solver/test_bounds_two_bounce.py runs both through
``bound_two_bounce(..., engine=batch)`` and compares the pieces.

For a tuple (light x0, caster triangle 1, caster triangle 2, receiver triangle k) and a box U1
of triangle 1's barycentrics (u1, v1), a *piece* gets the position bound (eq 4–5): a box of
receiver barycentrics (uk, vk) and of receiver UV coordinates containing the hit point of every
admissible path x0 -> x1 -> x2 -> xk with x1 in U1 (∩ triangle 1) and x2 on triangle 2.

Rational formulation (§4.3) in two stages, every non-rational or high-degree part replaced by
a low-degree expression plus remainder variables (eq 12–13 and the degree reduction of §6.1),
so the bound stays conservative:

1. Vertex 1 -> 2: x1, n1 affine in (u1, v1) (eq 6–7), d̃1 from eq 10 with the exact √β1 and
   u2, v2 by eq 9 with triangle 2 as the "receiver", all in affine arithmetic over the box
   (``addon.solver.bounds.two_bounce_irradiance.first_bounce_forms``; √ by its Chebyshev enclosure, so no approximation
   error is left out).
2. Degree reduction (§6.1 "Degree reduction", with a linear approximant): the affine form of u2,
   L_u(u1, v1) ± r, becomes u2 = L_u - r + ξa 2r with a new remainder variable ξa in [0, 1]; the
   same for v2 with ξb.  When the remainder is wider than the clipped range [u2_lo, u2_hi] ∩
   [0, 1] itself, or the line can be parallel to triangle 2, the constant form
   u2 = u2_lo + ξa (u2_hi - u2_lo) is used instead (it drops the correlation of x2 with x1 that
   the affine part keeps).
3. Vertex 2 -> receiver: x2, n2 (eq 6–7) and d1 = x2 - x1 (eq 8) are affine in the four
   variables (u1, v1, ξa, ξb); d̃2 from eq 10 (refraction: √β2 -> aβ2 + b + δ with δ spanning
   [δ_lo, δ_hi] through a remainder variable ξ2) and (uk, vk) by eq 9.  The receiver
   coordinates are linear fractional in ξ2 (d̃2 is affine in ξ2 and eq 9 is linear in d̃2), so
   their 5-variable Bernstein coefficients are those at ξ2 = 0 and ξ2 = 1: the bound (eq 3) is
   taken over both coefficient sets together (``_flat_common``, ``bounds_one_bounce.receiver_box``), exact for
   the 5-variable polynomial without a fifth array dimension.  Every receiver quantity bounded
   (uk, vk, 1 - uk - vk, UV) is affine in (uk, vk), so one elevation of pu, pv, q serves all.
4. The steps before eq 9 do not depend on the receiver: a pair (triangle 1, triangle 2) is
   subdivided once for all receiver triangles (``pair_pieces_two``), each keeping its own
   quadtree of the §6.1 stopping rules.  A box lives for a receiver only where the reach grid
   of ``addon.solver.bounds.two_bounce_irradiance.receivers_reached`` (the exact map in affine arithmetic on triangle 1's
   2^d x 2^d cells) does not prove that no path of the cell reaches it: the relaxation
   d1 = x2 - x1 of step 3 cannot see that light leaving triangle 1 misses the neighbouring
   triangles of its own surface, and those (pair, receiver) tuples were most of the work.

Degrees stay at most 6 per variable (TT), far below the ~40 where the paper reduces degree.
The bound converges as U1 shrinks: the remainders of step 2 are O(|U1|²) away from focal points.

Orientation at each vertex follows CONTRACT.md (the light's side of the geometric normal turned
to the shading normal); at vertex 2 the "light" is x1, whose side of triangle 2's plane is
taken over the corners of U1.  η' = 1/η entering the medium (shading normal towards the
incoming light), η leaving it.  The irradiance bound (Ē, E̲ of every final piece) is a
separate pass, ``addon.solver.bounds.two_bounce_irradiance.bound_irradiance_two`` (eq 14–16 in affine arithmetic);
``bound_two_bounce`` runs it unless ``irradiance=False``.  Subdivision here follows the
position rules only (σ, depth), not the ratio α of §6.1: the irradiance pass refines inside
each piece by itself.
"""


import numpy as np

from addon.solver.runtime.jit import kernel, parallel_range
from addon.solver.polynomials.bernstein import (with_extent, add, affine, affine_map, coef_range, elevate, lincomb, mul,
                                     sqrt_linearisation)
from addon.solver.bounds.layout import (P_BU0, P_DEPTH, P_EHI, P_ELO, P_RECEIVER, P_U0, P_U1, P_V0, P_V1, POS_PAD,
                                        ior_ratio, orientation_mask, push_children)
from addon.solver.bounds.two_bounce_irradiance import box_reached
from addon.solver.bounds.two_bounce_position import stage_one
from reference.bounds_one_bounce import _c3, _d3, _dot, _orientations, _receiver_numerators, receiver_box



@kernel
def _vertex_two(P1, P2, N2, fu, fv, lo4, hi4):
    """x2, n2 (eq 6–7) and d1 = x2 - x1 (eq 8) as Bernstein polynomials in (u1, v1, ξa, ξb),
    with u2 = fu[0] + fu[1] u1 + fu[2] v1 + fu[3] ξa and v2 likewise with ξb."""
    e1 = P2[1] - P2[0]
    e2 = P2[2] - P2[0]
    m1 = N2[1] - N2[0]
    m2 = N2[2] - N2[0]
    f1 = P1[1] - P1[0]
    f2 = P1[2] - P1[0]
    g = np.zeros(4)
    xs = []
    ns = []
    ds = []
    for i in range(3):
        g[0] = fu[1] * e1[i] + fv[1] * e2[i]
        g[1] = fu[2] * e1[i] + fv[2] * e2[i]
        g[2] = fu[3] * e1[i]
        g[3] = fv[3] * e2[i]
        c = P2[0, i] + fu[0] * e1[i] + fv[0] * e2[i]
        xs.append(affine(c, g, lo4, hi4))
        g[0] -= f1[i]
        g[1] -= f2[i]
        ds.append(affine(c - P1[0, i], g, lo4, hi4))
        g[0] = fu[1] * m1[i] + fv[1] * m2[i]
        g[1] = fu[2] * m1[i] + fv[2] * m2[i]
        g[2] = fu[3] * m1[i]
        g[3] = fv[3] * m2[i]
        ns.append(affine(N2[0, i] + fu[0] * m1[i] + fv[0] * m2[i], g, lo4, hi4))
    return (xs[0], xs[1], xs[2]), (ns[0], ns[1], ns[2]), (ds[0], ds[1], ds[2])


@kernel
def _orientations_two(P1, P2, n2, lo, hi):
    """Orientation mask at vertex 2 (bit 1: o = +1, bit 2: o = -1), as ``chain1._orientations``
    with the light replaced by x1 in the box: the sign of (x1 - p2_0)·ng2 at the box corners
    (x1 is affine in (u1, v1), so the corners bound it) times the sign range of n2·ng2."""
    ng = _c3(P2[1] - P2[0], P2[2] - P2[0])
    f1 = P1[1] - P1[0]
    f2 = P1[2] - P1[0]
    base = _d3(P1[0] - P2[0], ng)
    a = _d3(f1, ng)
    b = _d3(f2, ng)
    smin = np.inf
    smax = -np.inf
    for k in range(4):
        u = lo[0] if k & 1 == 0 else hi[0]
        v = lo[1] if k & 2 == 0 else hi[1]
        s = base + a * u + b * v
        smin = min(smin, s)
        smax = max(smax, s)
    ndot = lincomb(lincomb(n2[0], ng[0], n2[1], ng[1]), 1.0, n2[2], ng[2])
    nlo, nhi = coef_range(ndot)
    return orientation_mask(smin, smax, nlo, nhi)


@kernel
def _directions_two(refract, o, eta_ratio, n, d):
    """d̃2 (eq 10) at ξ2 = 0, and the direction m with d̃2(ξ2) = d̃2(0) + ξ2 m.  Refraction replaces
    √β2 (eq 11) by aβ2 + b + δ_lo + ξ2 (δ_hi - δ_lo) (eq 12–13), so m = -o (δ_hi - δ_lo) n2 is
    affine; reflection has m = 0 (has_m False).  ok = False where β2 < 0 on the whole box (total
    internal reflection).  Returns (ok, has_m, d̃2(0), m)."""
    nn = _dot(n[0], n[1], n[2], n[0], n[1], n[2])
    dn = _dot(d[0], d[1], d[2], n[0], n[1], n[2])
    if not refract:
        dt = (lincomb(mul(nn, d[0]), 1.0, mul(dn, n[0]), -2.0), lincomb(mul(nn, d[1]), 1.0, mul(dn, n[1]), -2.0),
              lincomb(mul(nn, d[2]), 1.0, mul(dn, n[2]), -2.0))
        return True, False, dt, n
    e2 = eta_ratio * eta_ratio
    dd = _dot(d[0], d[1], d[2], d[0], d[1], d[2])
    beta = lincomb(mul(nn, dd), 1.0 - e2, mul(dn, dn), e2)
    blo, bhi = coef_range(beta)
    if bhi <= 0.0:
        return False, False, (beta, beta, beta), n
    a, b, dlo, dhi = sqrt_linearisation(blo, bhi)
    r0 = np.empty_like(beta)
    bf = beta.ravel()
    r0f = r0.ravel()
    for i in range(bf.shape[0]):  # aβ + b + δ_lo: adding a constant adds it to every coefficient
        r0f[i] = a * bf[i] + b + dlo
    dt = (lincomb(lincomb(mul(nn, d[0]), eta_ratio, mul(dn, n[0]), -eta_ratio), 1.0, mul(r0, n[0]), -o),
          lincomb(lincomb(mul(nn, d[1]), eta_ratio, mul(dn, n[1]), -eta_ratio), 1.0, mul(r0, n[1]), -o),
          lincomb(lincomb(mul(nn, d[2]), eta_ratio, mul(dn, n[2]), -eta_ratio), 1.0, mul(r0, n[2]), -o))
    s = -o * (dhi - dlo)
    m = (affine_map(n[0], s, 0.0), affine_map(n[1], s, 0.0), affine_map(n[2], s, 0.0))
    return True, True, dt, m


@kernel
def _flat_common(a, b, c, d, e, f):
    """The six polynomials elevated to their common degree and laid out as two flat
    coefficient sets: (a | d), (b | e), (c | f) (the ξ2 = 0 and ξ2 = 1 sets of pu, pv, q)."""
    shape = a.shape
    for k in range(4):
        shape = with_extent(shape, k, max(a.shape[k], b.shape[k], c.shape[k], d.shape[k], e.shape[k], f.shape[k]))
    n = shape[0] * shape[1] * shape[2] * shape[3]
    x = np.empty(2 * n)
    y = np.empty(2 * n)
    z = np.empty(2 * n)
    x[:n] = elevate(a, shape).ravel()
    x[n:] = elevate(d, shape).ravel()
    y[:n] = elevate(b, shape).ravel()
    y[n:] = elevate(e, shape).ravel()
    z[:n] = elevate(c, shape).ravel()
    z[n:] = elevate(f, shape).ravel()
    return x, y, z




@kernel
def _box_bounds(chain_code, x0, P1, N1, P2, N2, Q, UV, alive, eta, lo, hi, out, found, stats):
    """Position bounds of the box lo <= (u1, v1) <= hi for every receiver r with alive[r]
    (the shared steps 1–3 once, then eq 9 and eq 3 per receiver): writes out[r, 0:8] (receiver
    barycentric box, then UV box, padded by POS_PAD) and found[r] (False: the bound misses)."""
    for r in range(Q.shape[0]):
        found[r] = False
    if lo[0] + lo[1] > 1.0:
        return
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    lo4 = np.zeros(4)
    hi4 = np.ones(4)
    lo4[0], lo4[1], hi4[0], hi4[1] = lo[0], lo[1], hi[0], hi[1]
    mask1 = _orientations(x0, P1, N1, lo4, hi4)
    if mask1 == 0:
        return
    fu = np.zeros(4)
    fv = np.zeros(4)
    res = np.zeros(8)
    reached = False
    for v1 in range(2):
        if not (mask1 >> v1) & 1:
            continue
        if not refract1 and v1 == 1 and (mask1 & 1):
            continue  # reflection does not depend on the normal's sign
        o1 = 1.0 if v1 == 0 else -1.0
        if not stage_one(refract1, o1, x0, P1, N1, P2, eta, lo, hi, fu, fv, stats):
            continue
        reached = True
        x, n, d = _vertex_two(P1, P2, N2, fu, fv, lo4, hi4)
        mask2 = _orientations_two(P1, P2, n, lo, hi)
        for v2 in range(2):
            if not (mask2 >> v2) & 1:
                continue
            if not refract2 and v2 == 1 and (mask2 & 1):
                continue
            o2 = 1.0 if v2 == 0 else -1.0
            ok, has_m, dt, m = _directions_two(refract2, o2, ior_ratio(o2, eta), n, d)
            if not ok:
                continue
            for r in range(Q.shape[0]):
                if not alive[r]:
                    continue
                pu0, pv0, q0 = _receiver_numerators(x, dt, Q[r])
                if has_m:  # ξ2 = 1: numerators are linear in the direction
                    mu, mv, mq = _receiver_numerators(x, m, Q[r])
                    pu1, pv1, q1 = add(pu0, mu), add(pv0, mv), add(q0, mq)
                else:
                    pu1, pv1, q1 = pu0, pv0, q0
                fpu, fpv, fq = _flat_common(pu0, pv0, q0, pu1, pv1, q1)
                if not receiver_box(fpu, fpv, fq, UV[r], res):
                    continue
                o = out[r]
                if not found[r]:
                    o[0] = o[2] = o[4] = o[6] = np.inf
                    o[1] = o[3] = o[5] = o[7] = -np.inf
                    found[r] = True
                for k in range(4):
                    o[2 * k] = min(o[2 * k], res[2 * k] - POS_PAD)
                    o[2 * k + 1] = max(o[2 * k + 1], res[2 * k + 1] + POS_PAD)
    if not reached:
        stats[1] += 1


@kernel
def piece_position_two(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, lo, hi, out, stats):
    """Position bound (eq 4–5, 9, 12–13) of the two-bounce piece lo <= (u1, v1) <= hi for one
    receiver triangle Q (3,3) with UV (3,2).

    chain_code: bit 0 set when vertex 1 refracts, bit 1 when vertex 2 refracts ("RR" 0, "TR" 1,
    "RT" 2, "TT" 3).  Writes out[0:8] as ``chain1.piece_position`` (receiver barycentric box,
    then UV box, padded by POS_PAD) and returns False when no admissible path of the piece can
    reach the receiver triangle."""
    res = np.zeros((1, 8))
    found = np.zeros(1, dtype=np.bool_)
    alive = np.ones(1, dtype=np.bool_)
    _box_bounds(chain_code, x0, P1, N1, P2, N2, Q.reshape((1, 3, 3)), UV.reshape((1, 3, 2)), alive, eta, lo, hi, res, found, stats)
    for k in range(8):
        out[k] = res[0, k]
    return found[0]




@kernel
def pair_pieces_two(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, max_depth, sigma, out, stats, reach):
    """Subdivide triangle 1's domain for the pair (triangle 1, triangle 2) and every receiver
    triangle at once (§6.1: split at the midpoint while the position bound's area is >= σ and
    the depth is below the limit; a receiver whose bound misses is dropped from the box and its
    sub-boxes).  Each receiver's pieces are those of its own quadtree: a receiver that stops at
    a box emits its piece there and is not evaluated in the sub-boxes; the shared work of a box
    (vertex 1 -> 2 and d̃2) is done once for all receivers still splitting.

    reach[r]: receiver r's ``addon.solver.bounds.two_bounce_irradiance.receivers_reached`` grid (a box lives for r while
    ``box_reached``).  Writes rows of chain1's P_* layout plus the receiver index in column
    P_RECEIVER (Ē = inf, E̲ = 0) and returns their number; when the rows might not fit, boxes
    stop splitting (stats[3])."""
    nr = Q.shape[0]
    cap = out.shape[0]
    size = 4 * (max_depth + 2)
    stack = np.empty((size, 5))
    alive = np.zeros((size, nr), dtype=np.bool_)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0.0, 1.0, 0.0, 1.0, 0.0
    alive[0, :] = True
    top = 1
    count = 0
    lo = np.zeros(2)
    hi = np.zeros(2)
    pos = np.zeros((nr, 8))
    found = np.zeros(nr, dtype=np.bool_)
    node_alive = np.zeros(nr, dtype=np.bool_)
    child = np.zeros(nr, dtype=np.bool_)
    while top > 0:
        top -= 1
        lo[0], hi[0], lo[1], hi[1] = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        depth = int(stack[top, 4])
        any_alive = False
        for r in range(nr):
            node_alive[r] = alive[top, r] and box_reached(reach[r], lo, hi)
            any_alive = any_alive or node_alive[r]
        if not any_alive:
            continue
        stats[0] += 1
        _box_bounds(chain_code, x0, P1, N1, P2, N2, Q, UV, node_alive, eta, lo, hi, pos, found, stats)
        can_split = depth < max_depth and count + (top + 4) * nr <= cap
        any_child = False
        for r in range(nr):
            child[r] = False
            if not found[r]:
                continue
            area = (pos[r, 1] - pos[r, 0]) * (pos[r, 3] - pos[r, 2])
            if area >= sigma and can_split:
                child[r] = True
                any_child = True
                continue
            if depth < max_depth and area >= sigma:
                stats[3] += 1
            row = out[count]
            row[P_U0], row[P_U1], row[P_V0], row[P_V1] = lo[0], hi[0], lo[1], hi[1]
            for k in range(8):
                row[P_BU0 + k] = pos[r, k]
            row[P_EHI] = np.inf
            row[P_ELO] = 0.0
            row[P_DEPTH] = depth
            row[P_RECEIVER] = r
            count += 1
        if any_child:
            pushed = push_children(stack, top, lo, hi, depth)
            for k in range(top, pushed):
                alive[k] = child
            top = pushed
    return count


@parallel_range("pairs")
def _batch_two(chain_code, x0, P, N, Q, UV, eta, pairs, reach, row_start, max_depth, sigma, rows, counts, stats, first, last):
    for t in range(first, last):
        a = pairs[t, 0]
        b = pairs[t, 1]
        counts[t] = pair_pieces_two(chain_code, x0[t], P[a], N[a], P[b], N[b], Q, UV, eta[t], max_depth, sigma,
                                    rows[row_start[t]:row_start[t + 1]], stats[t], reach[t])


def batch(chain_code, x0, P, N, Q, UV, eta, pairs, reach, per_box, row_start, max_depth, sigma, rows, counts, stats, chunks=256):
    """``two_bounce_position.batch``'s signature; this engine assumes per_box = the receiver count
    (``bound_two_bounce``'s rows) and does not use ``chunks``."""
    _batch_two(chain_code, x0, P, N, Q, UV, eta, pairs, reach, row_start, max_depth, sigma, rows, counts, stats)
