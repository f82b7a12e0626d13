"""Two-bounce position bounds (Fan et al. 2025 §4.2–4.3, eq 3–13; §6.1): the production engine.

The readable reference engine, whose module doc this follows step by step, is
tests/reference/bounds_two_bounce.py; this engine computes the same bounds without allocation
per box and with the receiver-independent work done once per box.  Steps 1–2 (vertex 1 ->
triangle 2 and the affine forms with remainder of (u2, v2)) are :func:`stage_one`, shared with
the reference, so the forms are bit-identical.  Step 3 (vertex 2 -> the receivers) runs on a
per-thread workspace.

Representation (as ``slot_algebra``): a polynomial is a row ("slot") of the workspace W holding
its *scaled* Bernstein coefficients c_i = b_i Π C(n_d, i_d) in C order, its extents (degree + 1
per variable) in the matching row of E.  In scaled form the Bernstein product is a plain
convolution (Farouki 2012), degree elevation by r a convolution with the binomial row C(r, ·)
per variable, and eq 3 applies to scaled coefficients of one degree directly (c_i(p)/c_i(q) =
b_i(p)/b_i(q)); coefficient *values* (the range of β2 for eq 12–13) divide by the binomials.
Degrees follow the reference exactly (an affine polynomial has degree 0 in a variable whose
gradient component is 0, products add degrees, sums take the larger), so eq 3 sees the
reference's coefficient sets, up to rounding.

Work shared by re-association (the same polynomials, other rounding):

* eq 9 for a receiver Q is pu = ek2·G - d̃·(ek2 × (Q0 - O)), pv = -ek1·G + d̃·(ek1 × (Q0 - O)),
  q = d̃·(ek2 × ek1) with G = (x2 - O) × d̃ (the reference's (d̃ × ek2)·(x2 - Q0),
  ((x2 - Q0) × ek1)·d̃, (d̃ × ek2)·ek1 as scalar triple products): the products G are formed once
  per box and direction, each receiver costs linear combinations.  O is the first receiver's
  first corner, so x2 - O is no larger than the reference's x2 - Q0.
* ξ2 = 1: d̃2 + s n2 (eq 12–13, s = -o (δ_hi - δ_lo)) has G + s H with H = (x2 - O) × n2.
* d̃2 = η' nn d1 + K n2 with K = -(η' dn + o (aβ2 + b + δ_lo)) (eq 10 with eq 12).
* When q has one sign, eq 3 of uk, vk, 1 - uk - vk and the UV coordinates (all affine in uk, vk)
  is read from the quotients pu/q and pv/q, formed once.

Results equal the reference's up to rounding (about 1e-13 on the slab and ball meshes), except
where rounding flips the sign of a near-zero numerator coefficient in eq 3's reciprocal case:
then one of the two engines returns the unbounded (clipped, wider) interval.
"""

import numpy as np

from ..runtime.jit import kernel, run_chunks
from ..polynomials.bernstein import BINOM, clip_hull, sqrt_linearisation
from .layout import (P_BU0, P_DEPTH, P_EHI, P_ELO, P_RECEIVER, P_U0, P_U1, P_V0, P_V1, POS_PAD, ior_ratio, orientation_mask,
                     push_children)
from .slot_algebra import ratio_bound
from .two_bounce_irradiance import box_reached, first_bounce_forms

MAXC4 = 7 * 7 * 7 * 7  # largest polynomial: the vertex-2 numerators, degree 6 in each of (u1, v1, ξa, ξb)
WIDTH = 2 * MAXC4      # slot width: the two coefficient sets (ξ2 = 0 and 1) of one receiver numerator

# slots of W / E (np.int64, not Python ints: numba would compile a callee once per literal slot number)
_i = np.int64
S_T = _i(0)                                   # 0..7 scratch
S2_X, S2_N, S2_D = _i(8), _i(11), _i(14)      # vertex 2: x2 - O, n2, d1 (eq 6–8) in (u1, v1, ξa, ξb)
S2_DT, S2_G, S2_H = _i(17), _i(20), _i(23)    # d̃2 at ξ2 = 0, G = (x2 - O) × d̃2, H = (x2 - O) × n2
S2_DTC, S2_GC = _i(26), _i(29)                # d̃2 and G at the common degree of the receiver numerators
S2_DT1, S2_G1 = _i(32), _i(35)                # the same at ξ2 = 1: d̃2 + s n2 and G + s H
S_NN, S_DN, S_DD, S_BETA, S_R0, S_K, S_NN5 = _i(38), _i(39), _i(40), _i(41), _i(42), _i(43), _i(44)
S_FPU, S_FPV, S_FQ = _i(45), _i(46), _i(47)   # receiver numerators, both ξ2 sets end to end
S_BU, S_BV = _i(48), _i(49)                   # quotients pu/q, pv/q
N_SLOTS = 50
ZERO = _i(0)


