"""The specular constraint in path space: residual, Jacobian, Newton polish, validation.

A candidate vertex x1 = p0 + u e1 + v e2 with normal n̂ = normalize(n0 + u m1 + v m2) is a
true specular vertex when the outgoing unit direction equals the reflected / refracted
incoming one.  That is the full vertex constraint, eq (3) of Fan et al. 2024
(h × n = 0, the generalised half vector parallel to the normal), written with the side
rules that eq (3) alone does not see: the incoming side is the geometric side x0 lies on,
a reflection leaves on that side, a refraction crosses, and total internal reflection has
no refracted direction.  The rules are spelled out in ``CONTRACT.md``.
"""

import math

from ..runtime.jit import kernel
from ..geometry.vec3 import cross, dot, madd, norm, row, scale, sub, tangent_derivative_by_inverse

DIRECTION_TOLERANCE = 1e-7  # |wo - expected| for an accepted path (unit vectors)
INSIDE_EPSILON = 1e-9  # barycentric slack at triangle edges
SETTLED_STEP = 1e-9  # a Newton step this small in (u, v) means the iterate has converged
FAR_START = -1.0  # the |residual| polish_validate_normal_matrix reports for a start rejected as far from any path
RETURNED = -2.0  # ... and for a probe abandoned on its way back to the known path
FLOOR_RESIDUAL = 1e-13  # a residual this small, with a step under FLOOR_STEP, is at rounding level:
FLOOR_STEP = 1e-12  # the last step is taken unevaluated


@kernel
def scatter_residual(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta):
    """Residual wo - expected(wi, n̂) at barycentrics (u, v) and its (u, v) Jacobian.

    Returns (ok, residual, d_residual/du, d_residual/dv); ok is False when the
    configuration has no scattered direction (wrong side, back-facing shading normal,
    total internal reflection, zero-length segments or normals).
    """
    zero = (0.0, 0.0, 0.0)
    # Segments from the vertex p0, not from absolute positions: in a scene far from the
    # origin x1 - x0 would carry the rounding of |x1| (1e-14 at 100 units), which on a
    # small triangle is a 1e-12 direction error and a visible positional blur.
    di = madd(madd(sub(p0, x0), e1, u), e2, v)
    do = madd(madd(sub(x2, p0), e1, -u), e2, -v)
    n = madd(madd(n0, m1, u), m2, v)
    ln = norm(n)
    li = norm(di)
    lo = norm(do)
    if not (ln > 0.0 and li > 0.0 and lo > 0.0):
        return False, zero, zero, zero
    inv_ln = 1.0 / ln
    inv_li = 1.0 / li
    inv_lo = 1.0 / lo
    nh = scale(n, inv_ln)
    wi = scale(di, inv_li)
    wo = scale(do, inv_lo)
    ng = ng_raw if dot(ng_raw, nh) >= 0.0 else scale(ng_raw, -1.0)
    side_in = -dot(di, ng)
    side_out = dot(do, ng)
    if side_in == 0.0 or side_out == 0.0:
        return False, zero, zero, zero
    if refract == (side_in * side_out > 0.0):
        return False, zero, zero, zero
    s = 1.0 if side_in > 0.0 else -1.0
    no = scale(nh, s)
    c = -dot(wi, no)
    if not c > 0.0:
        return False, zero, zero, zero
    if refract:
        r = 1.0 / eta if s > 0.0 else eta
        k = 1.0 - r * r * (1.0 - c * c)
        if not k > 1e-24:
            return False, zero, zero, zero
        sk = math.sqrt(k)
        expected = madd(scale(wi, r), no, r * c - sk)
    else:
        r = 1.0
        sk = 0.0
        expected = madd(wi, no, 2.0 * c)
    res = sub(wo, expected)
    jac_u = zero
    jac_v = zero
    for axis in range(2):
        d = e1 if axis == 0 else e2
        dm = m1 if axis == 0 else m2
        dwi = tangent_derivative_by_inverse(wi, d, inv_li)
        dwo = scale(tangent_derivative_by_inverse(wo, d, inv_lo), -1.0)
        dno = scale(tangent_derivative_by_inverse(nh, dm, inv_ln), s)
        dc = -(dot(dwi, no) + dot(wi, dno))
        if refract:
            dsk = r * r * c * dc / sk
            dexp = madd(madd(scale(dwi, r), no, r * dc - dsk), dno, r * c - sk)
        else:
            dexp = madd(madd(dwi, no, 2.0 * dc), dno, 2.0 * c)
        col = sub(dwo, dexp)
        if axis == 0:
            jac_u = col
        else:
            jac_v = col
    return True, res, jac_u, jac_v


