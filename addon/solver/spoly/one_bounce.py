"""One-bounce Specular Polynomials: the R and T chains (Fan et al. 2024, §3.3–4.3).

For a tuple (x0, triangle, x2) the unknowns are the barycentrics (u, v) of the specular
vertex x1.  Two bivariate polynomials vanish at every admissible path:

* a(u, v): coplanarity, endpoint-difference form, eq (6): ((x1 - x0) × (x2 - x0)) · n = 0,
  total degree 2 (eq 25/26, first line);
* b(u, v): angularity, the product form for reflection, eq (13) (degree 4, eq 25), or the
  square form for refraction, eq (10) (degree 6, eq 26).

u is eliminated with the resultant r(v) = Res_u(a, b) (eq 28–30) and the real roots of r in
[0, 1] are found by Bernstein isolation (``roots.py``); u follows from a(u, v*) = 0, and
each candidate is Newton-polished and validated in path space (``one_vertex.py``).  r always
has a spurious root where d0·t and d1·t vanish together (a double root for T): it is divided
out first (``double_point_v``), so that rounding does not split it into a near pair.

Resultant.  a has total degree 2, so a = a2 u² + a1(v) u + a0(v) with a2 a constant, and
Res_u(a, b) = a2^n b(ρ1) b(ρ2) (ρ the u-roots of a); r has degree ≤ 8 (R) or ≤ 12 (T).  It
is evaluated, per v with q = -(a1 + sign(a1) √disc) / 2, as Res = B(q, a2) b(a0 / q),
B(x, y) = Σ b_i x^i y^(n-i) (complex roots: a2^n |b(ρ)|²), at the Chebyshev nodes (all
nodes at once, ``resultant_at_nodes``) and interpolated to Bernstein form: values are good to
a few ulps, where an expansion of the square form cancels badly when b is small along the
conic next to a path (an endpoint close to a large triangle, grazing incidence); where the
node values span more than DYNAMIC_RANGE the range is re-interpolated piecewise
(``_resultant_v_roots``).  For R (degree 8) the nine node values and their interpolation
also cost less than the symbolic expansion of eq (28-30) that the product form would allow
(Σ_i a0^i b_i T_i by power sums).  The triangle's corners are relabelled per tuple so that
u is eliminated along an edge where the conic does not fold (``elimination_labelling``).
Tested against brute force in tests/solver/test_solver_random.py and test_solver_grazing.py.

The projection vector b (eq 10) and the tangent t = n × b (eq 13) are chosen per tuple as
the normal of the plane of incidence at the mean shading normal, b = (x2 - x0) × n̄, so
neither form degenerates (the paper's fixed (1,0,0) / n × e1 vanish on whole curves when
the plane of incidence contains that axis, e.g. a mirror and a light in the x-y plane).
"""

import math

import numpy as np

from ..runtime.jit import kernel, parallel_range
from ..paths.order import sort_rows
from ..paths.one_vertex import (FAR_START, endpoint_sides, line_crossing_barycentrics, polish_and_validate,
                                polish_validate_normal_matrix)
from ..polynomials.roots import (MAX_DEGREE, STACK_ROWS, roots_in_interval, roots_in_unit_interval,
                                 roots_in_unit_interval_bernstein)
from ..polynomials.small_products import mul_quadratic_quartic, mul_quadratics
from ..geometry.vec3 import cross, dot, madd, norm, row, scale, sub

MAX_PATHS_ONE_BOUNCE = 8  # per tuple; a one-bounce tuple seldom has more than 2
CHUNK = 256  # tuples per parallel work item (scratch is allocated once per chunk)

ROOT_X_TOLERANCE = 1e-13
ROOT_TOUCH_TOLERANCE = 1e-10
V_MARGIN = 1e-6  # v roots are searched slightly outside [0, 1]; the inside test is exact
SAME_PATH = 1e-7  # barycentric distance under which two polished candidates are one path
NEAR_PATH = 1e-5  # largest merge radius, used where the Jacobian barely pins the path
CANDIDATE_REACH = 0.1  # a resultant candidate whose first Gauss-Newton step is longer is no path's root
INEXACT_ROOT = 1e-9  # |b| / Σ|b_ij u^i v^j| above which a candidate is no exact root of the system
POLISH_STEPS = 40  # Gauss-Newton steps at most (stops once converged or a step stops helping)
ACCEPT_RESIDUAL = 1e-12  # residual accepted outright; above it (up to 1e-7) Newton must have settled
NEGLIGIBLE = 1e-13  # relative size below which a coefficient is treated as exactly zero
FOLD_RATIO = 1e-4  # lam_min / lam_max of J^T J under which a path counts as near a fold
FOLD_STEPS = (1e-5, 1e-4, 1e-3)  # barycentric probe distances along the null direction
PROBE_RETURN = 0.25  # a probe whose iterate comes this share of its distance back to the path is abandoned
DYNAMIC_RANGE = 1e-6  # node values spanning more than this: interpolate the resultant piecewise
SPLIT = 4  # pieces per level of that refinement
SPLIT_DEPTH = 2  # levels at most (16 pieces)
NODE_SCRATCH = 16  # first row of the univariate scratch that resultant_at_nodes works in
ROW_B_VALUE = 7  # rows of the univariate scratch holding b(·, v*) by powers of u (_rows_at_v) ...
ROW_B_SIZE = 8  # ... and the sizes of its terms
SPURIOUS_B = 1e-3  # |b| / Σ|b_ij u^i v^j| at a u-root of a(·, v*) above which b clearly does not vanish there
SINGULAR_MARGIN = 0.01  # barycentric slack of the test for a path at normal incidence
SWITCH_RATIO = 0.1  # relabel the corners when the default elimination's |Q| is below this share of the best
DOUBLE_POINT_REACH = 0.25  # the double point is divided out only within this distance of v's range [0, 1]
DOUBLE_POINT_F3 = 1e-9  # |f3| / Σ|f3_ij u^i v^j| under which a root of Res_u(a, g) is the double point

def _bernstein_collocation(degree, lo=0.0, hi=1.0):
    """(nodes, inverse): Chebyshev nodes of [lo, hi] and the inverse of the matrix of the degree
    ``degree`` Bernstein basis of [0, 1] at them (values at the nodes -> Bernstein coefficients)."""
    from math import comb

    k = np.arange(degree + 1)
    nodes = lo + (hi - lo) * 0.5 * (1.0 - np.cos((2.0 * k + 1.0) * np.pi / (2.0 * degree + 2.0)))
    basis = np.array([[comb(degree, j) * x ** j * (1.0 - x) ** (degree - j) for j in range(degree + 1)] for x in nodes])
    return nodes, np.linalg.inv(basis)


NODES_R, TO_BERNSTEIN_R = _bernstein_collocation(8)  # the R resultant has degree <= 8 in v
NODES_T, TO_BERNSTEIN_T = _bernstein_collocation(12)  # the T resultant, degree <= 12
# The resultants with the spurious root of the double point divided out (``double_point_v``):
# degree 7 (R) and 10 (T).  Each has a second node set, of a slightly wider interval, used when a
# node of the first lies close to the divided-out root (where the division amplifies rounding):
# one of the two sets always keeps every node at least 0.005 of the interval away from it.
NODES_R_DEFLATED, TO_BERNSTEIN_R_DEFLATED = _bernstein_collocation(7)
NODES_R_DEFLATED_WIDE, TO_BERNSTEIN_R_DEFLATED_WIDE = _bernstein_collocation(7, -0.07, 1.07)
NODES_T_DEFLATED, TO_BERNSTEIN_T_DEFLATED = _bernstein_collocation(10)
NODES_T_DEFLATED_WIDE, TO_BERNSTEIN_T_DEFLATED_WIDE = _bernstein_collocation(10, -0.085, 1.065)