@kernel
def workspace():
    """W (slots × WIDTH, zero: the padding invariant below) and E (the extents of each slot)."""
    return np.zeros((N_SLOTS, WIDTH)), np.zeros((N_SLOTS, 4), dtype=np.int64)


# ---------------------------------------------------------------------------------------
# slot arithmetic (scaled Bernstein form, padded layout)
#
# Coefficient (i0, i1, i2, i3) of a slot lies at i0·343 + i1·49 + i2·7 + i3 whatever the
# extents (each <= 7), and every entry outside the extents is 0.  A product term is then one
# shifted axpy over the whole array and an elevation step a sum of shifted copies: long
# vectorisable loops instead of loops over short rows.

STRIDES = (343, 49, 7, 1)


@kernel(inline="always")
def _ext(E, s):
    return (E[s, 0], E[s, 1], E[s, 2], E[s, 3])


@kernel(inline="always")
def _set_ext(E, s, e):
    E[s, 0] = e[0]
    E[s, 1] = e[1]
    E[s, 2] = e[2]
    E[s, 3] = e[3]


@kernel(inline="always")
def _count(e):
    return e[0] * e[1] * e[2] * e[3]


@kernel(inline="always")
def _span(e):
    """One past the padded index of the last coefficient (0 for an empty slot)."""
    if e[0] == 0:
        return 0
    return (e[0] - 1) * 343 + (e[1] - 1) * 49 + (e[2] - 1) * 7 + e[3]


@kernel(inline="always")
def _emax(a, b):
    return (max(a[0], b[0]), max(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))


@kernel
def _zero(W, E, o, e):
    """Slot o = 0 with extents e (clears what the old extents used)."""
    out = W[o]
    for i in range(_span(_emax(_ext(E, o), e))):
        out[i] = 0.0
    _set_ext(E, o, e)


@kernel
def _set_affine(W, E, s, c, g0, g1, g2, g3, lo, hi):
    """Slot s = c + Σ g_j x_j on the box lo <= x <= hi (``bernstein.affine``: degree 1 in the
    variables with g_j != 0, coefficients = corner values, summed in the same order)."""
    n0 = 2 if g0 != 0.0 else 1
    n1 = 2 if g1 != 0.0 else 1
    n2 = 2 if g2 != 0.0 else 1
    n3 = 2 if g3 != 0.0 else 1
    _zero(W, E, s, (n0, n1, n2, n3))
    out = W[s]
    for i0 in range(n0):
        for i1 in range(n1):
            for i2 in range(n2):
                for i3 in range(n3):
                    out[i0 * 343 + i1 * 49 + i2 * 7 + i3] = (c + g0 * (hi[0] if i0 else lo[0]) + g1 * (hi[1] if i1 else lo[1])
                                                             + g2 * (hi[2] if i2 else lo[2]) + g3 * (hi[3] if i3 else lo[3]))


@kernel
def _elevate_step(src, dst, n, stride, r):
    """dst[k] = Σ_t C(r, t) src[k - t·stride] for k < n: variable with this stride elevated by r
    (scaled form).  The padding makes the shifted reads land on zeros where they cross rows."""
    for k in range(n):
        dst[k] = src[k]
    for t in range(1, r + 1):
        w = BINOM[r, t]
        off = t * stride
        for k in range(off, n):
            dst[k] += w * src[k - off]


@kernel
def _elevate(W, E, a, et, o, t):
    """Slot o = slot a elevated to extents et (each >= a's); t is scratch (o, t != a)."""
    ea = _ext(E, a)
    k = 0
    for d in range(4):
        if et[d] > ea[d]:
            k += 1
    n = _span(et)
    _zero(W, E, o, et)
    if k == 0:
        src = W[a]
        dst = W[o]
        for i in range(n):
            dst[i] = src[i]
        return
    _zero(W, E, t, et)
    src = a
    dst = o if k % 2 == 1 else t  # ping-pong so that the last pass writes o
    cur = ea
    for d in range(3, -1, -1):  # last variable first: the early passes cover short spans
        if et[d] > cur[d]:
            cur = (et[0] if d == 0 else cur[0], et[1] if d == 1 else cur[1], et[2] if d == 2 else cur[2],
                   et[3] if d == 3 else cur[3])
            _elevate_step(W[src], W[dst], _span(cur), STRIDES[d], et[d] - ea[d])
            src = dst
            dst = t if dst == o else o


@kernel
def _acc(W, E, s, a, o, t1, t2):
    """Slot o += s · (slot a elevated to o's extents); t1, t2 scratch."""
    eo = _ext(E, o)
    ea = _ext(E, a)
    src = W[a]
    if ea[0] != eo[0] or ea[1] != eo[1] or ea[2] != eo[2] or ea[3] != eo[3]:
        _elevate(W, E, a, eo, t1, t2)
        src = W[t1]
    out = W[o]
    for i in range(_span(eo)):
        out[i] += s * src[i]