@kernel
def polish_and_validate(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta, max_steps, tolerance):
    """Gauss-Newton on the path-space residual (eq 3) from (u, v), then the acceptance test
    (:func:`polish_validate_normal_matrix` without the normal matrix).
    Returns (accepted, u, v, |residual|, smallest singular value of the Jacobian)."""
    accepted, u, v, err, sigma_min, _a11, _a12, _a22 = polish_validate_normal_matrix(
        u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta, max_steps, tolerance, math.inf)
    return accepted, u, v, err, sigma_min


@kernel
def polish_validate_normal_matrix(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta, max_steps, tolerance,
                                  max_first_step, known_u=0.0, known_v=0.0, return_radius=0.0):
    """Gauss-Newton on the path-space residual from (u, v), then the acceptance test.

    The polynomial roots are already close (the system is exact for one bounce), so one
    or two steps reach rounding level; the loop stops early once the step stalls, and a step
    from a residual at rounding level (FLOOR_RESIDUAL, FLOOR_STEP) is taken unevaluated.
    Near a fold of the caustic the residual is flat along one direction and Gauss-Newton
    converges only linearly, so a stalled iterate can sit ~1e-3 from the root with a
    residual of 1e-8: ``tolerance`` (well below DIRECTION_TOLERANCE) rejects such points,
    unless Newton has settled in position (its next step at rounding level).
    A start whose first step would move it farther than ``max_first_step`` (in u or v) is no
    path's root and is rejected unpolished (|residual| reported as FAR_START): a polish from
    there is a search that at best finds a path some other candidate finds.
    A probe for a second path next to a known one at (known_u, known_v) (``one_bounce._probe_fold``)
    is abandoned once a Gauss-Newton step would take it within ``return_radius`` (in u and v) of
    the known path, before the residual is evaluated there: it is converging back to it
    (|residual| reported as RETURNED).
    Returns (accepted, u, v, |residual|, smallest singular value of the Jacobian, and the
    entries a11, a12, a22 of J^T J at the returned (u, v), so that a caller testing for a fold
    need not evaluate the residual there again).
    """
    ok, res, ju, jv = scatter_residual(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta)
    if not ok:
        return False, u, v, math.inf, 0.0, 0.0, 0.0, 0.0
    err = norm(res)
    last_step = math.inf
    for _ in range(max_steps):
        if err < 1e-15:
            last_step = 0.0
            break
        # Normal equations of the 3x2 least-squares step: (J^T J) delta = -J^T r.
        a11 = dot(ju, ju)
        a12 = dot(ju, jv)
        a22 = dot(jv, jv)
        b1 = -dot(ju, res)
        b2 = -dot(jv, res)
        det = a11 * a22 - a12 * a12
        if not abs(det) > 1e-300:
            break
        du = (b1 * a22 - b2 * a12) / det
        dv = (a11 * b2 - a12 * b1) / det
        if last_step == math.inf and not max(abs(du), abs(dv)) <= max_first_step:
            return False, u, v, FAR_START, 0.0, 0.0, 0.0, 0.0
        last_step = max(abs(du), abs(dv))
        if max(abs(u + du - known_u), abs(v + dv - known_v)) < return_radius:
            return False, u + du, v + dv, RETURNED, 0.0, 0.0, 0.0, 0.0  # heading back: not evaluated there
        if err <= FLOOR_RESIDUAL and last_step <= FLOOR_STEP:
            # At the rounding floor: Newton's step from here lands within rounding of the root,
            # so it is taken without the evaluation that would only confirm it.
            u += du
            v += dv
            break
        ok2, res2, ju2, jv2 = scatter_residual(u + du, v + dv, x0, x2, p0, e1, e2, n0, m1, m2, ng_raw, refract, eta)
        if not ok2:
            break
        err2 = norm(res2)
        if not err2 < err:
            break
        u += du
        v += dv
        res, ju, jv, err = res2, ju2, jv2, err2
    inside = u >= -INSIDE_EPSILON and v >= -INSIDE_EPSILON and u + v <= 1.0 + INSIDE_EPSILON
    # Converged in position: the step Newton still wants is negligible, so the residual is
    # at its rounding floor (near total internal reflection that floor is ~1e-8).  A point
    # stalled near a fold, where the residual is flat, still wants a large step.
    settled = last_step <= SETTLED_STEP
    accepted = inside and (err <= tolerance or (settled and err <= DIRECTION_TOLERANCE))
    # Smallest singular value of the Jacobian: how well (u, v) is pinned by the residual.
    a11 = dot(ju, ju)
    a12 = dot(ju, jv)
    a22 = dot(jv, jv)
    half_gap = math.sqrt(max(0.0, 0.25 * (a11 - a22) ** 2 + a12 * a12))
    sigma_min = math.sqrt(max(0.0, 0.5 * (a11 + a22) - half_gap))
    return accepted, u, v, err, sigma_min, a11, a12, a22


