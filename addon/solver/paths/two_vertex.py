"""Two-vertex specular constraint in path space: residual, Jacobian, Gauss-Newton polish.

The two-bounce generalisation of ``one_vertex.py`` (which stays as it is for one bounce).
The unknowns are θ = (u1, v1, u2, v2), the barycentrics of x1 on triangle 1 and x2 on
triangle 2; the residual stacks, per vertex, the outgoing unit direction minus the one the
vertex rule expects (reflect / refract the incoming one about the shading normal):

    r1 = normalize(x2 - x1) - scatter1(normalize(x1 - x0), n̂1)
    r2 = normalize(x3 - x2) - scatter2(normalize(x2 - x1), n̂2)

With the side rules of CONTRACT.md applied per vertex: the incoming side of vertex i is the
geometric side of x_{i-1} against triangle i's plane (its normal oriented by the shading
normal at the vertex), a reflection leaves on that side, a refraction crosses it, and a
refraction's IOR pair follows the side (outside -> inside: 1 -> eta; inside -> outside:
eta -> 1).  Total internal reflection, back-facing shading normals or wrong sides make the
residual undefined (``ok`` False).

All positions are taken relative to the first vertex of triangle 1 (as in the one-bounce
residual), so a scene far from the origin does not lose digits in the segment vectors.
"""

import math

import numpy as np

from ..runtime.jit import kernel
from ..geometry.vec3 import cross, dot, madd, norm, row, scale, sub, tangent_derivative

DIRECTION_TOLERANCE = 1e-7  # |r_i| per vertex for an accepted path (contract)
INSIDE_EPSILON = 1e-9
SETTLED_STEP = 1e-9
TIR_FLOOR = 1e-24  # k = 1 - r² sin² below this counts as total internal reflection


@kernel(inline="always")
def _vertex(prev, x, nxt, n, ng_raw, refract, eta):
    """Residual of one vertex and what its derivative needs.

    Returns (ok, res, wi, wo, li, lo, nh, ln, s, c, r, sk).
    """
    zero = (0.0, 0.0, 0.0)
    di = sub(x, prev)
    do = sub(nxt, x)
    ln = norm(n)
    li = norm(di)
    lo = norm(do)
    if not (ln > 0.0 and li > 0.0 and lo > 0.0):
        return False, zero, zero, zero, 1.0, 1.0, zero, 1.0, 1.0, 0.0, 1.0, 0.0
    nh = scale(n, 1.0 / ln)
    wi = scale(di, 1.0 / li)
    wo = scale(do, 1.0 / lo)
    ng = ng_raw if dot(ng_raw, nh) >= 0.0 else scale(ng_raw, -1.0)
    side_in = -dot(di, ng)
    side_out = dot(do, ng)
    if side_in == 0.0 or side_out == 0.0 or refract == (side_in * side_out > 0.0):
        return False, zero, wi, wo, li, lo, nh, ln, 1.0, 0.0, 1.0, 0.0
    s = 1.0 if side_in > 0.0 else -1.0
    no = scale(nh, s)
    c = -dot(wi, no)
    if not c > 0.0:
        return False, zero, wi, wo, li, lo, nh, ln, s, c, 1.0, 0.0
    if refract:
        r = 1.0 / eta if s > 0.0 else eta
        k = 1.0 - r * r * (1.0 - c * c)
        if not k > TIR_FLOOR:
            return False, zero, wi, wo, li, lo, nh, ln, s, c, r, 0.0
        sk = math.sqrt(k)
        expected = madd(scale(wi, r), no, r * c - sk)
    else:
        r = 1.0
        sk = 0.0
        expected = madd(wi, no, 2.0 * c)
    return True, sub(wo, expected), wi, wo, li, lo, nh, ln, s, c, r, sk


@kernel(inline="always")
def _vertex_derivative(ddi, ddo, dn, wi, wo, li, lo, nh, ln, s, c, r, sk, refract):
    """d(residual) when the incoming segment changes by ddi, the outgoing by ddo and the
    (unnormalised) normal by dn."""
    no = scale(nh, s)
    dwi = tangent_derivative(wi, ddi, li)
    dwo = tangent_derivative(wo, ddo, lo)
    dno = scale(tangent_derivative(nh, dn, ln), s)
    dc = -(dot(dwi, no) + dot(wi, dno))
    if refract:
        dsk = r * r * c * dc / sk
        dexp = madd(madd(scale(dwi, r), no, r * dc - dsk), dno, r * c - sk)
    else:
        dexp = madd(madd(dwi, no, 2.0 * dc), dno, 2.0 * c)
    return sub(dwo, dexp)