@kernel
def _conv_acc(W, E, s, a, b, o):
    """Slot o += s · (a b), o at the product's extents.  Scaled Bernstein: a convolution; in the
    padded layout one shifted axpy of the larger factor per coefficient of the smaller one."""
    ea = _ext(E, a)
    eb = _ext(E, b)
    if _count(ea) < _count(eb):
        a, b = b, a
        ea, eb = eb, ea
    A = W[a]
    B = W[b]
    O = W[o]
    n = _span(ea)
    sparse = n > 3 * _count(ea)  # mostly padding (degree 2 in every variable): row by row
    for j0 in range(eb[0]):
        for j1 in range(eb[1]):
            for j2 in range(eb[2]):
                for j3 in range(eb[3]):
                    off = j0 * 343 + j1 * 49 + j2 * 7 + j3
                    w = s * B[off]
                    if w == 0.0:
                        continue
                    if sparse:
                        for i0 in range(ea[0]):
                            for i1 in range(ea[1]):
                                for i2 in range(ea[2]):
                                    base = i0 * 343 + i1 * 49 + i2 * 7
                                    for i3 in range(ea[3]):
                                        O[off + base + i3] += w * A[base + i3]
                    else:
                        for k in range(n):
                            O[off + k] += w * A[k]


@kernel(inline="always")
def _product_ext(ea, eb):
    return (ea[0] + eb[0] - 1, ea[1] + eb[1] - 1, ea[2] + eb[2] - 1, ea[3] + eb[3] - 1)


@kernel
def _mul_acc(W, E, s, a, b, o, t1, t2, t3):
    """Slot o += s · (a b), the product elevated to o's extents where they are higher
    (t1, t2, t3 scratch)."""
    ep = _product_ext(_ext(E, a), _ext(E, b))
    eo = _ext(E, o)
    if ep[0] == eo[0] and ep[1] == eo[1] and ep[2] == eo[2] and ep[3] == eo[3]:
        _conv_acc(W, E, s, a, b, o)
        return
    _zero(W, E, t3, ep)
    _conv_acc(W, E, 1.0, a, b, t3)
    _acc(W, E, s, t3, o, t1, t2)


@kernel
def _mul(W, E, a, b, o):
    """Slot o = a b."""
    _zero(W, E, o, _product_ext(_ext(E, a), _ext(E, b)))
    _conv_acc(W, E, 1.0, a, b, o)


@kernel
def _dot3(W, E, a, b, o):
    """Slot o = Σ_i a_i b_i for slot triples a.., b.. (S_T..S_T+2 scratch)."""
    e = _product_ext(_ext(E, a), _ext(E, b))
    e = _emax(e, _product_ext(_ext(E, a + 1), _ext(E, b + 1)))
    e = _emax(e, _product_ext(_ext(E, a + 2), _ext(E, b + 2)))
    _zero(W, E, o, e)
    for i in range(3):
        _mul_acc(W, E, 1.0, a + i, b + i, o, S_T, S_T + 1, S_T + 2)


@kernel
def _cross3(W, E, a, b, o):
    """Slots o.. = a × b for slot triples (S_T..S_T+2 scratch)."""
    for k in range(3):
        i = (k + 1) % 3
        j = (k + 2) % 3
        _zero(W, E, o + k, _emax(_product_ext(_ext(E, a + i), _ext(E, b + j)), _product_ext(_ext(E, a + j), _ext(E, b + i))))
        _mul_acc(W, E, 1.0, a + i, b + j, o + k, S_T, S_T + 1, S_T + 2)
        _mul_acc(W, E, -1.0, a + j, b + i, o + k, S_T, S_T + 1, S_T + 2)


@kernel
def _value_range(W, E, s):
    """(min, max) of the plain Bernstein coefficients of slot s (eq 3 with q = 1)."""
    e = _ext(E, s)
    a = W[s]
    lo = np.inf
    hi = -np.inf
    for i0 in range(e[0]):
        for i1 in range(e[1]):
            for i2 in range(e[2]):
                w = BINOM[e[0] - 1, i0] * BINOM[e[1] - 1, i1] * BINOM[e[2] - 1, i2]
                k = i0 * 343 + i1 * 49 + i2 * 7
                for i3 in range(e[3]):
                    v = a[k + i3] / (w * BINOM[e[3] - 1, i3])
                    lo = min(lo, v)
                    hi = max(hi, v)
    return lo, hi


@kernel
def _add_constant(W, E, s, c):
    """Slot s += c (a constant's scaled coefficients are c Π C(n_d, i_d))."""
    e = _ext(E, s)
    a = W[s]
    for i0 in range(e[0]):
        for i1 in range(e[1]):
            for i2 in range(e[2]):
                w = c * BINOM[e[0] - 1, i0] * BINOM[e[1] - 1, i1] * BINOM[e[2] - 1, i2]
                k = i0 * 343 + i1 * 49 + i2 * 7
                for i3 in range(e[3]):
                    a[k + i3] += w * BINOM[e[3] - 1, i3]


