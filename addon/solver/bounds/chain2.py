"""Position bounds of two-bounce chains (RR, RT, TR, TT) from a point light (Fan et al. 2025).

For a tuple (light x0, caster triangle 1, caster triangle 2, receiver triangle k) and a box U1
of triangle 1's barycentrics (u1, v1), a *piece* gets the position bound (eq 4–5): a box of
receiver barycentrics (uk, vk) and of receiver UV coordinates containing the hit point of every
admissible path x0 -> x1 -> x2 -> xk with x1 in U1 (∩ triangle 1) and x2 on triangle 2.

Rational formulation (§4.3) in two stages, every non-rational or high-degree part replaced by
a low-degree expression plus remainder variables (eq 12–13 and the degree reduction of §6.1),
so the bound stays conservative:

1. Vertex 1 -> 2 (exactly the one-bounce formulation of ``chain1``): x1, n1 affine in (u1, v1)
   (eq 6–7), d̃1 from eq 10 (refraction: √β1 -> aβ1 + b + ξ1 remainder, eq 11–13), and
   u2 = pu2/q2, v2 = pv2/q2 by eq 9 with triangle 2 as the "receiver".
2. Degree reduction (§6.1 "Degree reduction", with a linear approximant): u2 = L_u(u1, v1) + r_u
   with L_u the least-squares plane through pu2/q2 on a 3×3 grid of the box and r_u in
   [r_lo, r_hi], the rational Bernstein bound (eq 3) of (pu2 - L_u q2)/q2 over (u1, v1, ξ1);
   the same for v2.  u2 = L_u + r_lo + ξa (r_hi - r_lo), v2 = L_v + r_lo' + ξb (...) with new
   remainder variables ξa, ξb in [0, 1]; this eliminates ξ1, as the paper's reduction does.  When
   q2 can vanish on the box, or the remainder is wider than the clipped bound [u2_lo, u2_hi]
   itself, the constant form u2 = u2_lo + ξa (u2_hi - u2_lo) is used instead (it drops the
   correlation of x2 with x1 that the affine part keeps).
3. Vertex 2 -> receiver: x2, n2 (eq 6–7) and d1 = x2 - x1 (eq 8) are affine in the four
   variables (u1, v1, ξa, ξb); d̃2 from eq 10 (refraction: √β2 -> aβ2 + b + δ with δ spanning
   [δ_lo, δ_hi] through a remainder variable ξ2) and (uk, vk) by eq 9.  The receiver
   coordinates are linear fractional in ξ2 (d̃2 is affine in ξ2 and eq 9 is linear in d̃2), so
   their 5-variable Bernstein coefficients are those at ξ2 = 0 and ξ2 = 1: the bound (eq 3) is
   taken over both coefficient sets together (``rational_bound_pair``), exact for the 5-variable
   polynomial without a fifth array dimension.

Degrees stay at most 6 per variable (TT), far below the ~40 where the paper reduces degree.
The bound converges as U1 shrinks: the remainders of step 2 are O(|U1|²) away from focal points.

Orientation at each vertex follows CONTRACT.md (the light's side of the geometric normal turned
to the shading normal); at vertex 2 the "light" is x1, whose side of triangle 2's plane is
taken over the corners of U1.  η' = 1/η entering the medium (shading normal towards the
incoming light), η leaving it.  The irradiance bound of two-bounce chains is not computed here
(Ē = inf in every piece).
"""

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..jit import kernel, prange
from .bernstein import affine, clip_hull, coef_range, evaluate, lincomb, mul, rational_bound, rational_bound_pair, sqrt_linearisation, sub
from .chain1 import (P_BU0, P_DEPTH, P_EHI, P_ELO, P_U0, P_U1, P_V0, P_V1, P_X0, P_X1, P_Y0, P_Y1, PIECE_FIELDS, POS_PAD, _c3, _caster, _d3, _direction,
                     _dot, _eta_ratio, _orientations, _receiver_numerators)

N_STATS = 4  # position evaluations, stage-1 misses (light of the piece misses triangle 2), constant-form fallbacks, capacity stops


@kernel
def _grid_fit(pu, q):
    """Least-squares plane c + cs (s - ½) + ct (t - ½) through pu/q at the 3×3 grid of local
    coordinates s, t in {0, ½, 1} (ξ1 at ½).  Returns (c, cs, ct)."""
    mean = 0.0
    cs = 0.0
    ct = 0.0
    for i in range(3):
        for j in range(3):
            s = 0.5 * i
            t = 0.5 * j
            f = evaluate(pu, s, t, 0.5, 0.5) / evaluate(q, s, t, 0.5, 0.5)
            mean += f
            cs += (s - 0.5) * f
            ct += (t - 0.5) * f
    # Σ(s-½)² over the grid = 3 · (¼ + 0 + ¼) = 1.5
    return mean / 9.0, cs / 1.5, ct / 1.5