@kernel(inline="always")
def _unpack(geo, th):
    """The packed geometry (see :func:`pack_geometry`) as named vectors, plus the two
    vertices and their unnormalised normals at θ = (u1, v1, u2, v2)."""
    x0, x3, e11, e12, n10, m11, m12 = row(geo, 0), row(geo, 1), row(geo, 2), row(geo, 3), row(geo, 4), row(geo, 5), row(geo, 6)
    p20, e21, e22, n20, m21, m22 = row(geo, 7), row(geo, 8), row(geo, 9), row(geo, 10), row(geo, 11), row(geo, 12)
    ng1, ng2 = row(geo, 13), row(geo, 14)
    x1 = madd(scale(e11, th[0]), e12, th[1])
    x2 = madd(madd(p20, e21, th[2]), e22, th[3])
    n1 = madd(madd(n10, m11, th[0]), m12, th[1])
    n2 = madd(madd(n20, m21, th[2]), m22, th[3])
    return x0, x3, e11, e12, n10, m11, m12, p20, e21, e22, n20, m21, m22, ng1, ng2, x1, x2, n1, n2


@kernel
def two_vertex_residual(th, geo, refract1, refract2, eta, res, jac):
    """Residual (6,) and Jacobian (6, 4) at θ = th (4,); returns ok.

    ``geo`` (15, 3), positions relative to p1,0 (see :func:`pack_geometry`): 0 x0, 1 x3,
    2 e1,1, 3 e1,2, 4 n1,0, 5 m1,1, 6 m1,2, 7 p2,0, 8 e2,1, 9 e2,2, 10 n2,0, 11 m2,1, 12 m2,2,
    13 and 14 the unit geometric normals of triangles 1 and 2 (m = corner normal differences).
    """
    zero = (0.0, 0.0, 0.0)
    (x0, x3, e11, e12, n10, m11, m12, p20, e21, e22, n20, m21, m22, ng1, ng2,
     x1, x2, n1, n2) = _unpack(geo, th)
    ok1, r1, wi1, wo1, li1, lo1, nh1, ln1, s1, c1, q1, sk1 = _vertex(x0, x1, x2, n1, ng1, refract1, eta)
    if not ok1:
        return False
    ok2, r2, wi2, wo2, li2, lo2, nh2, ln2, s2, c2, q2, sk2 = _vertex(x1, x2, x3, n2, ng2, refract2, eta)
    if not ok2:
        return False
    for a in range(3):
        res[a] = r1[a]
        res[3 + a] = r2[a]
    for p in range(4):
        if p == 0:
            d1, dm1, d2, dm2 = e11, m11, zero, zero
        elif p == 1:
            d1, dm1, d2, dm2 = e12, m12, zero, zero
        elif p == 2:
            d1, dm1, d2, dm2 = zero, zero, e21, m21
        else:
            d1, dm1, d2, dm2 = zero, zero, e22, m22
        # vertex 1: incoming x1 - x0, outgoing x2 - x1, normal n1
        col1 = _vertex_derivative(d1, sub(d2, d1), dm1, wi1, wo1, li1, lo1, nh1, ln1, s1, c1, q1, sk1, refract1)
        # vertex 2: incoming x2 - x1, outgoing x3 - x2, normal n2
        col2 = _vertex_derivative(sub(d2, d1), scale(d2, -1.0), dm2, wi2, wo2, li2, lo2, nh2, ln2, s2, c2, q2, sk2, refract2)
        for a in range(3):
            jac[a, p] = col1[a]
            jac[3 + a, p] = col2[a]
    return True