# ---------------------------------------------------------------------------------------
# geometry: orientations (CONTRACT.md), vertex 1 and vertex 2

@kernel
def _orientations_one(x0, P, N, lo, hi):
    """The reference engine's ``_orientations`` on the box (same arithmetic on the four corner coefficients)."""
    e1 = P[1] - P[0]
    e2 = P[2] - P[0]
    ng0 = e1[1] * e2[2] - e1[2] * e2[1]
    ng1 = e1[2] * e2[0] - e1[0] * e2[2]
    ng2 = e1[0] * e2[1] - e1[1] * e2[0]
    side = (x0[0] - P[0, 0]) * ng0 + (x0[1] - P[0, 1]) * ng1 + (x0[2] - P[0, 2]) * ng2
    if side == 0.0:
        return 0
    nlo = np.inf
    nhi = -np.inf
    for k in range(4):
        u = hi[0] if k & 2 else lo[0]
        v = hi[1] if k & 1 else lo[1]
        n0 = N[0, 0] + (N[1, 0] - N[0, 0]) * u + (N[2, 0] - N[0, 0]) * v + 0.0 * lo[2] + 0.0 * lo[3]
        n1 = N[0, 1] + (N[1, 1] - N[0, 1]) * u + (N[2, 1] - N[0, 1]) * v + 0.0 * lo[2] + 0.0 * lo[3]
        n2 = N[0, 2] + (N[1, 2] - N[0, 2]) * u + (N[2, 2] - N[0, 2]) * v + 0.0 * lo[2] + 0.0 * lo[3]
        t = 1.0 * (ng0 * n0 + ng1 * n1) + ng2 * n2
        nlo = min(nlo, t)
        nhi = max(nhi, t)
    mask = 0
    s = 1.0 if side > 0.0 else -1.0
    if nhi > 0.0:
        mask |= 1 if s > 0.0 else 2
    if nlo < 0.0:
        mask |= 2 if s > 0.0 else 1
    return mask


@kernel
def _numerators(W, E, dtc, g, origin, Q, pu, pv, q, off):
    """eq 9 for the receiver triangle Q from G = (x - O) × d̃ (slots g..) and d̃ (slots dtc..), all
    at one degree: pu = ek2·G - d̃·(ek2 × (Q0 - O)), pv = -ek1·G + d̃·(ek1 × (Q0 - O)),
    q = d̃·(ek2 × ek1), the reference's (d̃ × ek2)·(x - Q0), ((x - Q0) × ek1)·d̃ and (d̃ × ek2)·ek1
    (scalar triple products), into slots pu, pv, q densely (C order) from index off on."""
    ek1 = Q[1] - Q[0]
    ek2 = Q[2] - Q[0]
    r0 = Q[0, 0] - origin[0]
    r1 = Q[0, 1] - origin[1]
    r2 = Q[0, 2] - origin[2]
    a0 = ek2[1] * r2 - ek2[2] * r1
    a1 = ek2[2] * r0 - ek2[0] * r2
    a2 = ek2[0] * r1 - ek2[1] * r0
    b0 = ek1[1] * r2 - ek1[2] * r1
    b1 = ek1[2] * r0 - ek1[0] * r2
    b2 = ek1[0] * r1 - ek1[1] * r0
    c0 = ek2[1] * ek1[2] - ek2[2] * ek1[1]
    c1 = ek2[2] * ek1[0] - ek2[0] * ek1[2]
    c2 = ek2[0] * ek1[1] - ek2[1] * ek1[0]
    e = _ext(E, g)
    G0 = W[g]
    G1 = W[g + 1]
    G2 = W[g + 2]
    T0 = W[dtc]
    T1 = W[dtc + 1]
    T2 = W[dtc + 2]
    PU = W[pu]
    PV = W[pv]
    QQ = W[q]
    o = off
    for i0 in range(e[0]):  # padded operands -> coefficient sets laid out densely for eq 3
        for i1 in range(e[1]):
            for i2 in range(e[2]):
                base = i0 * 343 + i1 * 49 + i2 * 7
                for i3 in range(e[3]):
                    k = base + i3
                    PU[o] = ek2[0] * G0[k] + ek2[1] * G1[k] + ek2[2] * G2[k] - (a0 * T0[k] + a1 * T1[k] + a2 * T2[k])
                    PV[o] = -(ek1[0] * G0[k] + ek1[1] * G1[k] + ek1[2] * G2[k]) + (b0 * T0[k] + b1 * T1[k] + b2 * T2[k])
                    QQ[o] = c0 * T0[k] + c1 * T1[k] + c2 * T2[k]
                    o += 1


@kernel(error_model="numpy")
def _quotients(p, q, n, out):
    for k in range(n):
        out[k] = p[k] / q[k]


@kernel
def _one_signed(a, n):
    npos = 0
    nneg = 0
    for k in range(n):
        v = a[k]
        npos += 1 if v > 0.0 else 0
        nneg += 1 if v < 0.0 else 0
    return npos == n or nneg == n