@kernel
def _reduce(p, q, lo4, hi4, clip_lo, clip_hi, form):
    """Affine form with remainder of the coordinate p/q over the box (module doc, step 2).

    Writes form[0:4] = (c, g_u, g_v, g_xi): p/q lies in c + g_u u1 + g_v v1 + g_xi ξ for some ξ
    in [0, 1] (global u1, v1).  Returns True when the linear approximant was used, False for the
    constant form [clip_lo, clip_hi]."""
    qlo, qhi = coef_range(q)
    if qlo > 0.0 or qhi < 0.0:
        c, cs, ct = _grid_fit(p, q)
        wu = hi4[0] - lo4[0]
        wv = hi4[1] - lo4[1]
        gu = cs / wu
        gv = ct / wv
        c0 = c - gu * (lo4[0] + 0.5 * wu) - gv * (lo4[1] + 0.5 * wv)
        g = np.zeros(4)
        g[0] = gu
        g[1] = gv
        lin = affine(c0, g, lo4, hi4)
        a, b, _, _ = rational_bound(sub(p, mul(lin, q)), q)
        # The remainder is the part of u2 that loses its correlation with x1 (the affine part
        # keeps it): prefer the affine form unless its remainder is wider than the whole bound.
        if a <= b and math.isfinite(a) and math.isfinite(b) and math.isfinite(c0) and b - a < clip_hi - clip_lo:
            form[0] = c0 + a
            form[1] = gu
            form[2] = gv
            form[3] = b - a
            return True
    form[0] = clip_lo
    form[1] = 0.0
    form[2] = 0.0
    form[3] = clip_hi - clip_lo
    return False


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
    mask = 0
    if smax > 0.0:  # x1 on ng's side
        if nhi > 0.0:
            mask |= 1
        if nlo < 0.0:
            mask |= 2
    if smin < 0.0:
        if nhi > 0.0:
            mask |= 2
        if nlo < 0.0:
            mask |= 1
    return mask


@kernel
def _directions_two(refract, o, eta_ratio, n, d):
    """d̃2 (eq 10) at ξ2 = 0 and ξ2 = 1 (identical for reflection).  Refraction replaces √β2
    (eq 11) by aβ2 + b + δ, δ in [δ_lo, δ_hi] (eq 12–13).  ok = False where β2 < 0 on the whole
    box (total internal reflection)."""
    nn = _dot(n[0], n[1], n[2], n[0], n[1], n[2])
    dn = _dot(d[0], d[1], d[2], n[0], n[1], n[2])
    if not refract:
        dt = (lincomb(mul(nn, d[0]), 1.0, mul(dn, n[0]), -2.0), lincomb(mul(nn, d[1]), 1.0, mul(dn, n[1]), -2.0),
              lincomb(mul(nn, d[2]), 1.0, mul(dn, n[2]), -2.0))
        return True, dt, dt
    e2 = eta_ratio * eta_ratio
    dd = _dot(d[0], d[1], d[2], d[0], d[1], d[2])
    beta = lincomb(mul(nn, dd), 1.0 - e2, mul(dn, dn), e2)
    blo, bhi = coef_range(beta)
    if bhi <= 0.0:
        return False, (beta, beta, beta), (beta, beta, beta)
    a, b, dlo, dhi = sqrt_linearisation(blo, bhi)
    base = (lincomb(mul(nn, d[0]), eta_ratio, mul(dn, n[0]), -eta_ratio),
            lincomb(mul(nn, d[1]), eta_ratio, mul(dn, n[1]), -eta_ratio),
            lincomb(mul(nn, d[2]), eta_ratio, mul(dn, n[2]), -eta_ratio))
    r0 = np.empty_like(beta)
    r1 = np.empty_like(beta)
    bf = beta.ravel()
    r0f = r0.ravel()
    r1f = r1.ravel()
    for i in range(bf.shape[0]):  # aβ + b + δ: adding a constant adds it to every coefficient
        r0f[i] = a * bf[i] + b + dlo
        r1f[i] = a * bf[i] + b + dhi
    d0 = (lincomb(base[0], 1.0, mul(r0, n[0]), -o), lincomb(base[1], 1.0, mul(r0, n[1]), -o),
          lincomb(base[2], 1.0, mul(r0, n[2]), -o))
    d1 = (lincomb(base[0], 1.0, mul(r1, n[0]), -o), lincomb(base[1], 1.0, mul(r1, n[1]), -o),
          lincomb(base[2], 1.0, mul(r1, n[2]), -o))
    return True, d0, d1