# Indices into the per-tuple statistics row.
STAT_ROOTS = 0  # real resultant roots in range
STAT_CANDIDATES = 1  # (u, v) candidates polished and validated
STAT_PATHS = 2  # accepted paths
STAT_SKIPPED = 3  # 1 when the tuple was rejected before solving (sides, degeneracy)
N_STATS = 4
# Columns of a chunk's statistics (solve_one_bounce_batch): the STAT_ columns summed, then
CHUNK_OVERFLOW = N_STATS  # tuples that found more paths than MAX_PATHS_ONE_BOUNCE (the rest are dropped)
CHUNK_NONFINITE = N_STATS + 1  # tuples with a NaN or Inf in their input (not solved)
CHUNK_COLUMNS = N_STATS + 2


# --- bivariate polynomials: p[i, j] multiplies u^i v^j -------------------------------------


@kernel(inline="always")
def _lin_dot(out, a0, au, av, b0, bu, bv):
    """(a0 + u au + v av) · (b0 + u bu + v bv) as a quadratic in (u, v)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = 0.0
    out[0, 0] = dot(a0, b0)
    out[1, 0] = dot(a0, bu) + dot(au, b0)
    out[0, 1] = dot(a0, bv) + dot(av, b0)
    out[2, 0] = dot(au, bu)
    out[1, 1] = dot(au, bv) + dot(av, bu)
    out[0, 2] = dot(av, bv)


@kernel(inline="always")
def _bcombine(out, d, ca, a, cb, b):
    """out = ca a + cb b (total degree d)."""
    for i in range(d + 1):
        for j in range(d + 1 - i):
            out[i, j] = ca * a[i, j] + cb * b[i, j]


@kernel(inline="always")
def _bmax(p, d):
    m = 0.0
    for i in range(d + 1):
        for j in range(d + 1 - i):
            m = max(m, abs(p[i, j]))
    return m


# --- the resultant in v -------------------------------------------------------------------


@kernel(inline="always")
def _resultant_from_b_values(a2, a1, a0, b_at_nodes, k, nb):
    """Res_u(a, b) at one v, from the u-roots of a = a2 u² + a1 u + a0 and b_i(v) =
    b_at_nodes[NODE_B + i, k] (see the module docstring).

    Real roots q / a2 and a0 / q (q = -(a1 + sign(a1) √disc) / 2): Res = B(q, a2) b(a0 / q),
    B(x, y) = Σ b_i x^i y^(nb-i) the homogeneous form, exact as a2 -> 0.  Complex roots ρ, ρ̄
    (then a2 ≠ 0): Res = a2^nb |b(ρ)|², evaluated with ρ √|a2| (modulus √|a0|).
    """
    disc = a1 * a1 - 4.0 * a2 * a0
    if disc >= 0.0:
        q = -0.5 * (a1 + math.copysign(math.sqrt(disc), a1))
        if q == 0.0:
            # a1 = 0 and a2 a0 = 0: a = a2 u² (double root 0) or the constant a0
            if a2 != 0.0:
                return a2 ** nb * b_at_nodes[NODE_B, k] * b_at_nodes[NODE_B, k]
            return a0 ** nb * b_at_nodes[NODE_B + nb, k] * b_at_nodes[NODE_B + nb, k]
        # B(q, a2) and b(a0 / q) in one loop (two independent Horner chains)
        rho = a0 / q
        far = b_at_nodes[NODE_B + nb, k]
        near = far
        p = 1.0
        for i in range(nb - 1, -1, -1):
            p *= a2
            far = far * q + b_at_nodes[NODE_B + i, k] * p
            near = near * rho + b_at_nodes[NODE_B + i, k]
        return far * near
    s = math.sqrt(abs(a2))
    zr = -a1 / (2.0 * a2) * s
    zi = math.sqrt(-disc) / (2.0 * a2) * s
    ar = b_at_nodes[NODE_B + nb, k]
    ai = 0.0
    p = 1.0
    for i in range(nb - 1, -1, -1):
        p *= s
        ar, ai = ar * zr - ai * zi + b_at_nodes[NODE_B + i, k] * p, ar * zi + ai * zr
    val = ar * ar + ai * ai
    if a2 < 0.0 and nb % 2 == 1:
        val = -val
    return val


# Rows of the node scratch of ``resultant_at_nodes`` (one column per node).
NODE_V = 0  # v_k
NODE_B = 1  # rows NODE_B + i: b_i(v_k), i = 0..6
NODE_A1 = 8
NODE_A0 = 9
NODE_DISC = 10
NODE_Q = 11
NODE_RHO = 12
NODE_FAR = 13
NODE_NEAR = 14
NODE_ROWS = 15


@kernel(refcounted=False, error_model="numpy")
def resultant_at_nodes(a, b, nb, tb, origin, width, nodes, node_scratch, values):
    """values[k] = Res_u(a, b)(v_k), v_k = origin + width nodes[k] (eq 28-30, evaluated as in
    ``_resultant_from_b_values``, with the same arithmetic per node).

    ``node_scratch`` has NODE_ROWS rows of at least len(nodes) (see the NODE_ constants).
    Each step runs over all nodes, the nodes innermost: one node's Horner chains wait on
    every multiply-add, a dozen independent ones keep the CPU busy and vectorise.  Nodes
    where a's u-roots are complex, or q = 0, are finished one by one.  error_model="numpy":
    no zero-division checks in the loops (the one division is guarded).
    """
    count = nodes.shape[0]
    vs = node_scratch[NODE_V]
    for k in range(count):
        vs[k] = origin + width * nodes[k]
    for i in range(nb + 1):
        bi = node_scratch[NODE_B + i]
        for k in range(count):
            bi[k] = 0.0
        for j in range(tb - i, -1, -1):
            c = b[i, j]
            for k in range(count):
                bi[k] = bi[k] * vs[k] + c
    a2 = a[2, 0]
    a1s = node_scratch[NODE_A1]
    a0s = node_scratch[NODE_A0]
    discs = node_scratch[NODE_DISC]
    qs = node_scratch[NODE_Q]
    rhos = node_scratch[NODE_RHO]
    fars = node_scratch[NODE_FAR]
    nears = node_scratch[NODE_NEAR]
    top = node_scratch[NODE_B + nb]
    for k in range(count):
        v = vs[k]
        a1 = a[1, 0] + a[1, 1] * v
        a0 = a[0, 0] + (a[0, 1] + a[0, 2] * v) * v
        disc = a1 * a1 - 4.0 * a2 * a0
        q = -0.5 * (a1 + math.copysign(math.sqrt(max(disc, 0.0)), a1))
        a1s[k] = a1
        a0s[k] = a0
        discs[k] = disc
        qs[k] = q
        rhos[k] = a0 / q if q != 0.0 else 0.0
        fars[k] = top[k]
        nears[k] = top[k]
    # B(q, a2) and b(a0 / q) at the nodes with real u-roots (the others are redone below)
    p = 1.0
    for i in range(nb - 1, -1, -1):
        p *= a2
        bi = node_scratch[NODE_B + i]
        for k in range(count):
            fars[k] = fars[k] * qs[k] + bi[k] * p
            nears[k] = nears[k] * rhos[k] + bi[k]
    for k in range(count):
        if discs[k] >= 0.0 and qs[k] != 0.0:
            values[k] = fars[k] * nears[k]
        else:
            values[k] = _resultant_from_b_values(a2, a1s[k], a0s[k], node_scratch, k, nb)


@kernel(refcounted=False)
def resultant_bernstein(a, b, nb, tb, origin, width, v_double, b_at_nodes, values, out):
    """Bernstein coefficients on s ∈ [0, 1] of r(s) = Res_u(a, b)(origin + width s), divided by
    (v - v_double)^m when ``v_double`` is finite (m = 1 for R, 2 for T: ``double_point_v``);
    returns the degree (2 tb - m: 8 or 7 for R, 12 or 10 for T).

    The resultant is evaluated at the Chebyshev nodes (``resultant_at_nodes``, each value to
    a few ulps) and interpolated (eq 28-30 give the same polynomial).  Expanding it
    symbolically instead cancels: where b is small along the conic next to a path (an
    endpoint close to a large triangle, a grazing refraction) the power coefficients carried
    absolute errors far above the resultant's values there.  The division is exact (the
    factor divides the resultant); it is done on the node values, from the node set whose
    nodes lie farther from v_double.  ``b_at_nodes``: scratch for ``resultant_at_nodes``.
    """
    # each call names its tables directly: as compile-time constants their sizes let the compiler
    # unroll and vectorise the node loops (tables picked at run time cost 8 % of a planted solve)
    if not np.isfinite(v_double):
        if tb == 4:
            return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 0, NODES_R, TO_BERNSTEIN_R,
                                          b_at_nodes, values, out)
        return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 0, NODES_T, TO_BERNSTEIN_T,
                                      b_at_nodes, values, out)
    s = (v_double - origin) / width
    if tb == 4:
        if _nearest_node(NODES_R_DEFLATED, s) >= _nearest_node(NODES_R_DEFLATED_WIDE, s):
            return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 1, NODES_R_DEFLATED,
                                          TO_BERNSTEIN_R_DEFLATED, b_at_nodes, values, out)
        return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 1, NODES_R_DEFLATED_WIDE,
                                      TO_BERNSTEIN_R_DEFLATED_WIDE, b_at_nodes, values, out)
    if _nearest_node(NODES_T_DEFLATED, s) >= _nearest_node(NODES_T_DEFLATED_WIDE, s):
        return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 2, NODES_T_DEFLATED,
                                      TO_BERNSTEIN_T_DEFLATED, b_at_nodes, values, out)
    return _interpolate_resultant(a, b, nb, tb, origin, width, v_double, 2, NODES_T_DEFLATED_WIDE,
                                  TO_BERNSTEIN_T_DEFLATED_WIDE, b_at_nodes, values, out)


@kernel(inline="always")
def _nearest_node(nodes, s):
    """Distance from s to the nearest of ``nodes``."""
    d = math.inf
    for k in range(nodes.shape[0]):
        d = min(d, abs(nodes[k] - s))
    return d


@kernel(inline="always")
def _interpolate_resultant(a, b, nb, tb, origin, width, v_double, multiplicity, nodes, to_bernstein, b_at_nodes,
                           values, out):
    """``resultant_bernstein`` with one node set: values at the nodes, divided by
    (v - v_double)^multiplicity, times the inverse collocation matrix."""
    resultant_at_nodes(a, b, nb, tb, origin, width, nodes, b_at_nodes, values)
    deg = nodes.shape[0] - 1
    if multiplicity > 0:
        for k in range(deg + 1):
            d = origin + width * nodes[k] - v_double
            values[k] /= d if multiplicity == 1 else d * d
    for i in range(deg + 1):
        acc = 0.0
        for k in range(deg + 1):
            acc += to_bernstein[i, k] * values[k]
        out[i] = acc
    return deg


@kernel(refcounted=False)
def double_point_v(a, f3, g):
    """v of the double point of the square form (T) / simple root of the product form (R), or
    NaN when there is none to divide out.

    With the fixed projection vector C, t = n × C, f3 = d0·t = C·(d0 × n) and g = w·t =
    C·(w × n).  On the conic a = 0 the vectors d0, w, n are coplanar, so d0 × n = α (w × n)
    and f3 = α g, d1·t = (1 - α) g: where the line g = 0 (g is linear) meets the conic away
    from the point where n ∥ w, both d0·t and d1·t vanish.  There the square form eq (10)
    has a double zero and the product form eq (13) a simple one, for any η: a root of the
    resultant that is never a path (the plane of incidence there contains C), and as a double
    root the one that rounding splits into a near pair no isolation separates cheaply.
    The line meets the conic where D(v) = Res_u(a, g) = a2 c² - a1 c g_u + a0 g_u² vanishes
    (c = g00 + g01 v); of its two roots the double point is the one where f3 vanishes too.
    The caller divides it out only within DOUBLE_POINT_REACH of [0, 1] (a double root farther
    out splits no pair inside) and only from the resultant of the untrimmed b (``_solve_system``:
    with negligible leading u-terms dropped it is no exact double root).  Tested in
    tests/solver/test_solver_double_point.py against an independent evaluation of the resultant.
    """
    gu = g[1, 0]
    gv = g[0, 1]
    g0 = g[0, 0]
    if not abs(gu) > 1e-8 * (abs(g0) + abs(gv)):
        return math.nan  # flat normals (g constant) or a line along u: nothing to divide out
    a20 = a[2, 0]
    d2 = a20 * gv * gv - a[1, 1] * gv * gu + a[0, 2] * gu * gu
    d1 = 2.0 * a20 * g0 * gv - (a[1, 0] * gv + a[1, 1] * g0) * gu + a[0, 1] * gu * gu
    d0 = a20 * g0 * g0 - a[1, 0] * g0 * gu + a[0, 0] * gu * gu
    best = math.nan
    best_size = DOUBLE_POINT_F3
    for k in range(2):
        if d2 == 0.0:
            if k == 1 or d1 == 0.0:
                break
            v = -d0 / d1
        else:
            disc = d1 * d1 - 4.0 * d2 * d0
            if disc < 0.0:
                break
            q = -0.5 * (d1 + math.copysign(math.sqrt(disc), d1))
            if k == 0:
                v = q / d2
            elif q != 0.0:
                v = d0 / q
            else:
                break
        u = -(g0 + gv * v) / gu
        size = _relative_size(f3, 2, u, v)
        if np.isfinite(v) and size < best_size:
            best = v
            best_size = size
    return best


@kernel(refcounted=False)
def solve_one_bounce_tuple(refract, x0, x2, tri_p, tri_n, eta, stop_after, scratch_biv, scratch_uni, chain, lists, stack, root_buf, out_uv, stats):
    """All admissible one-bounce paths of one tuple; returns how many were written to out_uv.

    ``stop_after`` cuts the pipeline for stage timing in the benchmark: 1 = polynomials and
    resultant only, 2 = also the v roots, 0 = everything.  The corners are relabelled first
    (``elimination_labelling``) so that u is eliminated along a direction where the
    coplanarity conic is not nearly linear; the paths come back in the caller's barycentrics.
    """
    for k in range(N_STATS):
        stats[k] = 0
    q0 = row(tri_p, 0)
    q1 = row(tri_p, 1)
    q2 = row(tri_p, 2)
    k0 = row(tri_n, 0)
    k1 = row(tri_n, 1)
    k2 = row(tri_n, 2)
    # The side tests of _solve_labelled first, in the caller's labelling: most tuples of an
    # unculled batch end here, before the labelling costs anything.
    ok, ng, length, side0, side2 = endpoint_sides(x0, x2, q0, sub(q1, q0), sub(q2, q0), eta)
    if not ok or (side0 * side2 < 0.0) != refract:
        stats[STAT_SKIPPED] = 1
        return 0
    labelling = elimination_labelling(x0, x2, q0, q1, q2, k0, k1, k2)
    if labelling == 0:
        return _solve_labelled(refract, x0, x2, q0, q1, q2, k0, k1, k2, eta, True, ng, length, side0, side2,
                               stop_after, scratch_biv, scratch_uni,
                               chain, lists, stack, root_buf, out_uv, stats)
    if labelling == 1:
        # corners (p0, p2, p1): u' = v, v' = u
        count = _solve_labelled(refract, x0, x2, q0, q2, q1, k0, k2, k1, eta, False, ng, length, side0, side2,
                                stop_after, scratch_biv, scratch_uni,
                                chain, lists, stack, root_buf, out_uv, stats)
        for q in range(min(count, out_uv.shape[0])):
            up = out_uv[q, 0]
            out_uv[q, 0] = out_uv[q, 1]
            out_uv[q, 1] = up
        return count
    # corners (p1, p2, p0): x = p1 + u' (p2 - p1) + v' (p0 - p1), so u = 1 - u' - v', v = u'
    count = _solve_labelled(refract, x0, x2, q1, q2, q0, k1, k2, k0, eta, False, ng, length, side0, side2,
                            stop_after, scratch_biv, scratch_uni,
                            chain, lists, stack, root_buf, out_uv, stats)
    for q in range(min(count, out_uv.shape[0])):
        up = out_uv[q, 0]
        vp = out_uv[q, 1]
        out_uv[q, 0] = 1.0 - up - vp
        out_uv[q, 1] = up
    return count


@kernel(refcounted=False)
def elimination_labelling(x0, x2, q0, q1, q2, k0, k1, k2):
    """Which corner labelling the resultant eliminates u in: 0 = (p0, p1, p2), 1 = (p0, p2, p1),
    2 = (p1, p2, p0), i.e. along the edge direction d = (1, 0), (0, 1) or (-1, 1) in (u, v).

    Eliminating u along d goes wrong where the coplanarity conic a = 0 turns parallel to d
    inside the triangle (∂a/∂d changes sign there): with a small leading coefficient Q(d)
    one u-root of a(·, v) runs far away (|ρ| ~ |a1(v)| / |Q(d)|) and Res = Q^n b(ρ1) b(ρ2)
    spans many orders of magnitude over v, and with a nearly linear a (flat normals) the
    whole triangle maps to a sliver of v; either way the v root of a path is at the
    resultant's rounding floor, and u = ρ(v) turns its error into a miss.  A grazing
    refraction into a dense medium is the typical case.  Score of d: |Q(d)| plus, when
    ∂a/∂d (linear in u, v) keeps its sign over the triangle, its smallest size at the corners.
    The default labelling is kept unless its score is below SWITCH_RATIO of the best one.
    """
    w = sub(x2, x0)
    e1 = sub(q1, q0)
    e2 = sub(q2, q0)
    m1 = sub(k1, k0)
    m2 = sub(k2, k0)
    c0 = cross(sub(q0, x0), w)
    c1 = cross(e1, w)
    c2 = cross(e2, w)
    a20 = dot(c1, m1)
    a02 = dot(c2, m2)
    a11 = dot(c1, m2) + dot(c2, m1)
    a10 = dot(c0, m1) + dot(c1, k0)
    a01 = dot(c0, m2) + dot(c2, k0)
    # ∂a/∂u and ∂a/∂v at the corners (0, 0), (1, 0), (0, 1)
    du0 = a10
    du1 = a10 + 2.0 * a20
    du2 = a10 + a11
    dv0 = a01
    dv1 = a01 + a11
    dv2 = a01 + 2.0 * a02
    score_u = abs(a20) + _fold_free_size(du0, du1, du2)
    score_v = abs(a02) + _fold_free_size(dv0, dv1, dv2)
    score_s = abs(a20 - a11 + a02) + _fold_free_size(dv0 - du0, dv1 - du1, dv2 - du2)
    best = max(score_v, score_s)
    if not (score_u < SWITCH_RATIO * best):
        return 0
    return 1 if score_v >= score_s else 2


@kernel(inline="always")
def _fold_free_size(g0, g1, g2):
    """Smallest |g| over the corners of a linear function with corner values g0, g1, g2, or 0
    when it changes sign on the triangle."""
    if (g0 > 0.0 and g1 > 0.0 and g2 > 0.0) or (g0 < 0.0 and g1 < 0.0 and g2 < 0.0):
        return min(abs(g0), min(abs(g1), abs(g2)))
    return 0.0


@kernel(refcounted=False)
def _solve_labelled(refract, x0, x2, q0, q1, q2, k0, k1, k2, eta, sides_known, ng, length, side0, side2, stop_after,
                    scratch_biv, scratch_uni, chain, lists, stack, root_buf, out_uv, stats):
    """The solve of ``solve_one_bounce_tuple`` for corners q0, q1, q2 with normals k0, k1, k2;
    ``sides_known``: (ng, length, side0, side2) are endpoint_sides' for these corners already
    (the caller's own labelling), else they are recomputed here."""
    p0 = q0
    e1 = sub(q1, q0)
    e2 = sub(q2, q0)
    n0 = k0
    m1 = sub(k1, k0)
    m2 = sub(k2, k0)
    if not sides_known:
        # the labelling's own edges set the scale (length) of the local frame below
        ok, ng, length, side0, side2 = endpoint_sides(x0, x2, p0, e1, e2, eta)
        if not ok or (side0 * side2 < 0.0) != refract:
            stats[STAT_SKIPPED] = 1
            return 0
    n_mean = madd(madd(scale(n0, 3.0), m1, 1.0), m2, 1.0)
    if norm(n_mean) == 0.0:
        stats[STAT_SKIPPED] = 1
        return 0

    # Local frame: origin p0, unit scale, so coefficients are O(1) for any scene size.
    inv_l = 1.0 / length
    E1 = scale(e1, inv_l)
    E2 = scale(e2, inv_l)
    A = scale(sub(x0, p0), inv_l)
    B = scale(sub(x2, p0), inv_l)
    w = sub(B, A)
    # Projection / tangent vector: normal of the plane of incidence at the mean normal.
    C = cross(w, n_mean)
    lc = norm(C)
    if not lc > 1e-9 * norm(w) * norm(n_mean):
        C = cross(E1, n_mean)
        lc = norm(C)
    C = scale(C, 1.0 / lc)

    zero = (0.0, 0.0, 0.0)
    minus_a = scale(A, -1.0)
    t0 = cross(n0, C)
    tu = cross(m1, C)
    tv = cross(m2, C)
    a_poly = scratch_biv[0]
    f1 = scratch_biv[1]
    f3 = scratch_biv[2]
    g = scratch_biv[3]
    h = scratch_biv[4]
    b_poly = scratch_biv[5]
    t1 = scratch_biv[6]
    t2 = scratch_biv[7]
    t3 = scratch_biv[8]
    t4 = scratch_biv[9]
    t5 = scratch_biv[10]
    t6 = scratch_biv[11]
    t7 = scratch_biv[12]
    # a = ((x1 - x0) × w) · n                                           eq (6)
    _lin_dot(a_poly, cross(minus_a, w), cross(E1, w), cross(E2, w), n0, m1, m2)
    # f1 = d0 · n,  f3 = d0 · t,  g = w · t,  h = w · n   with d0 = x1 - x0, d1 = w - d0
    _lin_dot(f1, minus_a, E1, E2, n0, m1, m2)
    _lin_dot(f3, minus_a, E1, E2, t0, tu, tv)
    _lin_dot(g, w, zero, zero, t0, tu, tv)
    _lin_dot(h, w, zero, zero, n0, m1, m2)
    max_a = _bmax(a_poly, 2)
    if not np.isfinite(max_a):
        stats[STAT_SKIPPED] = 1
        return 0
    # Size a's terms could have: |x1 - x0| |w| |n| over the triangle (local units).
    natural_a = (norm(A) + 1.0) * norm(w) * (norm(n0) + norm(m1) + norm(m2))
    if max_a <= 1e-13 * natural_a:
        # Coplanarity holds everywhere up to rounding (flat normals along x2 - x0): only a
        # path at normal incidence is possible.
        count = _on_axis_candidate(x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv, 0, stats)
        stats[STAT_PATHS] = count
        return count
    for i in range(3):
        for j in range(3 - i):
            if abs(a_poly[i, j]) <= NEGLIGIBLE * max_a:
                a_poly[i, j] = 0.0
    if _conic_misses_triangle(a_poly, max_a):
        stats[STAT_SKIPPED] = 1
        return 0

    v_double = double_point_v(a_poly, f3, g)
    if not (v_double >= -DOUBLE_POINT_REACH and v_double <= 1.0 + DOUBLE_POINT_REACH):
        v_double = math.nan  # a double root that far from [0, 1] splits no root pair inside it
    count = 0
    if not refract:
        # Product form, eq (13): (d0·n)(d1·t) + (d0·t)(d1·n) = f1 g + f3 h - 2 f1 f3.
        mul_quadratics(f1, g, t1)
        mul_quadratics(f3, h, t2)
        mul_quadratics(f1, f3, t3)
        for i in range(5):
            for j in range(5 - i):
                b_poly[i, j] = t1[i, j] + t2[i, j] - 2.0 * t3[i, j]
        count = _solve_system(a_poly, max_a, b_poly, 4, v_double, False, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                              stop_after, scratch_uni, chain, lists, stack, root_buf, out_uv, count, stats)
        if stop_after == 0 and _singular_point_near_triangle(a_poly):
            count = _on_axis_candidate(x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv, count, stats)
        stats[STAT_PATHS] = count
        return count

    # Square form, eq (10): eta_in² |d1|² (d0·t)² - eta_out² |d0|² (d1·t)².
    minus_e1 = scale(E1, -1.0)
    minus_e2 = scale(E2, -1.0)
    _lin_dot(t1, minus_a, E1, E2, minus_a, E1, E2)  # |d0|²
    _lin_dot(t2, B, minus_e1, minus_e2, B, minus_e1, minus_e2)  # |d1|², d1 = B - u E1 - v E2
    mul_quadratics(f3, f3, t3)  # (d0·t)²
    _bcombine(t4, 2, 1.0, g, -1.0, f3)  # d1·t
    mul_quadratics(t4, t4, t5)  # (d1·t)²
    mul_quadratic_quartic(t2, t3, t6)  # |d1|² (d0·t)²
    mul_quadratic_quartic(t1, t5, t7)  # |d0|² (d1·t)²
    # Which side holds the medium follows the shading normal at the solution (CONTRACT.md).
    # ng·n is linear in (u, v), so its signs at the vertices tell whether the normal field
    # turns over the face; then both IOR assignments are solved.
    s0 = dot(ng, n0)
    s1 = dot(ng, k1)
    s2 = dot(ng, k2)
    any_front = s0 > 0.0 or s1 > 0.0 or s2 > 0.0
    any_back = s0 < 0.0 or s1 < 0.0 or s2 < 0.0
    for outward in (True, False):
        if (outward and not any_front) or (not outward and not any_back):
            continue
        from_outside = (side0 > 0.0) == outward
        eta_in = 1.0 if from_outside else eta
        eta_out = eta if from_outside else 1.0
        _bcombine(b_poly, 6, eta_in * eta_in, t6, -eta_out * eta_out, t7)
        count = _solve_system(a_poly, max_a, b_poly, 6, v_double, True, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                              stop_after, scratch_uni, chain, lists, stack, root_buf, out_uv, count, stats)
    if stop_after == 0 and _singular_point_near_triangle(a_poly):
        count = _on_axis_candidate(x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv, count, stats)
    stats[STAT_PATHS] = count
    return count


@kernel(refcounted=False)
def _solve_system(a_poly, max_a, b_poly, total_b, v_double, refract, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                  stop_after, scratch_uni, chain, lists, stack, root_buf, out_uv, count, stats):
    """Roots of {a = 0, b = 0} in the triangle -> validated paths appended to out_uv.

    Returns the new path count; candidates that converge onto a stored path are merged,
    keeping the smaller residual.
    """
    # Effective u-degree of b: exactly-zero leading terms (flat normals) must not stay as
    # rounding noise, or the resultant would be noise too.
    max_b = _bmax(b_poly, total_b)
    if not (max_b > 0.0) or not np.isfinite(max_b):
        return count
    nb = total_b
    while nb > 0:
        big = 0.0
        for j in range(total_b - nb + 1):
            big = max(big, abs(b_poly[nb, j]))
        if big > NEGLIGIBLE * max_b:
            break
        for j in range(total_b - nb + 1):
            b_poly[nb, j] = 0.0
        nb -= 1

    res = scratch_uni[15]
    v_roots = root_buf[0]
    if nb == 0:
        # b does not depend on u: its own roots in v ∈ [-V_MARGIN, 1 + V_MARGIN] are the
        # candidates, found as roots in s ∈ [0, 1] of b(-V_MARGIN + (1 + 2 V_MARGIN) s), so
        # the root finder's [0, 1] fast path applies.
        deg_r = total_b
        for k in range(deg_r + 1):
            res[k] = b_poly[0, k]
        if stop_after == 1:
            return count
        _shift_to_unit_interval(res, deg_r, -V_MARGIN, 1.0 + 2.0 * V_MARGIN)
        n_v = roots_in_unit_interval(res, deg_r, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, lists, stack, v_roots)
        for iv in range(n_v):
            v_roots[iv] = -V_MARGIN + (1.0 + 2.0 * V_MARGIN) * v_roots[iv]
    else:
        # the double point divides the resultant of the whole b only: with negligible leading
        # u-terms trimmed off b (a far u-root) it is no exact double root any more
        v_divided = v_double if nb == total_b else math.nan
        if stop_after == 1:
            resultant_bernstein(a_poly, b_poly, nb, total_b, -V_MARGIN, 1.0 + 2.0 * V_MARGIN, v_divided,
                                scratch_uni[NODE_SCRATCH:], scratch_uni[1], res)
            return count
        n_v = _resultant_v_roots(a_poly, b_poly, nb, total_b, v_divided, scratch_uni, chain, lists, stack, v_roots)
    stats[STAT_ROOTS] += n_v
    if stop_after == 2:
        return count
    u_roots = root_buf[1]
    b_at_v = root_buf[2]
    row_value = scratch_uni[ROW_B_VALUE]
    row_size = scratch_uni[ROW_B_SIZE]
    for iv in range(n_v):
        vr = v_roots[iv]
        rows_at_vr = False  # row_value / row_size hold b(·, vr) (_rows_at_v), computed when first needed
        a2 = a_poly[2, 0]
        a1 = a_poly[1, 0] + a_poly[1, 1] * vr
        a0 = a_poly[0, 0] + (a_poly[0, 1] + a_poly[0, 2] * vr) * vr
        u_hi = 1.0 - vr + V_MARGIN
        if abs(a2) + abs(a1) > 1e-10 * max_a:
            # both real u-roots of a(·, v*), then those in range
            all_u = root_buf[2]
            n_all = _quadratic_u_roots(a2, a1, a0, -math.inf, math.inf, all_u)
            n_u = 0
            for k in range(n_all):
                if not (all_u[k] >= -V_MARGIN and all_u[k] <= u_hi):
                    continue
                if n_all == 2:
                    if not rows_at_vr:
                        _rows_at_v(b_poly, total_b, vr, row_value, row_size)
                        rows_at_vr = True
                    if _spurious_u_root(row_value, row_size, total_b, all_u[k], all_u[1 - k]):
                        continue
                u_roots[n_u] = all_u[k]
                n_u += 1
        else:
            # a vanishes identically in u at this v: u comes from b(u, v*) = 0.
            for i in range(nb + 1):
                acc = 0.0
                for j in range(total_b - i, -1, -1):
                    acc = acc * vr + b_poly[i, j]
                b_at_v[i] = acc
            n_u = roots_in_interval(b_at_v, nb, -V_MARGIN, u_hi, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, lists, u_roots)
        for iu in range(n_u):
            stats[STAT_CANDIDATES] += 1
            ok, uu, vv, err, sig, j11, j12, j22 = polish_validate_normal_matrix(
                u_roots[iu], vr, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, POLISH_STEPS, ACCEPT_RESIDUAL,
                CANDIDATE_REACH)
            if not ok and err == FAR_START and not rows_at_vr:
                _rows_at_v(b_poly, total_b, vr, row_value, row_size)
                rows_at_vr = True
            if not ok and (err != FAR_START or _relative_size_from_rows(row_value, row_size, total_b, u_roots[iu])
                           > INEXACT_ROOT):
                # Fallback: Newton on the exact polynomial system, which stays smooth where
                # the path-space residual is undefined (a resultant root a hair past the
                # critical angle of a grazing refraction), then polish again.  Not first:
                # between two close roots it may jump to the neighbour and lose one.  For a
                # candidate rejected as far from any path only when it is an inexact root of
                # the system (near grazing the resultant's root can be off by 1e-4): at an
                # exact one Newton would not move it.
                uu, vv = _refine_on_polynomials(a_poly, b_poly, total_b, u_roots[iu], vr)
                ok, uu, vv, err, sig, j11, j12, j22 = polish_validate_normal_matrix(
                    uu, vv, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, POLISH_STEPS, ACCEPT_RESIDUAL,
                    CANDIDATE_REACH)
            if not ok:
                continue
            before = count
            count = store_path(uu, vv, err, sig, root_buf, out_uv, count)
            if count == before:
                continue
            count = _probe_fold(uu, vv, j11, j12, j22, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv,
                                count)
    return count


@kernel(refcounted=False)
def _resultant_v_roots(a_poly, b_poly, nb, total_b, v_double, scratch_uni, chain, lists, stack, v_roots):
    """Roots in v ∈ [-V_MARGIN, 1 + V_MARGIN] of Res_u(a, b) (its double-point factor divided out
    when ``v_double`` is finite: ``resultant_bernstein``), ascending; returns their count.

    One Bernstein interpolant over the whole range first.  Its coefficients carry errors of
    ~1e-12 of the resultant's largest value there, so where the values at the nodes span more
    than DYNAMIC_RANGE (an endpoint close to a large triangle puts a cluster of near roots
    next to the path, where the resultant is 1e-10 of its size elsewhere) the range is cut in
    SPLIT pieces, each interpolated from its own values, down to SPLIT_DEPTH levels.
    """
    b_at_nodes = scratch_uni[NODE_SCRATCH:]  # see resultant_at_nodes
    values = scratch_uni[1]
    power = scratch_uni[2]
    found = scratch_uni[3]
    piece_lo = scratch_uni[4]
    piece_hi = scratch_uni[5]
    piece_depth = scratch_uni[6]
    res = scratch_uni[15]
    capacity = v_roots.shape[0]
    piece_lo[0] = -V_MARGIN
    piece_hi[0] = 1.0 + V_MARGIN
    piece_depth[0] = 0.0
    top = 1
    n_v = 0
    while top > 0:
        top -= 1
        lo = piece_lo[top]
        hi = piece_hi[top]
        depth = piece_depth[top]
        deg_r = resultant_bernstein(a_poly, b_poly, nb, total_b, lo, hi - lo, v_double, b_at_nodes, values, res)
        if depth < SPLIT_DEPTH:
            big = 0.0
            small = math.inf
            for k in range(deg_r + 1):
                big = max(big, abs(values[k]))
                small = min(small, abs(values[k]))
            if small < DYNAMIC_RANGE * big:
                # pieces pushed right to left so that they come off the stack in ascending order
                for j in range(SPLIT - 1, -1, -1):
                    piece_lo[top] = lo + (hi - lo) * j / SPLIT
                    piece_hi[top] = lo + (hi - lo) * (j + 1) / SPLIT
                    piece_depth[top] = depth + 1.0
                    top += 1
                continue
        n_piece = roots_in_unit_interval_bernstein(res, deg_r, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, lists, stack,
                                                   power, found)
        for j in range(n_piece):
            v = lo + (hi - lo) * found[j]
            if n_v > 0 and v - v_roots[n_v - 1] <= ROOT_X_TOLERANCE:
                continue  # the same root at a piece boundary
            if n_v < capacity:
                v_roots[n_v] = v
                n_v += 1
    return n_v


@kernel(refcounted=False)
def store_path(uu, vv, err, sigma_min, root_buf, out_uv, count):
    """Append (uu, vv) unless it is a path already stored; returns the new count.

    Two polished candidates are one path when they are closer than the residuals can tell
    apart: |Δuv| ≲ (err_a + err_b + rounding) / σ_min(J), and at least SAME_PATH.  In an
    ill-conditioned tuple (small triangle, far endpoints, near a fold) Newton lands anywhere
    on a short segment at rounding-level residual, so the radius grows there (capped at
    NEAR_PATH); two well-pinned paths farther apart than SAME_PATH stay distinct.  The
    copy with the smaller residual is kept.
    """
    for q in range(min(count, out_uv.shape[0])):
        dist = max(abs(out_uv[q, 0] - uu), abs(out_uv[q, 1] - vv))
        sig = min(sigma_min, root_buf[4, q])
        radius = SAME_PATH
        if sig > 0.0:
            radius = max(radius, 4.0 * (err + root_buf[3, q] + 1e-12) / sig)
        else:
            radius = NEAR_PATH
        if dist < min(radius, NEAR_PATH):
            if err < root_buf[3, q]:
                out_uv[q, 0] = uu
                out_uv[q, 1] = vv
                root_buf[3, q] = err
                root_buf[4, q] = sigma_min
            return count
    if count < out_uv.shape[0]:
        out_uv[count, 0] = uu
        out_uv[count, 1] = vv
        root_buf[3, count] = err
        root_buf[4, count] = sigma_min
    return count + 1


@kernel(refcounted=False)
def _probe_fold(u, v, a11, a12, a22, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv, count):
    """Near a fold of the caustic two paths can lie within ~1e-5 of each other and project
    onto one (double) resultant root, so only one of them is a candidate.  When the path's
    Jacobian is nearly singular (a11, a12, a22: J^T J at the polished path (u, v), as the
    polish returns it), polish from a few points along its null direction (FOLD_STEPS, both
    ways) and keep any new path.  The probes are polished, not predicted from the residual
    along that line: near the critical angle of a refraction the partner can lie off the line
    in a curved valley of the residual (tests/solver/test_solver_grazing.py, light leaving
    just under the critical angle).  A probe whose Gauss-Newton step would take it back within
    PROBE_RETURN of its distance to the path is abandoned (most probes: there is no partner, and
    the first step already falls back onto the path; polishing it to the end would only find it
    again)."""
    tr = a11 + a22
    disc = math.sqrt(max(0.0, 0.25 * (a11 - a22) ** 2 + a12 * a12))
    lam_min = 0.5 * tr - disc
    lam_max = 0.5 * tr + disc
    if not (lam_max > 0.0) or lam_min > FOLD_RATIO * lam_max:
        return count
    # Null direction: eigenvector of J^T J for lam_min.
    if abs(a12) > 0.0:
        su, sv = a12, lam_min - a11
    elif a11 <= a22:
        su, sv = 1.0, 0.0
    else:
        su, sv = 0.0, 1.0
    ls = math.sqrt(su * su + sv * sv)
    su /= ls
    sv /= ls
    for k in range(6):
        step = FOLD_STEPS[k // 2] * (1.0 if k % 2 == 0 else -1.0)
        ok2, uu, vv, err, sig, _a11, _a12, _a22 = polish_validate_normal_matrix(
            u + step * su, v + step * sv, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, POLISH_STEPS, ACCEPT_RESIDUAL,
            math.inf, u, v, PROBE_RETURN * FOLD_STEPS[k // 2])
        if not ok2:
            continue
        count = store_path(uu, vv, err, sig, root_buf, out_uv, count)
    return count


@kernel(inline="always")
def _spurious_u_root(row_value, row_size, total_b, u, u_other):
    """Whether the u-root u of a(·, v) is no root of the system although v is a root of the
    resultant: Res = a2^n b(ρ1) b(ρ2) vanishes where b does at one u-root of a(·, v), so u is
    skipped when b is clearly nonzero there (SPURIOUS_B) and the other u-root, in the triangle
    or not, accounts for the resultant's root (its polish would only wander off, or to a path
    found anyway).  b(·, v) is given by its rows at v (``_rows_at_v``); the other root's size is
    evaluated only when the test needs it."""
    return (_relative_size_from_rows(row_value, row_size, total_b, u) > SPURIOUS_B
            and _relative_size_from_rows(row_value, row_size, total_b, u_other) <= SPURIOUS_B)


@kernel(inline="always")
def _relative_size(p, d, u, v):
    """|p(u, v)| / Σ |p_ij u^i v^j| for the bivariate polynomial p of total degree d: how far
    from zero p is at (u, v), against the size its terms give it there (0 when all vanish)."""
    value = 0.0
    size = 0.0
    u_power = 1.0
    for i in range(d + 1):
        row_value, row_size = _row_sums(p, d, i, v)
        value += row_value * u_power
        size += row_size * abs(u_power)
        u_power *= u
    return abs(value) / size if size > 0.0 else 0.0


@kernel(inline="always")
def _row_sums(p, d, i, v):
    """(Σ_j p_ij v^j, Σ_j |p_ij| |v|^j): row i of p at v and the size of its terms."""
    value = 0.0
    size = 0.0
    for j in range(d - i, -1, -1):
        value = value * v + p[i, j]
        size = size * abs(v) + abs(p[i, j])
    return value, size


@kernel(inline="always")
def _rows_at_v(p, d, v, row_value, row_size):
    """The inner sums of ``_relative_size`` at v (``_row_sums`` of every row), for several u at
    one v."""
    for i in range(d + 1):
        row_value[i], row_size[i] = _row_sums(p, d, i, v)


@kernel(inline="always")
def _relative_size_from_rows(row_value, row_size, d, u):
    """``_relative_size`` at (u, v) from the rows of ``_rows_at_v`` at v (the same sums, the same
    bits)."""
    value = 0.0
    size = 0.0
    u_power = 1.0
    for i in range(d + 1):
        value += row_value[i] * u_power
        size += row_size[i] * abs(u_power)
        u_power *= u
    return abs(value) / size if size > 0.0 else 0.0


@kernel(refcounted=False)
def _eval_with_gradient(p, d, u, v):
    """Value and (d/du, d/dv) of the bivariate polynomial p of total degree d."""
    f = 0.0
    fu = 0.0
    fv = 0.0
    ui = 1.0  # u^i
    ui_1 = 0.0  # u^(i-1)
    for i in range(d + 1):
        vj = 1.0  # v^j
        vj_1 = 0.0  # j v^(j-1)
        for j in range(d + 1 - i):
            c = p[i, j]
            f += c * ui * vj
            fv += c * ui * vj_1
            if i > 0:
                fu += c * i * ui_1 * vj
            vj_1 = (j + 1) * vj
            vj *= v
        ui_1 = ui
        ui *= u
    return f, fu, fv


@kernel(refcounted=False)
def _refine_on_polynomials(a, b, db, u, v):
    """A few Newton steps on {a(u,v) = 0, b(u,v) = 0}, kept only while they reduce |a|+|b|."""
    fa, au, av = _eval_with_gradient(a, 2, u, v)
    fb, bu, bv = _eval_with_gradient(b, db, u, v)
    size = abs(fa) + abs(fb)
    for _ in range(4):
        det = au * bv - av * bu
        if det == 0.0 or size == 0.0:
            break
        du = -(fa * bv - av * fb) / det
        dv = -(au * fb - fa * bu) / det
        ga, gau, gav = _eval_with_gradient(a, 2, u + du, v + dv)
        gb, gbu, gbv = _eval_with_gradient(b, db, u + du, v + dv)
        new_size = abs(ga) + abs(gb)
        if not new_size < size:
            break
        u += du
        v += dv
        fa, au, av, fb, bu, bv, size = ga, gau, gav, gb, gbu, gbv, new_size
    return u, v


@kernel(refcounted=False)
def _conic_misses_triangle(a, scale):
    """True when the coplanarity conic a(u, v) = 0 has no point on the triangle.

    The six Bernstein coefficients of the quadratic over the triangle bound its values there
    (convex hull property); if all share one sign, by more than a rounding margin that also
    covers the INSIDE_EPSILON slack at the edges, no path can exist.
    """
    b200 = a[0, 0]
    b020 = a[0, 0] + a[1, 0] + a[2, 0]
    b002 = a[0, 0] + a[0, 1] + a[0, 2]
    b110 = a[0, 0] + 0.5 * a[1, 0]
    b101 = a[0, 0] + 0.5 * a[0, 1]
    b011 = a[0, 0] + 0.5 * (a[1, 0] + a[0, 1] + a[1, 1])
    lo = min(min(b200, b020), min(min(b002, b110), min(b101, b011)))
    hi = max(max(b200, b020), max(max(b002, b110), max(b101, b011)))
    margin = 1e-7 * scale
    return lo > margin or hi < -margin


@kernel(refcounted=False)
def _shift_to_unit_interval(c, deg, origin, width):
    """In place: c(x) -> c(origin + width s), by Taylor shift (Horner, O(deg²))."""
    for i in range(deg):
        for j in range(deg - 1, i - 1, -1):
            c[j] += origin * c[j + 1]
    p = 1.0
    for k in range(deg + 1):
        c[k] *= p
        p *= width


@kernel(refcounted=False)
def _quadratic_u_roots(a2, a1, a0, lo, hi, out):
    """Roots of a2 u² + a1 u + a0 in [lo, hi] (a1 or a2 nonzero); near-double roots kept."""
    if a2 == 0.0:
        u = -a0 / a1
        if u >= lo and u <= hi:
            out[0] = u
            return 1
        return 0
    disc = a1 * a1 - 4.0 * a2 * a0
    if disc < 0.0:
        if disc < -1e-12 * (a1 * a1 + abs(4.0 * a2 * a0)):
            return 0
        disc = 0.0
    sq = math.sqrt(disc)
    q = -0.5 * (a1 + sq) if a1 >= 0.0 else -0.5 * (a1 - sq)
    n = 0
    r1 = q / a2
    if r1 >= lo and r1 <= hi:
        out[n] = r1
        n += 1
    if q != 0.0:
        r2 = a0 / q
        if r2 >= lo and r2 <= hi and (n == 0 or r2 != r1):
            out[n] = r2
            n += 1
    return n


@kernel(refcounted=False)
def _singular_point_near_triangle(a):
    """False when the coplanarity conic a(u, v) has no singular point within SINGULAR_MARGIN of
    the triangle, so that no path at normal incidence can lie in it: there x1 - x0 ∥ w and
    n ∥ w, which zero both ∂a/∂u = (e1 × w)·n + (d0 × w)·m1 and ∂a/∂v.  The singular point
    solves the 2x2 system ∇a = 0; with a (nearly) singular Hessian (a parabola or a line) the
    test cannot tell and answers True."""
    h11 = 2.0 * a[2, 0]
    h12 = a[1, 1]
    h22 = 2.0 * a[0, 2]
    det = h11 * h22 - h12 * h12
    if not abs(det) > 1e-12 * (h11 * h11 + h12 * h12 + h22 * h22):
        return True
    u = (-a[1, 0] * h22 + a[0, 1] * h12) / det
    v = (-a[0, 1] * h11 + a[1, 0] * h12) / det
    return u >= -SINGULAR_MARGIN and v >= -SINGULAR_MARGIN and u + v <= 1.0 + SINGULAR_MARGIN


@kernel(refcounted=False)
def _on_axis_candidate(x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, root_buf, out_uv, count, stats):
    """The path at normal incidence, where x1 lies on the line x0-x2 and n(x1) is along it.

    There the coplanarity conic a = 0 degenerates (identically zero for flat normals, a
    double point otherwise), so the resultant does not isolate this path reliably; the
    candidate is the line's intersection with the triangle's plane, kept when the normal
    there is nearly along the line and the polish validates it.
    """
    ok, u, v = line_crossing_barycentrics(x0, x2, p0, e1, e2, ng)
    if not ok:
        return count
    w = sub(x2, x0)
    if u < -1e-6 or v < -1e-6 or u + v > 1.0 + 1e-6:
        return count
    n = madd(madd(n0, m1, u), m2, v)
    ln = norm(n)
    lw = norm(w)
    if not (ln > 0.0 and lw > 0.0) or norm(cross(n, w)) > 1e-2 * ln * lw:
        return count
    stats[STAT_CANDIDATES] += 1
    ok, uu, vv, err, sig = polish_and_validate(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta, POLISH_STEPS, ACCEPT_RESIDUAL)
    if ok:
        count = store_path(uu, vv, err, sig, root_buf, out_uv, count)
    return count


@parallel_range("x_start", CHUNK)
def solve_one_bounce_batch(refract, x_start, x_end, P, N, eta, stop_after, chunk_index, chunk_uv, chunk_paths,
                           chunk_stats, first, last):
    """Solve every tuple of a batch in parallel (chunks of ``CHUNK`` tuples per worker).

    Chunk c writes its paths densely, in canonical order (by tuple, then u, then v), from row
    c * CHUNK * MAX_PATHS_ONE_BOUNCE of chunk_index (the tuple) and chunk_uv (rows, 2), their
    count to chunk_paths[c], and its statistics summed to chunk_stats[c] (CHUNK_COLUMNS: the
    STAT_ columns, the tuples that found more than MAX_PATHS_ONE_BOUNCE paths, the tuples with a
    NaN or Inf in their input, which are not solved).  So the caller gathers only the paths, not
    a slot table of every tuple.
    """
    n = x_start.shape[0]
    for c in range(first, last):
        biv, uni, chain, lists, stack, roots, slots, swap, stats = make_scratch()
        chunk_paths[c] = _solve_chunk(refract, x_start, x_end, P, N, eta, stop_after, c * CHUNK, min(n, (c + 1) * CHUNK),
                                      c * CHUNK * MAX_PATHS_ONE_BOUNCE, chunk_index, chunk_uv, chunk_stats[c],
                                      biv, uni, chain, lists, stack, roots, slots, swap, stats)


@kernel(refcounted=False)
def _solve_chunk(refract, x_start, x_end, P, N, eta, stop_after, begin, end, first_row, chunk_index, chunk_uv, totals,
                 biv, uni, chain, lists, stack, roots, slots, swap, stats):
    """Tuples [begin, end) of a batch with one set of scratch; their paths from row first_row on
    (see ``solve_one_bounce_batch``); returns how many.  Apart from the batch kernel (which
    allocates the scratch, so it counts references), the per-tuple row views cost no atomic
    reference counting."""
    for k in range(CHUNK_COLUMNS):
        totals[k] = 0
    r = first_row
    for t in range(begin, end):
        if not _finite_tuple(x_start, x_end, P, N, eta, t):
            totals[CHUNK_NONFINITE] += 1
            continue
        count = solve_one_bounce_tuple(
            refract, row(x_start, t), row(x_end, t), P[t, 0], N[t, 0], eta[t], stop_after,
            biv, uni, chain, lists, stack, roots, slots, stats)
        for k in range(N_STATS):
            totals[k] += stats[k]
        kept = min(count, MAX_PATHS_ONE_BOUNCE)
        if count > kept:
            totals[CHUNK_OVERFLOW] += 1
        if kept > 1:
            sort_rows(slots, 0, kept, swap)
        for s in range(kept):
            chunk_index[r] = t
            chunk_uv[r, 0] = slots[s, 0]
            chunk_uv[r, 1] = slots[s, 1]
            r += 1
    return r - first_row


@kernel(inline="always")
def _finite_tuple(x_start, x_end, P, N, eta, t):
    """Whether every input value of tuple t is finite (x * 0 is 0 for finite x, NaN otherwise:
    no branch per value)."""
    acc = eta[t] * 0.0
    for k in range(3):
        acc += x_start[t, k] * 0.0 + x_end[t, k] * 0.0
        for j in range(3):
            acc += P[t, 0, k, j] * 0.0 + N[t, 0, k, j] * 0.0
    return acc == 0.0


@kernel
def make_scratch():
    """Per-worker scratch: bivariate terms, univariate polynomials, root lists, one tuple's path
    slots, a swap row and statistics."""
    biv = np.zeros((13, 7, 7))
    uni = np.zeros((NODE_SCRATCH + NODE_ROWS, 2 * MAX_DEGREE + 2))
    chain = np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1))
    lists = np.zeros((2, MAX_DEGREE + 1))
    stack = np.zeros((STACK_ROWS + 1, MAX_DEGREE + 4))
    roots = np.zeros((5, MAX_DEGREE + 1))
    slots = np.zeros((MAX_PATHS_ONE_BOUNCE, 2))
    swap = np.zeros(2)  # the row sort_rows swaps through
    stats = np.zeros(N_STATS, dtype=np.int64)
    return biv, uni, chain, lists, stack, roots, slots, swap, stats