@kernel
def _receiver_bound(W, pu, pv, q, n, UV, res):
    """The reference engine's ``receiver_box`` on the coefficient sets W[pu][:n], W[pv][:n], W[q][:n] of one degree.  When q has one sign, eq 3 of uk = pu/q,
    vk = pv/q, 1 - uk - vk and of the UV coordinates (affine in uk, vk) is read from the
    quotients pu/q and pv/q; otherwise each numerator goes through ``ratio_bound`` (the
    reciprocal and unbounded cases of §4.1)."""
    P = W[pu]
    V = W[pv]
    Q = W[q]
    BU = W[S_BU]
    BV = W[S_BV]
    cx0 = UV[0, 0]
    cx1 = UV[1, 0] - UV[0, 0]
    cx2 = UV[2, 0] - UV[0, 0]
    cy0 = UV[0, 1]
    cy1 = UV[1, 1] - UV[0, 1]
    cy2 = UV[2, 1] - UV[0, 1]
    inf = np.inf
    if _one_signed(Q, n):
        _quotients(P, Q, n, BU)
        _quotients(V, Q, n, BV)
        ulo = vlo = wlo = xlo = ylo = inf
        uhi = vhi = whi = xhi = yhi = -inf
        for k in range(n):
            u = BU[k]
            v = BV[k]
            w = 1.0 - u - v
            ulo = min(ulo, u)
            uhi = max(uhi, u)
            vlo = min(vlo, v)
            vhi = max(vhi, v)
            wlo = min(wlo, w)
            whi = max(whi, w)
            x = cx0 + cx1 * u + cx2 * v
            y = cy0 + cy1 * u + cy2 * v
            xlo = min(xlo, x)
            xhi = max(xhi, x)
            ylo = min(ylo, y)
            yhi = max(yhi, y)
        u2lo = v2lo = w2lo = x2lo = y2lo = inf
        u2hi = v2hi = w2hi = x2hi = y2hi = -inf
    else:
        T = W[S_BV]
        ulo, uhi, u2lo, u2hi = ratio_bound(P, Q, n, BU)
        vlo, vhi, v2lo, v2hi = ratio_bound(V, Q, n, BU)
        for k in range(n):
            T[k] = Q[k] - P[k] - V[k]
        wlo, whi, w2lo, w2hi = ratio_bound(T, Q, n, BU)
        for k in range(n):
            T[k] = cx0 * Q[k] + cx1 * P[k] + cx2 * V[k]
        xlo, xhi, x2lo, x2hi = ratio_bound(T, Q, n, BU)
        for k in range(n):
            T[k] = cy0 * Q[k] + cy1 * P[k] + cy2 * V[k]
        ylo, yhi, y2lo, y2hi = ratio_bound(T, Q, n, BU)
    ulo, uhi = clip_hull(ulo, uhi, u2lo, u2hi, 0.0, 1.0)
    if ulo > uhi:
        return False
    vlo, vhi = clip_hull(vlo, vhi, v2lo, v2hi, 0.0, 1.0)
    if vlo > vhi or ulo + vlo > 1.0:
        return False
    wlo, whi = clip_hull(wlo, whi, w2lo, w2hi, 0.0, 1.0)
    if wlo > whi:
        return False
    res[0] = ulo
    res[1] = min(uhi, 1.0 - vlo - wlo)
    res[2] = vlo
    res[3] = min(vhi, 1.0 - ulo - wlo)
    xlo, xhi = clip_hull(xlo, xhi, x2lo, x2hi, min(UV[0, 0], UV[1, 0], UV[2, 0]), max(UV[0, 0], UV[1, 0], UV[2, 0]))
    if xlo > xhi:
        return False
    res[4] = xlo
    res[5] = xhi
    ylo, yhi = clip_hull(ylo, yhi, y2lo, y2hi, min(UV[0, 1], UV[1, 1], UV[2, 1]), max(UV[0, 1], UV[1, 1], UV[2, 1]))
    if ylo > yhi:
        return False
    res[6] = ylo
    res[7] = yhi
    return True


@kernel
def _vertex_two(W, E, P1, P2, N2, origin, fu, fv, lo4, hi4):
    """The reference engine's ``_vertex_two``: x2 - O2, n2 (eq 6–7) and d1 = x2 - x1 (eq 8), affine in
    (u1, v1, ξa, ξb), with the reference's coefficients."""
    e1 = P2[1] - P2[0]
    e2 = P2[2] - P2[0]
    m1 = N2[1] - N2[0]
    m2 = N2[2] - N2[0]
    f1 = P1[1] - P1[0]
    f2 = P1[2] - P1[0]
    for i in range(3):
        g0 = fu[1] * e1[i] + fv[1] * e2[i]
        g1 = fu[2] * e1[i] + fv[2] * e2[i]
        g2 = fu[3] * e1[i]
        g3 = fv[3] * e2[i]
        c = P2[0, i] + fu[0] * e1[i] + fv[0] * e2[i]
        _set_affine(W, E, S2_X + i, c - origin[i], g0, g1, g2, g3, lo4, hi4)
        _set_affine(W, E, S2_D + i, c - P1[0, i], g0 - f1[i], g1 - f2[i], g2, g3, lo4, hi4)
        _set_affine(W, E, S2_N + i, N2[0, i] + fu[0] * m1[i] + fv[0] * m2[i], fu[1] * m1[i] + fv[1] * m2[i],
                    fu[2] * m1[i] + fv[2] * m2[i], fu[3] * m1[i], fv[3] * m2[i], lo4, hi4)