@kernel
def _stage_one(refract1, o1, x0, P1, N1, P2, eta, lo, hi, fu, fv, stats):
    """Steps 1–2 of the module doc for orientation o1 at vertex 1: the affine forms with
    remainder of (u2, v2) in fu, fv.  Returns False when the light of the box misses triangle 2."""
    lo4 = np.zeros(4)
    hi4 = np.ones(4)
    lo4[0], lo4[1], hi4[0], hi4[1] = lo[0], lo[1], hi[0], hi[1]
    x, n, d = _caster(x0, P1, N1, lo4, hi4)
    ok, dt = _direction(refract1, o1, _eta_ratio(o1, eta), n, d, lo4, hi4)
    if not ok:
        return False
    pu, pv, q = _receiver_numerators(x, dt, P2)
    a, b, c, e = rational_bound(pu, q)
    ulo, uhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if ulo > uhi:
        return False
    a, b, c, e = rational_bound(pv, q)
    vlo, vhi = clip_hull(a, b, c, e, 0.0, 1.0)
    if vlo > vhi or ulo + vlo > 1.0:
        return False
    w = lincomb(lincomb(q, 1.0, pu, -1.0), 1.0, pv, -1.0)
    a, b, c, e = rational_bound(w, q)
    wlo, whi = clip_hull(a, b, c, e, 0.0, 1.0)
    if wlo > whi:
        return False
    uhi = min(uhi, 1.0 - vlo - wlo)
    vhi = min(vhi, 1.0 - ulo - wlo)
    if not _reduce(pu, q, lo4, hi4, ulo, uhi, fu):
        stats[2] += 1
    if not _reduce(pv, q, lo4, hi4, vlo, vhi, fv):
        stats[2] += 1
    return True