@kernel
def pack_geometry(x0, x3, tri1_p, tri1_n, tri2_p, tri2_n, geo):
    """Fill ``geo`` (15, 3) for :func:`two_vertex_residual`; returns False for a zero-area
    triangle."""
    o = (tri1_p[0, 0], tri1_p[0, 1], tri1_p[0, 2])
    for a in range(3):
        geo[0, a] = x0[a] - o[a]
        geo[1, a] = x3[a] - o[a]
        geo[2, a] = tri1_p[1, a] - tri1_p[0, a]
        geo[3, a] = tri1_p[2, a] - tri1_p[0, a]
        geo[4, a] = tri1_n[0, a]
        geo[5, a] = tri1_n[1, a] - tri1_n[0, a]
        geo[6, a] = tri1_n[2, a] - tri1_n[0, a]
        geo[7, a] = tri2_p[0, a] - o[a]
        geo[8, a] = tri2_p[1, a] - tri2_p[0, a]
        geo[9, a] = tri2_p[2, a] - tri2_p[0, a]
        geo[10, a] = tri2_n[0, a]
        geo[11, a] = tri2_n[1, a] - tri2_n[0, a]
        geo[12, a] = tri2_n[2, a] - tri2_n[0, a]
    ok = True
    for t in range(2):
        ra = 2 if t == 0 else 8
        ea = (geo[ra, 0], geo[ra, 1], geo[ra, 2])
        eb = (geo[ra + 1, 0], geo[ra + 1, 1], geo[ra + 1, 2])
        g = cross(ea, eb)
        lg = norm(g)
        le = max(norm(ea), norm(eb))
        if not (lg > 1e-14 * le * le):
            ok = False
            lg = 1.0
        for a in range(3):
            geo[13 + t, a] = g[a] / lg
    return ok


@kernel
def _solve4(A, b, out):
    """Solve the 4x4 system A x = b (partial pivoting, A and b overwritten); False if singular."""
    n = 4
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        if not big > 0.0:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            if f != 0.0:
                for j in range(k, n):
                    A[i, j] -= f * A[k, j]
                b[i] -= f * b[k]
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc -= A[i, j] * out[j]
        out[i] = acc / A[i, i]
    return True


@kernel
def _normal_equations(jac, res, A, b):
    for i in range(4):
        acc = 0.0
        for r in range(6):
            acc += jac[r, i] * res[r]
        b[i] = -acc
        for j in range(4):
            acc = 0.0
            for r in range(6):
                acc += jac[r, i] * jac[r, j]
            A[i, j] = acc


@kernel
def _max_vertex_error(res):
    e1 = math.sqrt(res[0] * res[0] + res[1] * res[1] + res[2] * res[2])
    e2 = math.sqrt(res[3] * res[3] + res[4] * res[4] + res[5] * res[5])
    return max(e1, e2)


@kernel
def polish_and_validate2(th, geo, refract1, refract2, eta, max_steps, tolerance, work):
    """Gauss-Newton on the two-vertex residual from th (4,), in place, then the acceptance
    test.  ``work``: (25, 6) scratch.  Returns (accepted, error, sigma_estimate) where error is
    the larger per-vertex residual norm and sigma_estimate a lower bound of σ_min(J)."""
    res = work[0]
    res2 = work[1]
    jac = work[2:8, 0:4]
    jac2 = work[8:14, 0:4]
    A = work[14:18, 0:4]
    b = work[18, 0:4]
    step = work[19, 0:4]
    trial = work[20, 0:4]
    if not two_vertex_residual(th, geo, refract1, refract2, eta, res, jac):
        return False, math.inf, 0.0
    err = math.sqrt(dot((res[0], res[1], res[2]), (res[0], res[1], res[2])) + dot((res[3], res[4], res[5]), (res[3], res[4], res[5])))
    last_step = math.inf
    for _ in range(max_steps):
        if err < 1e-15:
            last_step = 0.0
            break
        _normal_equations(jac, res, A, b)
        if not _solve4(A, b, step):
            break
        last_step = max(max(abs(step[0]), abs(step[1])), max(abs(step[2]), abs(step[3])))
        if not last_step < 10.0:
            break
        improved = False
        lam = 1.0
        for _h in range(4):  # backtracking: far candidates (√ approximation) may overshoot
            for i in range(4):
                trial[i] = th[i] + lam * step[i]
            if two_vertex_residual(trial, geo, refract1, refract2, eta, res2, jac2):
                err2 = 0.0
                for r in range(6):
                    err2 += res2[r] * res2[r]
                err2 = math.sqrt(err2)
                if err2 < err:
                    improved = True
                    break
            if lam < 1.0 and err > 1e-9:
                lam *= 0.25
            elif err > 1e-9:
                lam = 0.5
            else:
                break
        if not improved:
            break
        for i in range(4):
            th[i] = trial[i]
        for r in range(6):
            res[r] = res2[r]
            for c in range(4):
                jac[r, c] = jac2[r, c]
        err = err2
        if lam < 1.0:
            last_step = math.inf
    inside = True
    for t in range(2):
        u = th[2 * t]
        v = th[2 * t + 1]
        if not (u >= -INSIDE_EPSILON and v >= -INSIDE_EPSILON and u + v <= 1.0 + INSIDE_EPSILON):
            inside = False
    verr = _max_vertex_error(res)
    settled = last_step <= SETTLED_STEP
    accepted = inside and (err <= tolerance or (settled and verr <= DIRECTION_TOLERANCE))
    # Lower bound of σ_min(J): 1 / sqrt(trace((JᵀJ)⁻¹)) (within a factor 2 of it).
    _normal_equations(jac, res, A, b)
    tmp = work[21:25, 0:4]
    tr = 0.0
    for col in range(4):
        for i in range(4):
            b[i] = 1.0 if i == col else 0.0
            for j in range(4):
                tmp[i, j] = A[i, j]
        if not _solve4(tmp, b, step):
            tr = math.inf
            break
        tr += step[col]
    sigma = 1.0 / math.sqrt(tr) if tr > 0.0 and tr < math.inf else 0.0
    return accepted, verr, sigma