@kernel
def _orientations_two(W, E, P1, P2, lo, hi):
    """The reference engine's ``_orientations_two`` from n2's slots (the sign of (x1 - p2_0)·ng2 at the box
    corners times the sign range of n2·ng2's coefficients)."""
    e1 = P2[1] - P2[0]
    e2 = P2[2] - P2[0]
    ng0 = e1[1] * e2[2] - e1[2] * e2[1]
    ng1 = e1[2] * e2[0] - e1[0] * e2[2]
    ng2 = e1[0] * e2[1] - e1[1] * e2[0]
    f1 = P1[1] - P1[0]
    f2 = P1[2] - P1[0]
    base = (P1[0, 0] - P2[0, 0]) * ng0 + (P1[0, 1] - P2[0, 1]) * ng1 + (P1[0, 2] - P2[0, 2]) * ng2
    a = f1[0] * ng0 + f1[1] * ng1 + f1[2] * ng2
    b = f2[0] * ng0 + f2[1] * ng1 + f2[2] * ng2
    smin = np.inf
    smax = -np.inf
    for k in range(4):
        u = lo[0] if k & 1 == 0 else hi[0]
        v = lo[1] if k & 2 == 0 else hi[1]
        s = base + a * u + b * v
        smin = min(smin, s)
        smax = max(smax, s)
    e = _emax(_emax(_ext(E, S2_N), _ext(E, S2_N + 1)), _ext(E, S2_N + 2))
    nlo = np.inf
    nhi = -np.inf
    A = W[S2_N]
    B = W[S2_N + 1]
    C = W[S2_N + 2]
    ea = _ext(E, S2_N)
    eb = _ext(E, S2_N + 1)
    ec = _ext(E, S2_N + 2)
    for i0 in range(e[0]):
        for i1 in range(e[1]):
            for i2 in range(e[2]):
                for i3 in range(e[3]):  # degree 1 elevated from 0 repeats the coefficient
                    ka = (min(i0, ea[0] - 1) * 343 + min(i1, ea[1] - 1) * 49 + min(i2, ea[2] - 1) * 7
                          + min(i3, ea[3] - 1))
                    kb = (min(i0, eb[0] - 1) * 343 + min(i1, eb[1] - 1) * 49 + min(i2, eb[2] - 1) * 7
                          + min(i3, eb[3] - 1))
                    kc = (min(i0, ec[0] - 1) * 343 + min(i1, ec[1] - 1) * 49 + min(i2, ec[2] - 1) * 7
                          + min(i3, ec[3] - 1))
                    t = 1.0 * (ng0 * A[ka] + ng1 * B[kb]) + ng2 * C[kc]
                    nlo = min(nlo, t)
                    nhi = max(nhi, t)
    return orientation_mask(smin, smax, nlo, nhi)