@kernel
def piece_position_two(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, lo, hi, out, stats):
    """Position bound (eq 4–5, 9, 12–13) of the two-bounce piece lo <= (u1, v1) <= hi.

    chain_code: bit 0 set when vertex 1 refracts, bit 1 when vertex 2 refracts ("RR" 0, "TR" 1,
    "RT" 2, "TT" 3).  Writes out[0:8] as ``chain1.piece_position`` (receiver barycentric box,
    then UV box, padded by POS_PAD) and returns False when no admissible path of the piece can
    reach the receiver triangle."""
    if lo[0] + lo[1] > 1.0:
        return False
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    lo4 = np.zeros(4)
    hi4 = np.ones(4)
    lo4[0], lo4[1], hi4[0], hi4[1] = lo[0], lo[1], hi[0], hi[1]
    mask1 = _orientations(x0, P1, N1, lo4, hi4)
    if mask1 == 0:
        return False
    bu0 = np.inf
    bu1 = -np.inf
    bv0 = np.inf
    bv1 = -np.inf
    X0 = np.inf
    X1 = -np.inf
    Y0 = np.inf
    Y1 = -np.inf
    uvlo_x = min(UV[0, 0], UV[1, 0], UV[2, 0])
    uvhi_x = max(UV[0, 0], UV[1, 0], UV[2, 0])
    uvlo_y = min(UV[0, 1], UV[1, 1], UV[2, 1])
    uvhi_y = max(UV[0, 1], UV[1, 1], UV[2, 1])
    fu = np.zeros(4)
    fv = np.zeros(4)
    reached = False
    for v1 in range(2):
        if not (mask1 >> v1) & 1:
            continue
        if not refract1 and v1 == 1 and (mask1 & 1):
            continue  # reflection does not depend on the normal's sign
        o1 = 1.0 if v1 == 0 else -1.0
        if not _stage_one(refract1, o1, x0, P1, N1, P2, eta, lo, hi, fu, fv, stats):
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
            ok, dA, dB = _directions_two(refract2, o2, _eta_ratio(o2, eta), n, d)
            if not ok:
                continue
            pu0, pv0, q0 = _receiver_numerators(x, dA, Q)
            pu1, pv1, q1 = _receiver_numerators(x, dB, Q)
            a, b, c, e = rational_bound_pair(pu0, q0, pu1, q1)
            ulo, uhi = clip_hull(a, b, c, e, 0.0, 1.0)
            if ulo > uhi:
                continue
            a, b, c, e = rational_bound_pair(pv0, q0, pv1, q1)
            vlo, vhi = clip_hull(a, b, c, e, 0.0, 1.0)
            if vlo > vhi or ulo + vlo > 1.0:
                continue
            w0 = lincomb(lincomb(q0, 1.0, pu0, -1.0), 1.0, pv0, -1.0)
            w1 = lincomb(lincomb(q1, 1.0, pu1, -1.0), 1.0, pv1, -1.0)
            a, b, c, e = rational_bound_pair(w0, q0, w1, q1)
            wlo, whi = clip_hull(a, b, c, e, 0.0, 1.0)
            if wlo > whi:
                continue
            uhi = min(uhi, 1.0 - vlo - wlo)
            vhi = min(vhi, 1.0 - ulo - wlo)
            t0 = lincomb(lincomb(q0, UV[0, 0], pu0, UV[1, 0] - UV[0, 0]), 1.0, pv0, UV[2, 0] - UV[0, 0])
            t1 = lincomb(lincomb(q1, UV[0, 0], pu1, UV[1, 0] - UV[0, 0]), 1.0, pv1, UV[2, 0] - UV[0, 0])
            a, b, c, e = rational_bound_pair(t0, q0, t1, q1)
            xlo, xhi = clip_hull(a, b, c, e, uvlo_x, uvhi_x)
            t0 = lincomb(lincomb(q0, UV[0, 1], pu0, UV[1, 1] - UV[0, 1]), 1.0, pv0, UV[2, 1] - UV[0, 1])
            t1 = lincomb(lincomb(q1, UV[0, 1], pu1, UV[1, 1] - UV[0, 1]), 1.0, pv1, UV[2, 1] - UV[0, 1])
            a, b, c, e = rational_bound_pair(t0, q0, t1, q1)
            ylo, yhi = clip_hull(a, b, c, e, uvlo_y, uvhi_y)
            if xlo > xhi or ylo > yhi:
                continue
            bu0, bu1, bv0, bv1 = min(bu0, ulo), max(bu1, uhi), min(bv0, vlo), max(bv1, vhi)
            X0, X1, Y0, Y1 = min(X0, xlo), max(X1, xhi), min(Y0, ylo), max(Y1, yhi)
    if not reached:
        stats[1] += 1
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
def tuple_pieces_two(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, max_depth, sigma, out, stats):
    """Subdivide triangle 1's domain of one two-bounce tuple (§6.1: split at the midpoint while
    the position bound's area is >= σ and the depth is below the limit; pieces whose bound misses
    the receiver are dropped).  Writes up to out.shape[0] rows (chain1's P_* layout, Ē = inf,
    E̲ = 0) and returns their number; a full buffer stops splitting (stats[3])."""
    cap = out.shape[0]
    stack = np.empty((4 * (max_depth + 2), 5))
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
        if not piece_position_two(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, lo, hi, pos, stats):
            continue
        area = (pos[1] - pos[0]) * (pos[3] - pos[2])
        can_split = depth < max_depth and count + top + 4 <= cap
        if area >= sigma and can_split:
            um = 0.5 * (lo[0] + hi[0])
            vm = 0.5 * (lo[1] + hi[1])
            for k in range(4):
                a0 = lo[0] if k & 1 == 0 else um
                a1 = um if k & 1 == 0 else hi[0]
                b0 = lo[1] if k & 2 == 0 else vm
                b1 = vm if k & 2 == 0 else hi[1]
                if a0 + b0 < 1.0:
                    stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3], stack[top, 4] = a0, a1, b0, b1, depth + 1
                    top += 1
            continue
        if depth < max_depth and area >= sigma:
            stats[3] += 1
        row = out[count]
        row[P_U0], row[P_U1], row[P_V0], row[P_V1] = lo[0], hi[0], lo[1], hi[1]
        for k in range(8):
            row[P_BU0 + k] = pos[k]
        row[P_EHI] = np.inf
        row[P_ELO] = 0.0
        row[P_DEPTH] = depth
        count += 1
    return count


@kernel(parallel=True)
def _batch_two(chain_code, x0, P, N, Q, UV, eta, triples, max_depth, sigma, out, counts, stats):
    for t in prange(triples.shape[0]):
        a = triples[t, 0]
        b = triples[t, 1]
        r = triples[t, 2]
        counts[t] = tuple_pieces_two(chain_code, x0, P[a], N[a], P[b], N[b], Q[r], UV[r], eta, max_depth, sigma, out[t], stats[t])


CHAIN_CODES = {"RR": 0, "TR": 1, "RT": 2, "TT": 3}