@kernel
def trace_to_second(u1, v1, geo, refract1, eta):
    """Exact mapping (u1, v1) -> (u2, v2): scatter the ray x0 -> x1 at vertex 1 and intersect
    triangle 2's plane.  Returns (ok, u2, v2); ok False under TIR / wrong side / no hit."""
    x0 = (geo[0, 0], geo[0, 1], geo[0, 2])
    e11 = (geo[2, 0], geo[2, 1], geo[2, 2])
    e12 = (geo[3, 0], geo[3, 1], geo[3, 2])
    n1 = madd(madd((geo[4, 0], geo[4, 1], geo[4, 2]), (geo[5, 0], geo[5, 1], geo[5, 2]), u1), (geo[6, 0], geo[6, 1], geo[6, 2]), v1)
    ng1 = (geo[13, 0], geo[13, 1], geo[13, 2])
    p20 = (geo[7, 0], geo[7, 1], geo[7, 2])
    e21 = (geo[8, 0], geo[8, 1], geo[8, 2])
    e22 = (geo[9, 0], geo[9, 1], geo[9, 2])
    x1 = madd(scale(e11, u1), e12, v1)
    di = sub(x1, x0)
    li = norm(di)
    ln = norm(n1)
    if not (li > 0.0 and ln > 0.0):
        return False, 0.0, 0.0
    wi = scale(di, 1.0 / li)
    nh = scale(n1, 1.0 / ln)
    ng = ng1 if dot(ng1, nh) >= 0.0 else scale(ng1, -1.0)
    side_in = -dot(di, ng)
    if side_in == 0.0:
        return False, 0.0, 0.0
    s = 1.0 if side_in > 0.0 else -1.0
    no = scale(nh, s)
    c = -dot(wi, no)
    if not c > 0.0:
        return False, 0.0, 0.0
    if refract1:
        r = 1.0 / eta if s > 0.0 else eta
        k = 1.0 - r * r * (1.0 - c * c)
        if not k > 0.0:
            return False, 0.0, 0.0
        d = madd(scale(wi, r), no, r * c - math.sqrt(k))
    else:
        d = madd(wi, no, 2.0 * c)
    # Möller-Trumbore against the plane of triangle 2 (unbounded).
    pvec = cross(d, e22)
    det = dot(e21, pvec)
    if det == 0.0:
        return False, 0.0, 0.0
    sv = sub(x1, p20)
    u2 = dot(sv, pvec) / det
    qvec = cross(sv, e21)
    v2 = dot(d, qvec) / det
    t = dot(e22, qvec) / det
    if not (t > 0.0) or not (np.isfinite(u2) and np.isfinite(v2)):
        return False, 0.0, 0.0
    return True, u2, v2