@kernel
def _directions_two(W, E, refract, o, eta_ratio):
    """The reference engine's ``_directions_two``: d̃2 at ξ2 = 0 in slots S2_DT.. (eq 10; refraction with
    √β2 -> aβ2 + b + δ_lo, eq 12–13) and the scale s of the ξ2 direction m = s n2.  Returns
    (ok, has_m, s); ok = False where β2 < 0 on the whole box (total internal reflection).

    Refraction as d̃2 = η' nn d1 + K n2 with K = -(η' dn + o (aβ2 + b + δ_lo)) (nn = n2·n2,
    dn = d1·n2), at the reference's degrees: nn is elevated to β2's degree first where that
    keeps nn d1 within them, so no product needs elevating afterwards."""
    _dot3(W, E, S2_N, S2_N, S_NN)
    _dot3(W, E, S2_D, S2_N, S_DN)
    if not refract:
        for i in range(3):
            _zero(W, E, S2_DT + i, _emax(_product_ext(_ext(E, S_NN), _ext(E, S2_D + i)),
                                         _product_ext(_ext(E, S_DN), _ext(E, S2_N + i))))
            _mul_acc(W, E, 1.0, S_NN, S2_D + i, S2_DT + i, S_T, S_T + 1, S_T + 2)
            _mul_acc(W, E, -2.0, S_DN, S2_N + i, S2_DT + i, S_T, S_T + 1, S_T + 2)
        return True, False, 0.0
    e2r = eta_ratio * eta_ratio
    _dot3(W, E, S2_D, S2_D, S_DD)
    eb = _emax(_product_ext(_ext(E, S_NN), _ext(E, S_DD)), _product_ext(_ext(E, S_DN), _ext(E, S_DN)))
    _zero(W, E, S_BETA, eb)
    _mul_acc(W, E, 1.0 - e2r, S_NN, S_DD, S_BETA, S_T, S_T + 1, S_T + 2)
    _mul_acc(W, E, e2r, S_DN, S_DN, S_BETA, S_T, S_T + 1, S_T + 2)
    blo, bhi = _value_range(W, E, S_BETA)
    if bhi <= 0.0:
        return False, False, 0.0
    a, b, dlo, dhi = sqrt_linearisation(blo, bhi)
    _zero(W, E, S_R0, eb)
    src = W[S_BETA]
    dst = W[S_R0]
    for k in range(_span(eb)):
        dst[k] = a * src[k]
    _add_constant(W, E, S_R0, b + dlo)
    _zero(W, E, S_K, eb)
    _acc(W, E, -eta_ratio, S_DN, S_K, S_T, S_T + 1)
    _acc(W, E, -o, S_R0, S_K, S_T, S_T + 1)
    _elevate(W, E, S_NN, eb, S_NN5, S_T)
    for i in range(3):
        et = _emax(_emax(_product_ext(_ext(E, S_NN), _ext(E, S2_D + i)), _product_ext(_ext(E, S_DN), _ext(E, S2_N + i))),
                   _product_ext(eb, _ext(E, S2_N + i)))
        _zero(W, E, S2_DT + i, et)
        e5 = _product_ext(eb, _ext(E, S2_D + i))
        nn = S_NN5 if e5[0] <= et[0] and e5[1] <= et[1] and e5[2] <= et[2] and e5[3] <= et[3] else S_NN
        _mul_acc(W, E, eta_ratio, nn, S2_D + i, S2_DT + i, S_T, S_T + 1, S_T + 2)
        _mul_acc(W, E, 1.0, S_K, S2_N + i, S2_DT + i, S_T, S_T + 1, S_T + 2)
    return True, True, -o * (dhi - dlo)


@kernel
def stage_one(refract1, o1, x0, P1, N1, P2, eta, lo, hi, fu, fv, stats):
    """Steps 1–2 (vertex 1 -> triangle 2) for orientation o1 at vertex 1: the forms with remainder of
    (u2, v2) in fu, fv (``two_bounce_irradiance.first_bounce_forms``).  Returns False when the light
    of the box misses triangle 2."""
    box = np.empty(4)
    box[0], box[1], box[2], box[3] = lo[0], hi[0], lo[1], hi[1]
    return first_bounce_forms(refract1, o1, x0, P1, N1, P2, eta, box, fu, fv, stats)