@kernel
def triangle_frame(tri_p, tri_n):
    """(p0, e1, e2, n0, m1, m2) of a (3,3) vertex / normal pair: x = p0 + u e1 + v e2,
    n = n0 + u m1 + v m2 (eq 1-2)."""
    p0 = row(tri_p, 0)
    n0 = row(tri_n, 0)
    return p0, sub(row(tri_p, 1), p0), sub(row(tri_p, 2), p0), n0, sub(row(tri_n, 1), n0), sub(row(tri_n, 2), n0)


@kernel
def line_crossing_barycentrics(x0, x2, p0, e1, e2, ng):
    """(ok, u, v): where the line x0 -> x2 crosses the triangle's plane, in barycentrics
    (Cramer's rule in the plane); ok is False when the line is parallel to the plane or
    the triangle is degenerate.  No inside test."""
    w = sub(x2, x0)
    denom = dot(w, ng)
    if denom == 0.0:
        return False, 0.0, 0.0
    rel = sub(madd(x0, w, dot(sub(p0, x0), ng) / denom), p0)
    d11 = dot(e1, e1)
    d12 = dot(e1, e2)
    d22 = dot(e2, e2)
    r1 = dot(rel, e1)
    r2 = dot(rel, e2)
    det = d11 * d22 - d12 * d12
    if not det > 0.0:
        return False, 0.0, 0.0
    return True, (r1 * d22 - r2 * d12) / det, (d11 * r2 - d12 * r1) / det


@kernel
def geometric_normal(e1, e2):
    """Unit normal of the triangle's plane (unoriented) and twice its area."""
    g = cross(e1, e2)
    area2 = norm(g)
    if area2 > 0.0:
        return scale(g, 1.0 / area2), area2
    return g, 0.0


@kernel
def endpoint_sides(x0, x2, p0, e1, e2, eta):
    """The plane test a one-vertex solve starts with (a reflection needs both endpoints on one
    side of the triangle's plane, a refraction one on each): (usable, ng, length, side0,
    side2), ng the unit geometric normal of the triangle (p0, e1, e2), length its longer edge
    from p0, side0 / side2 the signed distances of x0 / x2 to its plane.  Not usable: a
    degenerate triangle (twice its area <= 1e-14 length²), eta <= 0, or an endpoint within
    1e-12 length of the plane (no path)."""
    ng, area2 = geometric_normal(e1, e2)
    length = max(norm(e1), norm(e2))
    if not (area2 > 1e-14 * length * length) or not (eta > 0.0):
        return False, ng, length, 0.0, 0.0
    side0 = dot(sub(x0, p0), ng)
    side2 = dot(sub(x2, p0), ng)
    tiny = 1e-12 * length
    return not (abs(side0) <= tiny or abs(side2) <= tiny), ng, length, side0, side2