@kernel(inline="always")
def _scatter_derivative(dwi, dn, wi, nh, ln, s, c, r, sk, refract):
    """Derivative of the scattered unit direction when the incoming unit direction changes by
    dwi and the unnormalised normal by dn (same formulas as the residual's Jacobian)."""
    no = scale(nh, s)
    dno = scale(tangent_derivative(nh, dn, ln), s)
    dc = -(dot(dwi, no) + dot(wi, dno))
    if refract:
        dsk = r * r * c * dc / sk
        return madd(madd(scale(dwi, r), no, r * dc - dsk), dno, r * c - sk)
    return madd(madd(dwi, no, 2.0 * dc), dno, 2.0 * c)


@kernel
def two_bounce_footprint(th, geo, refract1, refract2, eta):
    """Generalised geometry term of a two-bounce path and what the Fresnel factors need.

    Returns (ok, geometry, cos1, s1, cos2, s2, w2) with geometry = dΩ0 / dA⊥ at x3: the solid
    angle of light leaving x0 (parametrised by x1's barycentrics) over the area, perpendicular
    to the arriving ray, that the ray tube covers at x3 — chain rule through both vertices:
    x1(u1, v1) → scattered w1 → x2 on triangle 2's plane → n2(x2) → scattered w2 → x3 + L w2."""
    zero = (0.0, 0.0, 0.0)
    (x0, x3, e11, e12, n10, m11, m12, p20, e21, e22, n20, m21, m22, ng1, ng2,
     x1, x2, n1, n2) = _unpack(geo, th)
    ok1, r1, wi1, wo1, li1, lo1, nh1, ln1, s1, c1, q1, sk1 = _vertex(x0, x1, x2, n1, ng1, refract1, eta)
    ok2, r2, wi2, wo2, li2, lo2, nh2, ln2, s2, c2, q2, sk2 = _vertex(x1, x2, x3, n2, ng2, refract2, eta)
    if not (ok1 and ok2):
        return False, 0.0, 0.0, 1.0, 0.0, 1.0, zero
    # the scattered directions (exact: the path is polished, wo ≈ expected)
    w1 = sub(wo1, r1)
    w1 = scale(w1, 1.0 / norm(w1))
    w2 = sub(wo2, r2)
    w2 = scale(w2, 1.0 / norm(w2))
    L1 = lo1
    L2 = lo2
    g12 = dot(e21, e21)
    g12x = dot(e21, e22)
    g22 = dot(e22, e22)
    det = g12 * g22 - g12x * g12x
    denom = dot(w1, ng2)
    if det == 0.0 or denom == 0.0:
        return False, 0.0, 0.0, 1.0, 0.0, 1.0, zero
    cols0 = zero
    cols1 = zero
    for p in range(2):
        dx1 = e11 if p == 0 else e12
        dn1 = m11 if p == 0 else m12
        dwi1 = tangent_derivative(wi1, dx1, li1)
        dw1 = _scatter_derivative(dwi1, dn1, wi1, nh1, ln1, s1, c1, q1, sk1, refract1)
        # x2 = x1 + t w1 stays on plane 2
        q = madd(dx1, dw1, L1)
        dx2 = madd(q, w1, -dot(q, ng2) / denom)
        b1 = dot(dx2, e21)
        b2 = dot(dx2, e22)
        du2 = (g22 * b1 - g12x * b2) / det
        dv2 = (g12 * b2 - g12x * b1) / det
        dn2 = madd(scale(m21, du2), m22, dv2)
        dw2 = _scatter_derivative(dw1, dn2, w1, nh2, ln2, s2, c2, q2, sk2, refract2)
        dX = madd(dx2, dw2, L2)
        dX = madd(dX, w2, -dot(dX, w2))
        if p == 0:
            cols0 = dX
        else:
            cols1 = dX
    area_perp = norm(cross(cols0, cols1))
    solid_angle = abs(dot(wi1, ng1)) * norm(cross(e11, e12)) / (li1 * li1)
    if not area_perp > 0.0:
        return False, 0.0, c1, s1, c2, s2, w2
    return True, solid_angle / area_perp, c1, s1, c2, s2, w2