@kernel
def _box_bounds(W, E, chain_code, x0, P1, N1, P2, N2, Q, UV, alive, eta, lo, hi, out, found,
                stats):
    """The reference engine's ``_box_bounds`` (same outputs: out[r, 0:8] and found[r] for every receiver r with
    alive[r]): steps 1–2 by the reference (:func:`stage_one`), the products of step 3 once
    for all receivers, then eq 9 and eq 3 per receiver."""
    for r in range(Q.shape[0]):
        found[r] = False
    if lo[0] + lo[1] > 1.0:
        return
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    lo4 = np.zeros(4)
    hi4 = np.ones(4)
    lo4[0], lo4[1], hi4[0], hi4[1] = lo[0], lo[1], hi[0], hi[1]
    mask1 = _orientations_one(x0, P1, N1, lo4, hi4)
    if mask1 == 0:
        return
    fu = np.zeros(4)
    fv = np.zeros(4)
    res = np.zeros(8)
    origin2 = Q[0, 0]
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
        _vertex_two(W, E, P1, P2, N2, origin2, fu, fv, lo4, hi4)
        mask2 = _orientations_two(W, E, P1, P2, lo, hi)
        for v2 in range(2):
            if not (mask2 >> v2) & 1:
                continue
            if not refract2 and v2 == 1 and (mask2 & 1):
                continue
            o2 = 1.0 if v2 == 0 else -1.0
            ok, has_m, s = _directions_two(W, E, refract2, o2, ior_ratio(o2, eta))
            if not ok:
                continue
            # the products of eq 9 shared by every receiver, at the common degree; ξ2 = 1: eq 9 is
            # linear in the direction, d̃2 + s n2, whose G is G + s H
            _cross3(W, E, S2_X, S2_DT, S2_G)
            ec = _emax(_emax(_ext(E, S2_G), _ext(E, S2_G + 1)), _ext(E, S2_G + 2))
            if has_m:
                _cross3(W, E, S2_X, S2_N, S2_H)
                ec = _emax(ec, _emax(_emax(_ext(E, S2_H), _ext(E, S2_H + 1)), _ext(E, S2_H + 2)))
            n = _count(ec)
            for i in range(3):
                _elevate(W, E, S2_DT + i, ec, S2_DTC + i, S_T)
                _elevate(W, E, S2_G + i, ec, S2_GC + i, S_T)
                if has_m:
                    _elevate(W, E, S2_H + i, ec, S_T + 5, S_T)
                    _elevate(W, E, S2_N + i, ec, S_T + 6, S_T)
                    G0 = W[S2_GC + i]
                    D0 = W[S2_DTC + i]
                    H = W[S_T + 5]
                    M = W[S_T + 6]
                    _zero(W, E, S2_G1 + i, ec)
                    _zero(W, E, S2_DT1 + i, ec)
                    G1 = W[S2_G1 + i]
                    D1 = W[S2_DT1 + i]
                    for k in range(_span(ec)):
                        G1[k] = G0[k] + s * H[k]
                        D1[k] = D0[k] + s * M[k]
            for r in range(Q.shape[0]):
                if not alive[r]:
                    continue
                _numerators(W, E, S2_DTC, S2_GC, origin2, Q[r], S_FPU, S_FPV, S_FQ, ZERO)
                total = n
                if has_m:
                    _numerators(W, E, S2_DT1, S2_G1, origin2, Q[r], S_FPU, S_FPV, S_FQ, n)
                    total = 2 * n
                if not _receiver_bound(W, S_FPU, S_FPV, S_FQ, total, UV[r], res):
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
def pair_pieces_chunk(chain_code, x0, P, N, Q, UV, eta, pairs, reach, per_box, row_start, max_depth, sigma, rows, counts, stats,
               start, stop):
    """The pair-level position quadtree of every receiver (§6.1 stopping rules, eq 3–13) for
    pairs start..stop-1 on one workspace (one function: every level of calls above the
    polynomial kernels costs compilation), pair t lit from x0[t] through IOR eta[t]; a box
    lives for receiver r while ``box_reached(reach[t, r], ...)``
    (``two_bounce_irradiance.receivers_reached``).  Pair t's rows go to
    rows[row_start[t]:row_start[t+1]]; one box emits at most per_box[t] rows (the receivers it
    can reach), and a box is split only while the rows of the pending boxes still fit."""
    nr = Q.shape[0]
    W, E = workspace()
    size = 4 * (max_depth + 2)
    stack = np.empty((size, 5))
    alive = np.zeros((size, nr), dtype=np.bool_)
    pos = np.zeros((nr, 8))
    found = np.zeros(nr, dtype=np.bool_)
    node_alive = np.zeros(nr, dtype=np.bool_)
    child = np.zeros(nr, dtype=np.bool_)
    lo = np.zeros(2)
    hi = np.zeros(2)
    for t in range(start, stop):
        counts[t] = 0
        r0 = row_start[t]
        cap = row_start[t + 1] - r0
        if cap == 0:
            continue
        a = pairs[t, 0]
        b = pairs[t, 1]
        stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0.0, 1.0, 0.0, 1.0, 0.0
        alive[0, :] = True
        top = 1
        count = 0
        while top > 0:
            top -= 1
            lo[0], hi[0], lo[1], hi[1] = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
            depth = int(stack[top, 4])
            any_alive = False
            for r in range(nr):
                node_alive[r] = alive[top, r] and box_reached(reach[t, r], lo, hi)
                any_alive = any_alive or node_alive[r]
            if not any_alive:
                continue
            stats[t, 0] += 1
            _box_bounds(W, E, chain_code, x0[t], P[a], N[a], P[b], N[b], Q, UV, node_alive, eta[t], lo, hi, pos, found, stats[t])
            can_split = depth < max_depth and count + (top + 4) * per_box[t] <= cap
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
                    stats[t, 3] += 1
                row = rows[r0 + count]
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
        counts[t] = count


def batch(chain_code, x0, P, N, Q, UV, eta, pairs, reach, per_box, row_start, max_depth, sigma, rows, counts, stats, chunks=256):
    """Every pair (rows of ``pairs``; :func:`pair_pieces_chunk`'s arguments), in about ``chunks``
    chunks on Python threads (``jit.run_chunks``: the chunk kernel releases the GIL; a
    ``parallel=True`` wrapper took about 14 s to compile)."""
    run_chunks(pair_pieces_chunk, (chain_code, x0, P, N, Q, UV, eta, pairs, reach, per_box, row_start, max_depth, sigma, rows,
                                   counts, stats), pairs.shape[0], chunks)


@kernel
def box_bounds_one(chain_code, x0, P1, N1, P2, N2, Q, UV, eta, lo, hi, out, found, stats):
    """One box of one pair for every receiver (tests): ``_box_bounds`` with every receiver alive."""
    W, E = workspace()
    alive = np.ones(Q.shape[0], dtype=np.bool_)
    _box_bounds(W, E, chain_code, x0, P1, N1, P2, N2, Q, UV, alive, eta, lo, hi, out, found, stats)