@dataclass
class TwoBounceBounds:
    """Result of :func:`bound_two_bounce`.

    tuples: (m, 3) int64 (triangle 1, triangle 2, receiver) of the tuples with at least one piece;
    piece_tuple, pieces, tuple_uv_box as ``chain1.OneBounceBounds`` (Ē = inf: no irradiance bound)."""

    chain: str
    tuples: np.ndarray
    piece_tuple: np.ndarray
    pieces: np.ndarray
    tuple_uv_box: np.ndarray
    report: dict = field(default_factory=dict)


def bound_two_bounce(chain, light, caster_P, caster_N, receiver_P, receiver_UV, eta=1.5, triples=None, max_depth=1,
                     sigma=1e-4, capacity=16):
    """Position bounds of two-bounce tuples (Fan et al. 2025 §4.2–4.3, eq 3–13; subdivision §6.1).

    chain: "RR", "RT", "TR" or "TT"; caster_P, caster_N: (n,3,3) corners and corner normals of
    the specular triangles (both vertices index into them); receiver_P (r,3,3), receiver_UV
    (r,3,2); eta: IOR behind the caster surfaces (normals point away from it);
    triples: (t,3) candidate (triangle 1, triangle 2, receiver) indices (default: every pair of
    distinct casters from :func:`..tuples.two_bounce_pairs` is up to the caller — here all n·(n-1)·r,
    only sensible for tiny meshes); max_depth, sigma: the stopping rules; capacity: most pieces
    per tuple."""
    if chain not in CHAIN_CODES:
        raise ValueError(f"bound_two_bounce handles chains RR, RT, TR and TT, got {chain!r}")
    t0 = time.perf_counter()
    light = np.ascontiguousarray(light, dtype=np.float64).reshape(3)
    caster_P = np.ascontiguousarray(caster_P, dtype=np.float64)
    caster_N = np.ascontiguousarray(caster_N, dtype=np.float64)
    receiver_P = np.ascontiguousarray(receiver_P, dtype=np.float64)
    receiver_UV = np.ascontiguousarray(receiver_UV, dtype=np.float64)
    if triples is None:
        n = caster_P.shape[0]
        a, b, r = np.meshgrid(np.arange(n), np.arange(n), np.arange(receiver_P.shape[0]), indexing="ij")
        keep = (a != b).ravel()
        triples = np.stack([a.ravel()[keep], b.ravel()[keep], r.ravel()[keep]], axis=1)
    triples = np.ascontiguousarray(triples, dtype=np.int64).reshape(-1, 3)
    n = triples.shape[0]
    capacity = max(1, min(int(capacity), 4 ** int(max_depth)))
    out = np.empty((n, capacity, PIECE_FIELDS))
    counts = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, N_STATS), dtype=np.int64)
    t1 = time.perf_counter()
    if n:
        _batch_two(CHAIN_CODES[chain], light, caster_P, caster_N, receiver_P, receiver_UV, float(eta), triples,
                   int(max_depth), float(sigma), out, counts, stats)
    t2 = time.perf_counter()
    keep = np.flatnonzero(counts > 0)
    kept = counts[keep]
    piece_tuple = np.repeat(np.arange(keep.shape[0]), kept)
    slot = np.arange(piece_tuple.shape[0]) - np.repeat(np.cumsum(kept) - kept, kept)
    pieces = out[keep[piece_tuple], slot] if piece_tuple.shape[0] else np.empty((0, PIECE_FIELDS))
    del out
    m = keep.shape[0]
    box = np.empty((m, 4))
    if m:
        starts = np.cumsum(kept) - kept
        box[:, 0] = np.minimum.reduceat(pieces[:, P_X0], starts)
        box[:, 1] = np.maximum.reduceat(pieces[:, P_X1], starts)
        box[:, 2] = np.minimum.reduceat(pieces[:, P_Y0], starts)
        box[:, 3] = np.maximum.reduceat(pieces[:, P_Y1], starts)
    t3 = time.perf_counter()
    total = stats.sum(axis=0)
    report = {
        "tuples_tried": int(n), "tuples": int(m), "pieces": int(pieces.shape[0]),
        "pieces_per_tuple": float(pieces.shape[0] / m) if m else 0.0,
        "position_evaluations": int(total[0]), "stage_one_misses": int(total[1]), "constant_forms": int(total[2]),
        "capacity_stops": int(total[3]),
        "memory_mb": (pieces.nbytes + box.nbytes + piece_tuple.nbytes) / 2**20,
        "seconds": {"prepare": t1 - t0, "bound": t2 - t1, "compact": t3 - t2},
    }
    return TwoBounceBounds(chain, triples[keep], piece_tuple, pieces, box, report)
