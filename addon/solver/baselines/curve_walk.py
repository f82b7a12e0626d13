"""Baseline 3: the coplanarity-curve walk of Dimension-reduction MNEE (Granizo-Hidalgo &
Holzschuch 2024), single refraction (chain "T").

A refracted path x0 -> x1 -> x2 needs x1 - x0, x2 - x1 and the shading normal n(x1) to be
coplanar.  On a triangle with interpolated normals that condition is a conic in the
barycentrics (eq 9-12):

    a(u, v) = n(u, v) · ((x1(u, v) - x0) × (x2 - x0))
            = A u² + B v² + C u v + D u + E v + F = 0,

and over a smooth mesh the conic pieces join into curves (§3.3.3).  The method walks such a
curve and looks for sign changes of a scalar refraction function f on it (eq 16-21):

* conic coefficients per triangle (eq 10-12, :func:`conic_coefficients`), its edge crossings
  (eq 22-24), the tangent from its gradient (eq 13-15) to march along an arc (predictor along
  the tangent, corrector back onto the conic, shorter steps where the curve turns);
* f is the paper's signed sine (eq 19-21) in half-vector form (Walter et al. 2009, §3.1):
  f = h · τ, h = eta_i wi - eta_t wo, τ the surface tangent in the plane of incidence
  (defined under total internal reflection; τ oriented by continuity along the walk, not by
  the curve tangent of eq 20, whose sign flips would fake sign changes);
* bisection along the curve where f changes sign (§3.4.3: the paper bisects sub-triangles,
  here the bracket is the curve piece between two marching samples, halved and projected
  back onto the conic), then the project's Newton polish and validation
  (``one_vertex.polish_and_validate``) and its rule for "one physical path"
  (``one_bounce.store_path``), the same as the other baselines;
* the ellipse wholly inside one triangle (§3.4.4): no edge crossing, the closed curve is
  marched all the way round from a point on it;
* the walk across a caster mesh (§3.3.3, §3.4.2-3.4.3, §4): from M0, where the line x0 -> x2
  crosses the mesh, both ways, through edge crossings into the neighbours of
  :func:`build_adjacency`, until the curve leaves the mesh, closes (back at M0) or a visit
  cap is reached; the ray-differential irradiance of a path (eq 26-33).

Entry points: :class:`CurveWalkSolver` ("curve", the tuple interface: every conic arc inside
the tuple's triangle plus the closed ellipse) and :func:`walk_mesh` (the paper's use: one
light, receiver points, a whole caster mesh -> (point, triangle, u, v) per path).

It finds the paths on the curve pieces it walks and only those: two roots of f between two
marching samples (a caustic fold) or a component not through M0 / the triangle's edges are
missed; reflection ("R") has no starting point on the curve (§6) and is refused.
"""

import math
import time
from dataclasses import dataclass

import numpy as np

from ..spoly.api import SolveReport, SolveResult, compact_paths, validate_inputs
from ..paths.irradiance import PathIrradiance, fresnel_dielectric
from ..runtime.jit import kernel, parallel_range
from ..spoly.one_bounce import ACCEPT_RESIDUAL, CHUNK, MAX_PATHS_ONE_BOUNCE, POLISH_STEPS, store_path
from ..paths.one_vertex import endpoint_sides, geometric_normal, line_crossing_barycentrics, polish_and_validate, triangle_frame
from ..geometry.vec3 import cross, dot, madd, norm, row, scale, sub

DEFAULT_STEPS = 32  # tuple walk: longest marching step 1/DEFAULT_STEPS in barycentric units
MESH_STEPS = 4  # mesh walk: longest step per triangle 1/MESH_STEPS (f is sampled at entry and exit too)
MAX_TURN_COS = 0.98  # a step may turn the tangent by ~11 degrees at most
MIN_STEP = 1e-10  # marching gives up (singular point of the conic) below this step
MAX_ARC_STEPS = 4096  # steps per arc (per triangle visit)
MAX_ROOTS_PER_ARC = 8
BISECT_TOL = 1e-13  # bracket width (barycentric) at which bisection stops; Newton finishes
MAX_CROSSINGS = 6  # a conic meets the three edges at most twice each
MAX_WALK_TRIANGLES = 1 << 16  # triangle visits per walk direction
MAX_PATHS_MESH = 32  # per receiver point
MESH_CHUNK = 16  # receiver points per parallel work item of the mesh walk (scratch once per chunk)
MAX_STARTS = 16  # line x0 -> x2 crossings of the mesh per receiver point
ON_AXIS = 1e-2  # |n̂ × ŵ| below which M0 is also polished as a normal-incidence candidate

# march status
EXITED = 0
CLOSED = 1
STALLED = 2
CAPPED = 3

# per-tuple statistics
STAT_ARCS = 0  # arcs marched (edge entries, closed ellipses)
STAT_SAMPLES = 1  # evaluations of f while marching
STAT_BRACKETS = 2  # sign changes of f bisected
STAT_CANDIDATES = 3  # candidates polished
STAT_PATHS = 4
STAT_SKIPPED = 5
STAT_CLOSED = 6  # closed ellipses inside the triangle
N_STATS = 7

# per-point statistics of the mesh walk
MSTAT_STARTS = 0
MSTAT_VISITS = 1  # triangle visits
MSTAT_SAMPLES = 2
MSTAT_BRACKETS = 3
MSTAT_CANDIDATES = 4
MSTAT_PATHS = 5
MSTAT_CLOSED = 6  # walks that came back to M0
MSTAT_OVERFLOW = 7
N_MSTATS = 8


# --- the conic (eq 9-15) -------------------------------------------------------------------


@kernel
def conic_coefficients(a0, e1, e2, w, n0, m1, m2):
    """(A, B, C, D, E, F) of the coplanarity conic, eq 10-12.

    a(u, v) = n(u, v) · (d(u, v) × w) with d = x1 - x0 = a0 + u e1 + v e2 (a0 = p0 - x0),
    w = x2 - x0 and n = n0 + u m1 + v m2: eq 9 with the matrices [N] and [Q] of eq 10
    multiplied out (q0 = a0 × w, q1 = e1 × w, q2 = e2 × w are [Q]'s columns up to sign).
    """
    q0 = cross(a0, w)
    q1 = cross(e1, w)
    q2 = cross(e2, w)
    return (dot(m1, q1), dot(m2, q2), dot(m1, q2) + dot(m2, q1),
            dot(n0, q1) + dot(m1, q0), dot(n0, q2) + dot(m2, q0), dot(n0, q0))


@kernel(inline="always")
def _conic(cf, u, v):
    return cf[0] * u * u + cf[1] * v * v + cf[2] * u * v + cf[3] * u + cf[4] * v + cf[5]


@kernel(inline="always")
def _conic_grad(cf, u, v):
    """Gradient of the conic: [M](u, v, 1) of eq 14 (times 2); the tangent is (-gv, gu), eq 15."""
    return 2.0 * cf[0] * u + cf[2] * v + cf[3], 2.0 * cf[1] * v + cf[2] * u + cf[4]


@kernel
def _project(cf, u, v, tol):
    """Newton along the gradient back onto the conic; (ok, u, v)."""
    for _ in range(8):
        val = _conic(cf, u, v)
        if abs(val) <= tol:
            return True, u, v
        gu, gv = _conic_grad(cf, u, v)
        g2 = gu * gu + gv * gv
        if not g2 > 0.0:
            return False, u, v
        u -= val * gu / g2
        v -= val * gv / g2
    return abs(_conic(cf, u, v)) <= 1e3 * tol, u, v


@kernel(inline="always")
def _edge_ends(k):
    """Edge k runs from corner k to corner k+1 (mod 3), corners (0,0), (1,0), (0,1) in (u, v)."""
    if k == 0:
        return 0.0, 0.0, 1.0, 0.0
    if k == 1:
        return 1.0, 0.0, 0.0, 1.0
    return 0.0, 1.0, 0.0, 0.0


@kernel(inline="always")
def _edge_point(k, s):
    ua, va, ub, vb = _edge_ends(k)
    return ua + s * (ub - ua), va + s * (vb - va)


@kernel(inline="always")
def _edge_inside(k, u, v):
    """Signed barycentric distance to edge k's line, >= 0 inside."""
    if k == 0:
        return v
    if k == 1:
        return 1.0 - u - v
    return u


@kernel(inline="always")
def _edge_inward(k):
    if k == 0:
        return 0.0, 1.0
    if k == 1:
        return -1.0, -1.0
    return 1.0, 0.0


@kernel
def _quadratic_roots(c2, c1, c0, size, lo, hi):
    """Real roots of c2 s² + c1 s + c0 in [lo, hi]; (n, r1, r2) with r1 <= r2.  ``size`` is the
    scale of the conic: terms below 1e-14 size count as zero; near-double roots are kept."""
    tiny = 1e-14 * size
    if abs(c2) <= tiny:
        if abs(c1) <= tiny:
            return 0, 0.0, 0.0
        r = -c0 / c1
        if lo <= r <= hi:
            return 1, r, r
        return 0, 0.0, 0.0
    disc = c1 * c1 - 4.0 * c2 * c0
    if disc < 0.0:
        if disc < -1e-12 * (c1 * c1 + abs(4.0 * c2 * c0)):
            return 0, 0.0, 0.0
        disc = 0.0
    sq = math.sqrt(disc)
    q = -0.5 * (c1 + sq) if c1 >= 0.0 else -0.5 * (c1 - sq)
    r1 = q / c2
    r2 = c0 / q if q != 0.0 else r1
    if r2 < r1:
        r1, r2 = r2, r1
    n = 0
    a = 0.0
    b = 0.0
    if lo <= r1 <= hi:
        a = r1
        n = 1
    if lo <= r2 <= hi and (n == 0 or r2 != r1):
        if n == 0:
            a = r2
        else:
            b = r2
        n += 1
    return n, a, b


@kernel
def _edge_roots(cf, size, k):
    """Crossings of the conic with edge k, as parameters s along it (eq 22-24 for the three
    edges: the conic restricted to the segment is a quadratic in s)."""
    ua, va, ub, vb = _edge_ends(k)
    du = ub - ua
    dv = vb - va
    c2 = cf[0] * du * du + cf[1] * dv * dv + cf[2] * du * dv
    c1 = 2.0 * cf[0] * ua * du + 2.0 * cf[1] * va * dv + cf[2] * (ua * dv + va * du) + cf[3] * du + cf[4] * dv
    c0 = _conic(cf, ua, va)
    return _quadratic_roots(c2, c1, c0, size, -1e-12, 1.0 + 1e-12)


# --- the refraction function on the curve (eq 16-21) ---------------------------------------


@kernel
def refraction_f(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, tau_ref):
    """Signed refraction function at barycentrics (u, v): (ok, f, tau).

    f = h · τ with h = eta_i wi - eta_t wo (the generalised half vector) and τ the unit
    tangent of the surface in the plane of incidence (n̂ × (wi × n̂), or with wo where wi is
    along n̂), turned to agree with ``tau_ref`` (the previous sample's τ; zero: any).  On the
    coplanarity curve h lies in the span of n̂ and τ, so f = eta_i sin θi - eta_t sin θt with
    signs: the signed sine of eq 19-21 in half-vector form, zero exactly where h ∥ n̂ (Snell's
    law).  Orienting τ by continuity along the walk replaces eq 20's sign from the curve
    tangent, which flips wherever the tangent lies in the plane of incidence.  The IOR pair
    follows the side x0 is on (CONTRACT.md): outside (IOR 1) into the medium, or the reverse.
    """
    zero = (0.0, 0.0, 0.0)
    di = madd(madd(sub(p0, x0), e1, u), e2, v)
    do = madd(madd(sub(x2, p0), e1, -u), e2, -v)
    n = madd(madd(n0, m1, u), m2, v)
    ln = norm(n)
    li = norm(di)
    lo = norm(do)
    if not (ln > 0.0 and li > 0.0 and lo > 0.0):
        return False, 0.0, zero
    nh = scale(n, 1.0 / ln)
    wi = scale(di, 1.0 / li)
    wo = scale(do, 1.0 / lo)
    ngo = ng if dot(ng, nh) >= 0.0 else scale(ng, -1.0)
    side = -dot(di, ngo)
    if side == 0.0:
        return False, 0.0, zero
    eta_i = 1.0 if side > 0.0 else eta
    eta_t = eta if side > 0.0 else 1.0
    b = cross(wi, nh)
    bo = cross(wo, nh)
    if norm(bo) > norm(b):
        b = bo
    tau = cross(nh, b)
    lt = norm(tau)
    if not lt > 0.0:
        # Both rays along n̂: normal incidence, a path (f = 0) whatever the orientation.
        return True, 0.0, tau_ref
    tau = scale(tau, 1.0 / lt)
    if dot(tau, tau_ref) < 0.0:
        tau = scale(tau, -1.0)
    return True, eta_i * dot(wi, tau) - eta_t * dot(wo, tau), tau


@kernel
def _bisect(cf, tol, ua, va, fa, ta, ub, vb, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta):
    """Bisection along the curve between two curve points with f of opposite signs (``ta``: τ
    at the first): the midpoint of the bracket is projected back onto the conic along its
    gradient (eq 14)."""
    for _ in range(100):
        if max(abs(ua - ub), abs(va - vb)) <= BISECT_TOL:
            break
        ok, um, vm = _project(cf, 0.5 * (ua + ub), 0.5 * (va + vb), tol)
        if not ok:
            break
        okf, fm, tm = refraction_f(um, vm, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, ta)
        if not okf:
            break
        if fm == 0.0:
            return um, vm
        if (fm > 0.0) == (fa > 0.0):
            ua, va, fa, ta = um, vm, fm, tm
        else:
            ub, vb = um, vm
    return 0.5 * (ua + ub), 0.5 * (va + vb)


@kernel
def _exit_point(cf, size, up, vp, uq, vq):
    """Where the arc from (up, vp) (inside) to (uq, vq) (outside) leaves the triangle:
    (edge, s, u, v) at the crossing of the conic with the edges (eq 22-24) nearest to where
    the chord crosses the boundary (all three edges are searched: near a corner the chord
    may cut a different edge from the arc); edge -1 if none."""
    best = 2.0
    edge = -1
    for k in range(3):
        a = _edge_inside(k, up, vp)
        b = _edge_inside(k, uq, vq)
        if b < 0.0:
            lam = 0.0 if a <= 0.0 else a / (a - b)
            if lam < best:
                best = lam
                edge = k
    if edge < 0:
        return -1, 0.0, up, vp
    uc = up + best * (uq - up)
    vc = vp + best * (vq - vp)
    # the chord's own crossing, as a fallback when the conic's crossing is not found
    if edge == 0:
        s = uc
    elif edge == 1:
        s = vc
    else:
        s = 1.0 - vc
    s = min(max(s, 0.0), 1.0)
    ue, ve = _edge_point(edge, s)
    dist = max(abs(uq - up), abs(vq - vp))
    for k in range(3):
        n, r1, r2 = _edge_roots(cf, size, k)
        for j in range(n):
            r = min(max(r1 if j == 0 else r2, 0.0), 1.0)
            ur, vr = _edge_point(k, r)
            d = max(abs(ur - uc), abs(vr - vc))
            if d < dist:
                dist = d
                edge = k
                s = r
                ue = ur
                ve = vr
    return edge, s, ue, ve


@kernel
def _add_root(roots, n_roots, u, v):
    if n_roots < roots.shape[0]:
        roots[n_roots, 0] = u
        roots[n_roots, 1] = v
    return n_roots + 1


@kernel
def _sample(fp, okp, tp, uq, vq, up, vp, cf, tol, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, roots, n_roots, counters):
    """f at the next curve point (uq, vq) (τ continued from ``tp``); a sign change against
    the previous sample (up, vp, fp) is bisected.  Returns (ok, f, tau, n_roots)."""
    okq, fq, tq = refraction_f(uq, vq, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, tp)
    counters[0] += 1
    if okq and okp:
        if fq == 0.0:
            n_roots = _add_root(roots, n_roots, uq, vq)
        elif fq * fp < 0.0:
            counters[1] += 1
            ur, vr = _bisect(cf, tol, up, vp, fp, tp, uq, vq, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta)
            n_roots = _add_root(roots, n_roots, ur, vr)
    return okq, fq, tq, n_roots


@kernel
def _march(cf, size, u, v, du, dv, f_start, ok_start, tau_start, h_max, check_stop, su, sv, min_steps,
           x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, roots, counters):
    """March along the conic arc through (u, v) in direction (du, dv) inside one triangle.

    Predictor along the tangent (eq 14-15), corrector back onto the conic; f is sampled at
    every step and each sign change is bisected (roots written to ``roots``).  Stops when the
    arc leaves the triangle (EXITED, with the exit crossing of eq 22-24 as the last sample),
    when ``check_stop`` and the arc passes (su, sv) again after ``min_steps`` steps (CLOSED:
    a closed curve), or when stepping fails (STALLED: a singular point) or the step cap.
    counters[0] += f samples, counters[1] += brackets.
    Returns (status, edge, s, u_exit, v_exit, n_roots, tau at the last sample).
    """
    tol = 1e-14 * size
    n_roots = 0
    gu, gv = _conic_grad(cf, u, v)
    lt = math.sqrt(gu * gu + gv * gv)
    if not lt > 0.0:
        return STALLED, -1, 0.0, u, v, 0, tau_start
    tu = -gv / lt
    tv = gu / lt
    if tu * du + tv * dv < 0.0:
        tu = -tu
        tv = -tv
    up, vp = u, v
    fp, okp, tp = f_start, ok_start, tau_start
    h = h_max
    steps = 0
    while steps < MAX_ARC_STEPS:
        ok, uq, vq = _project(cf, up + h * tu, vp + h * tv, tol)
        nu = 0.0
        nv = 0.0
        chord = 0.0
        if ok:
            gu, gv = _conic_grad(cf, uq, vq)
            lq = math.sqrt(gu * gu + gv * gv)
            ok = lq > 0.0
            if ok:
                nu = -gv / lq
                nv = gu / lq
                c = nu * tu + nv * tv
                if c < 0.0:
                    nu = -nu
                    nv = -nv
                    c = -c
                chord = math.sqrt((uq - up) ** 2 + (vq - vp) ** 2)
                ahead = (uq - up) * tu + (vq - vp) * tv
                ok = c >= MAX_TURN_COS and 0.5 * h <= chord <= 1.5 * h and ahead > 0.0
        if not ok:
            h *= 0.5
            if h < MIN_STEP:
                return STALLED, -1, 0.0, up, vp, n_roots, tp
            continue
        steps += 1
        if uq < 0.0 or vq < 0.0 or uq + vq > 1.0:
            edge, s, ue, ve = _exit_point(cf, size, up, vp, uq, vq)
            if edge < 0:
                return STALLED, -1, 0.0, up, vp, n_roots, tp
            oke, fe, te, n_roots = _sample(fp, okp, tp, ue, ve, up, vp, cf, tol, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                                           roots, n_roots, counters)
            return EXITED, edge, s, ue, ve, n_roots, te
        if check_stop and steps > min_steps:
            # Closed: the chord p -> q passes the stop point (within a fraction of its length).
            wu = uq - up
            wv = vq - vp
            lam = ((su - up) * wu + (sv - vp) * wv) / (chord * chord)
            if 0.0 <= lam <= 1.0:
                dist = math.sqrt((up + lam * wu - su) ** 2 + (vp + lam * wv - sv) ** 2)
                if dist <= 0.1 * chord + 1e-12:
                    oke, fe, te, n_roots = _sample(fp, okp, tp, su, sv, up, vp, cf, tol, x0, x2, p0, e1, e2, n0, m1, m2,
                                                   ng, eta, roots, n_roots, counters)
                    return CLOSED, -1, 0.0, su, sv, n_roots, te
        okp, fp, tp, n_roots = _sample(fp, okp, tp, uq, vq, up, vp, cf, tol, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                                       roots, n_roots, counters)
        up, vp = uq, vq
        tu, tv = nu, nv
        h = min(h_max, 1.5 * h)
    return CAPPED, -1, 0.0, up, vp, n_roots, tp


@kernel
def _local_conic(x0, x2, p0, e1, e2, n0, m1, m2):
    """Conic coefficients in the triangle's local unit (origin p0, longest edge 1), so they are
    O(1) for any scene size; returns (cf, natural size of its terms)."""
    length = max(norm(e1), norm(e2))
    inv_l = 1.0 / length
    a0 = scale(sub(p0, x0), inv_l)
    w = scale(sub(x2, x0), inv_l)
    cf = conic_coefficients(a0, scale(e1, inv_l), scale(e2, inv_l), w, n0, m1, m2)
    natural = (norm(a0) + 1.0) * norm(w) * (norm(n0) + norm(m1) + norm(m2))
    return cf, natural


@kernel
def _conic_misses_triangle(cf, margin):
    """True when the six Bernstein coefficients of the conic over the triangle share one sign
    (by more than ``margin``): no point of the triangle is on the curve."""
    b200 = cf[5]
    b020 = cf[0] + cf[3] + cf[5]
    b002 = cf[1] + cf[4] + cf[5]
    b110 = cf[5] + 0.5 * cf[3]
    b101 = cf[5] + 0.5 * cf[4]
    b011 = cf[5] + 0.5 * (cf[3] + cf[4] + cf[2])
    lo = min(min(b200, b020), min(min(b002, b110), min(b101, b011)))
    hi = max(max(b200, b020), max(max(b002, b110), max(b101, b011)))
    return lo > margin or hi < -margin


# --- per tuple: the walk restricted to one triangle -----------------------------------------


@kernel
def _polish_store(ur, vr, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, buf, out_uv, count, stats):
    stats[STAT_CANDIDATES] += 1
    ok, uu, vv, err, sig = polish_and_validate(ur, vr, x0, x2, p0, e1, e2, n0, m1, m2, ng, True, eta,
                                               POLISH_STEPS, ACCEPT_RESIDUAL)
    if ok:
        count = store_path(uu, vv, err, sig, buf, out_uv, count)
    return count


@kernel
def walk_tuple(x0, x2, tri_p, tri_n, eta, h_max, roots, crossings, counters, buf, out_uv, stats):
    """All paths the curve walk finds in one (x0, triangle, x2) tuple; returns the count.

    Every arc of the conic inside the triangle is entered at an edge crossing (eq 22-24) and
    marched to its exit crossing (marked as used, so no arc is walked twice); with no
    crossing at all an ellipse may lie wholly inside the triangle (§3.4.4, Fig 5a / 6): then
    it is marched once round from the point where the line through its centre parallel to
    the u axis meets it.
    """
    for k in range(N_STATS):
        stats[k] = 0
    p0, e1, e2, n0, m1, m2 = triangle_frame(tri_p, tri_n)
    ok, ng, length, side0, side2 = endpoint_sides(x0, x2, p0, e1, e2, eta)
    if not ok or side0 * side2 > 0.0:
        stats[STAT_SKIPPED] = 1
        return 0
    cf, natural = _local_conic(x0, x2, p0, e1, e2, n0, m1, m2)
    size = 0.0
    for k in range(6):
        size = max(size, abs(cf[k]))
    if not (np.isfinite(size) and np.isfinite(natural)):
        stats[STAT_SKIPPED] = 1
        return 0
    count = 0
    zero = (0.0, 0.0, 0.0)
    # M0, the line's crossing, is on the curve; at normal incidence (n̂ along x2 - x0 there)
    # τ is undefined at the root itself, so M0 is also polished as a candidate.
    okm, um, vm = line_crossing_barycentrics(x0, x2, p0, e1, e2, ng)
    if okm and um >= -1e-6 and vm >= -1e-6 and um + vm <= 1.0 + 1e-6:
        n = madd(madd(n0, m1, um), m2, vm)
        w = sub(x2, x0)
        if norm(cross(n, w)) <= ON_AXIS * norm(n) * norm(w):
            count = _polish_store(um, vm, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, buf, out_uv, count, stats)
    if size <= 1e-13 * natural or _conic_misses_triangle(cf, 1e-7 * size):
        # Coplanarity holds everywhere (flat normals along x2 - x0: only M0 can be a path) or
        # nowhere on the triangle.
        stats[STAT_PATHS] = count
        if count == 0:
            stats[STAT_SKIPPED] = 1
        return count
    n_cross = 0
    for k in range(3):
        nr, r1, r2 = _edge_roots(cf, size, k)
        for j in range(nr):
            s = min(max(r1 if j == 0 else r2, 0.0), 1.0)
            uc, vc = _edge_point(k, s)
            dup = False
            for q in range(n_cross):
                if abs(crossings[q, 0] - uc) <= 1e-12 and abs(crossings[q, 1] - vc) <= 1e-12:
                    dup = True
            if not dup and n_cross < MAX_CROSSINGS:
                crossings[n_cross, 0] = uc
                crossings[n_cross, 1] = vc
                crossings[n_cross, 2] = k
                crossings[n_cross, 3] = 0.0
                n_cross += 1
    counters[0] = 0
    counters[1] = 0
    for i in range(n_cross):
        if crossings[i, 3] != 0.0:
            continue
        crossings[i, 3] = 1.0
        uc = crossings[i, 0]
        vc = crossings[i, 1]
        k = int(crossings[i, 2])
        gu, gv = _conic_grad(cf, uc, vc)
        iu, iv = _edge_inward(k)
        into = -gv * iu + gu * iv  # tangent (eq 15) against the inward edge normal
        if abs(into) <= 1e-9 * math.sqrt(gu * gu + gv * gv) * math.sqrt(iu * iu + iv * iv):
            continue  # the conic touches the edge here
        direction = 1.0 if into > 0.0 else -1.0
        okf, f0, tau0 = refraction_f(uc, vc, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, zero)
        counters[0] += 1
        stats[STAT_ARCS] += 1
        status, edge, s, ue, ve, n_r, tau = _march(cf, size, uc, vc, -gv * direction, gu * direction, f0, okf, tau0,
                                                   h_max, False, 0.0, 0.0, 0, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta,
                                                   roots, counters)
        for r in range(min(n_r, roots.shape[0])):
            count = _polish_store(roots[r, 0], roots[r, 1], x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, buf, out_uv, count, stats)
        if status == EXITED:
            best = 1e-6
            hit = -1
            for q in range(n_cross):  # any edge: a crossing at a corner is listed once
                d = max(abs(crossings[q, 0] - ue), abs(crossings[q, 1] - ve))
                if d < best:
                    best = d
                    hit = q
            if hit >= 0:
                crossings[hit, 3] = 1.0
    if n_cross == 0 and cf[2] * cf[2] - 4.0 * cf[0] * cf[1] < 0.0:
        # An ellipse (eq 12 with C² < 4AB) with no edge crossing: wholly inside or outside.
        det = 4.0 * cf[0] * cf[1] - cf[2] * cf[2]
        uc = (cf[2] * cf[4] - 2.0 * cf[1] * cf[3]) / det
        vc = (cf[2] * cf[3] - 2.0 * cf[0] * cf[4]) / det
        if uc > 0.0 and vc > 0.0 and uc + vc < 1.0:
            nr, r1, r2 = _quadratic_roots(cf[0], cf[2] * vc + cf[3], (cf[1] * vc + cf[4]) * vc + cf[5], size, -1e300, 1e300)
            us = r2 if nr == 2 else r1
            if nr >= 1 and us > 0.0 and us + vc < 1.0:
                okf, f0, tau0 = refraction_f(us, vc, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, zero)
                counters[0] += 1
                stats[STAT_ARCS] += 1
                stats[STAT_CLOSED] += 1
                gu, gv = _conic_grad(cf, us, vc)
                status, edge, s, ue, ve, n_r, tau = _march(cf, size, us, vc, -gv, gu, f0, okf, tau0, h_max, True, us, vc, 3,
                                                           x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, roots, counters)
                for r in range(min(n_r, roots.shape[0])):
                    count = _polish_store(roots[r, 0], roots[r, 1], x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, buf, out_uv, count, stats)
    stats[STAT_SAMPLES] = counters[0]
    stats[STAT_BRACKETS] = counters[1]
    stats[STAT_PATHS] = count
    return count


@parallel_range("x_start", CHUNK)
def walk_tuple_batch(x_start, x_end, P, N, eta, h_max, out_uv, out_count, stats, first, last):
    """The per-tuple walk over a batch (chunks of ``CHUNK`` tuples per worker, scratch once per chunk)."""
    n = x_start.shape[0]
    for c in range(first, last):
        buf = np.zeros((5, MAX_PATHS_ONE_BOUNCE + 1))
        roots = np.zeros((MAX_ROOTS_PER_ARC, 2))
        crossings = np.zeros((MAX_CROSSINGS, 4))
        counters = np.zeros(2, dtype=np.int64)
        for t in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            out_count[t] = walk_tuple(row(x_start, t), row(x_end, t), P[t, 0], N[t, 0], eta[t], h_max,
                                      roots, crossings, counters, buf, out_uv[t], stats[t])


class CurveWalkSolver:
    """Coplanarity-curve walk (Granizo-Hidalgo & Holzschuch 2024) behind the tuple interface.

    Chain "T" only.  Per tuple: every conic arc inside the tuple's triangle plus the closed
    ellipse (see :func:`walk_tuple`); ``steps``: the longest marching step is 1/steps in
    barycentric units (more steps: fewer missed root pairs, more time).
    """

    name = "curve"

    def __init__(self, steps=DEFAULT_STEPS):
        if not 1 <= int(steps) <= 100000:
            raise ValueError("steps must be in [1, 100000]")
        self.steps = int(steps)

    def solve(self, chain, x_start, x_end, P, N, eta, **_ignored):
        """Same contract as ``SpecularPolynomialSolver.solve``, chain "T" only."""
        t0 = time.perf_counter()
        x_start, x_end, P, N, eta = validate_inputs(chain, x_start, x_end, P, N, eta)
        _check_chain(chain)
        report = SolveReport(solver=self.name, chain=chain, tuples=x_start.shape[0])
        n = x_start.shape[0]
        out_uv = np.zeros((n, MAX_PATHS_ONE_BOUNCE, 2))
        out_count = np.zeros(n, dtype=np.int64)
        stats = np.zeros((n, N_STATS), dtype=np.int64)
        t1 = time.perf_counter()
        if n:
            walk_tuple_batch(x_start, x_end, P, N, eta, 1.0 / self.steps, out_uv, out_count, stats)
        t2 = time.perf_counter()
        tuple_index, uv = compact_paths(out_uv, out_count)
        totals = stats.sum(axis=0)
        report.skipped = int(totals[STAT_SKIPPED])
        report.roots = int(totals[STAT_BRACKETS])
        report.candidates = int(totals[STAT_CANDIDATES])
        report.paths = int(tuple_index.shape[0])
        report.overflow = int(np.count_nonzero(out_count > MAX_PATHS_ONE_BOUNCE))
        report.seconds = {"prepare": t1 - t0, "solve": t2 - t1, "compact": time.perf_counter() - t2}
        return SolveResult(tuple_index, uv, report)


def _check_chain(chain):
    if chain != "T":
        raise ValueError(f"the curve solver (coplanarity-curve walk, Granizo-Hidalgo & Holzschuch 2024) solves chain 'T' "
                         f"only, not {chain!r}: " + ("a reflection has no starting point on the coplanarity curve (§6)"
                                                     if chain == "R" else "it handles a single refraction"))


# --- the mesh walk --------------------------------------------------------------------------


def build_adjacency(tri_p, tol=None):
    """Triangle adjacency of a caster mesh given as a triangle soup (T, 3, 3).

    Corners closer than ``tol`` (default 1e-9 x the bounding-box diagonal; positions are
    welded by rounding to that grid) are one vertex; an edge shared by exactly two triangles
    links them.  Returns (T, 3, 3) int64: for edge k of triangle t (corner k -> corner k+1),
    [neighbour triangle, its edge index, 1 if the neighbour runs the edge the other way]
    (a consistently wound mesh gives 1), or -1 in all three where the edge is on the border,
    degenerate or shared by more than two triangles.
    """
    tri_p = np.asarray(tri_p, dtype=np.float64)
    if tri_p.ndim != 3 or tri_p.shape[1:] != (3, 3):
        raise ValueError(f"tri_p must have shape (T, 3, 3), got {tri_p.shape}")
    if not np.all(np.isfinite(tri_p)):
        raise ValueError("tri_p contains NaN or Inf")
    n = tri_p.shape[0]
    adj = np.full((n, 3, 3), -1, dtype=np.int64)
    if n == 0:
        return adj
    verts = tri_p.reshape(-1, 3)
    if tol is None:
        tol = 1e-9 * max(float(np.linalg.norm(verts.max(0) - verts.min(0))), 1e-300)
    keys = np.round(verts / tol).astype(np.int64)
    _, vid = np.unique(keys, axis=0, return_inverse=True)
    vid = vid.reshape(n, 3)
    a = vid.reshape(-1)
    b = vid[:, [1, 2, 0]].reshape(-1)
    lo = np.minimum(a, b)
    hi = np.maximum(a, b)
    edge_id = np.arange(3 * n)
    good = lo != hi
    order = np.lexsort((hi, lo))
    order = order[good[order]]
    lo_s, hi_s = lo[order], hi[order]
    start = np.r_[True, (lo_s[1:] != lo_s[:-1]) | (hi_s[1:] != hi_s[:-1])]
    group = np.cumsum(start) - 1
    sizes = np.bincount(group)
    pair = sizes[group] == 2
    first = np.flatnonzero(start & pair)
    e1, e2 = edge_id[order[first]], edge_id[order[first + 1]]
    rev = (a[e1] == b[e2]).astype(np.int64)
    for src, dst in ((e1, e2), (e2, e1)):
        adj[src // 3, src % 3, 0] = dst // 3
        adj[src // 3, src % 3, 1] = dst % 3
        adj[src // 3, src % 3, 2] = rev
    return adj


@kernel
def _barycentric_in(x, p0, e1, e2):
    """Barycentrics of x projected onto the plane of (p0, e1, e2)."""
    rel = sub(x, p0)
    d11 = dot(e1, e1)
    d12 = dot(e1, e2)
    d22 = dot(e2, e2)
    r1 = dot(rel, e1)
    r2 = dot(rel, e2)
    det = d11 * d22 - d12 * d12
    if not det > 0.0:
        return 0.0, 0.0
    return (r1 * d22 - r2 * d12) / det, (d11 * r2 - d12 * r1) / det


@kernel
def _store_mesh_path(tri, u, v, x, tol, pos, out_tri, out_uv, count):
    """Append a mesh path unless one stored is the same point (within ``tol``, across triangles)."""
    for q in range(min(count, pos.shape[0])):
        if max(abs(pos[q, 0] - x[0]), max(abs(pos[q, 1] - x[1]), abs(pos[q, 2] - x[2]))) <= tol:
            return count
    if count < out_uv.shape[0]:
        out_tri[count] = tri
        out_uv[count, 0] = u
        out_uv[count, 1] = v
        pos[count, 0] = x[0]
        pos[count, 1] = x[1]
        pos[count, 2] = x[2]
    return count + 1


@kernel
def _polish_mesh_root(tri, ur, vr, x0, x2, tri_p, tri_n, adj, eta, pos, out_tri, out_uv, count, stats):
    """Polish a bracketed root in its triangle; a root on an edge that the polish pushes out
    of the triangle is polished again in the neighbour across that edge."""
    for attempt in range(4):
        t = tri
        uu = ur
        vv = vr
        if attempt > 0:
            k = attempt - 1
            dist = _edge_inside(k, ur, vr)
            if abs(dist) > 1e-6 or adj[tri, k, 0] < 0:
                continue
            t = adj[tri, k, 0]
            p0, e1, e2, n0, m1, m2 = triangle_frame(tri_p[tri], tri_n[tri])
            x = madd(madd(p0, e1, ur), e2, vr)
            q0, f1, f2, _, _, _ = triangle_frame(tri_p[t], tri_n[t])
            uu, vv = _barycentric_in(x, q0, f1, f2)
        p0, e1, e2, n0, m1, m2 = triangle_frame(tri_p[t], tri_n[t])
        ng, area2 = geometric_normal(e1, e2)
        if not area2 > 0.0:
            continue
        stats[MSTAT_CANDIDATES] += 1
        ok, uu, vv, err, sig = polish_and_validate(uu, vv, x0, x2, p0, e1, e2, n0, m1, m2, ng, True, eta,
                                                   POLISH_STEPS, ACCEPT_RESIDUAL)
        if ok:
            x = madd(madd(p0, e1, uu), e2, vv)
            tol = 1e-7 * max(norm(e1), norm(e2))
            return _store_mesh_path(t, uu, vv, x, tol, pos, out_tri, out_uv, count)
    return count


@kernel
def _walk_from(start, su, sv, direction, x0, x2, tri_p, tri_n, adj, eta, h_max, roots, counters, pos, out_tri,
               out_uv, count, stats, stamp, entry_s, walk_id):
    """One direction of the walk from M0 = (start, su, sv) across the mesh (§3.4.3).

    Every entry into a triangle (edge, position along it) is stamped with ``walk_id``: a
    walk that enters a triangle where this receiver point's walks already entered, at the
    same point of the same edge, is retracing a walked curve (a loop the marching joined at
    a singular point of the curve, or the other direction of a closed curve) and stops.
    Returns (count, closed): closed when the curve came back to M0 (then the other
    direction has nothing new)."""
    tri = start
    p0, e1, e2, n0, m1, m2 = triangle_frame(tri_p[tri], tri_n[tri])
    ng, area2 = geometric_normal(e1, e2)
    cf, natural = _local_conic(x0, x2, p0, e1, e2, n0, m1, m2)
    size = max(max(max(abs(cf[0]), abs(cf[1])), max(abs(cf[2]), abs(cf[3]))), max(abs(cf[4]), abs(cf[5])))
    if not (size > 1e-13 * natural) or not area2 > 0.0:
        return count, False
    u, v = su, sv
    gu, gv = _conic_grad(cf, u, v)
    du = -gv * direction
    dv = gu * direction
    okf, f0, tau = refraction_f(su, sv, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, (0.0, 0.0, 0.0))
    first = True
    for _ in range(MAX_WALK_TRIANGLES):
        stats[MSTAT_VISITS] += 1
        status, edge, s, ue, ve, n_r, tau = _march(cf, size, u, v, du, dv, f0, okf, tau, h_max, tri == start, su, sv,
                                                   3 if first else 0, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, roots,
                                                   counters)
        for r in range(min(n_r, roots.shape[0])):
            count = _polish_mesh_root(tri, roots[r, 0], roots[r, 1], x0, x2, tri_p, tri_n, adj, eta, pos, out_tri,
                                      out_uv, count, stats)
        if status == CLOSED:
            return count, True
        if status != EXITED:
            return count, False
        nt = adj[tri, edge, 0]
        if nt < 0:
            return count, False
        ne = adj[tri, edge, 1]
        s2 = 1.0 - s if adj[tri, edge, 2] == 1 else s
        # Continue in the neighbour: its own conic's crossing of the shared edge nearest to
        # the exit point (the same point for continuous vertex normals).
        tri = nt
        p0, e1, e2, n0, m1, m2 = triangle_frame(tri_p[tri], tri_n[tri])
        ng, area2 = geometric_normal(e1, e2)
        if not area2 > 0.0:
            return count, False
        cf, natural = _local_conic(x0, x2, p0, e1, e2, n0, m1, m2)
        size = max(max(max(abs(cf[0]), abs(cf[1])), max(abs(cf[2]), abs(cf[3]))), max(abs(cf[4]), abs(cf[5])))
        if not (size > 1e-13 * natural):
            return count, False
        nr, r1, r2 = _edge_roots(cf, size, ne)
        if nr == 0:
            return count, False
        se = r1
        if nr == 2 and abs(r2 - s2) < abs(r1 - s2):
            se = r2
        if abs(se - s2) > 1e-4:
            return count, False  # the curve does not continue across this edge (split normals)
        se = min(max(se, 0.0), 1.0)
        if stamp[tri, ne] == walk_id and abs(entry_s[tri, ne] - se) <= 1e-9:
            return count, False
        stamp[tri, ne] = walk_id
        entry_s[tri, ne] = se
        u, v = _edge_point(ne, se)
        gu, gv = _conic_grad(cf, u, v)
        iu, iv = _edge_inward(ne)
        into = -gv * iu + gu * iv
        if into == 0.0:
            return count, False
        sgn = 1.0 if into > 0.0 else -1.0
        du = -gv * sgn
        dv = gu * sgn
        okf, f0, tau = refraction_f(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng, eta, tau)
        counters[0] += 1
        first = False
    return count, False


@parallel_range("x_start", MESH_CHUNK)
def walk_mesh_batch(x_start, x_end, tri_p, tri_n, adj, eta, h_max, out_tri, out_uv, out_count, stats, first, last):
    """The mesh walk for every receiver point (independent: one point per parallel item).

    Starting points: every crossing of the segment x0 -> x2 with the mesh (Möller-Trumbore
    over all triangles; the paper shoots this ray on the GPU, §4); each is walked both ways.
    """
    n = x_start.shape[0]
    n_tri = tri_p.shape[0]
    for c in range(first, last):
        roots = np.zeros((MAX_ROOTS_PER_ARC, 2))
        pos = np.zeros((MAX_PATHS_MESH, 3))
        starts = np.zeros((MAX_STARTS, 6))
        counters = np.zeros(2, dtype=np.int64)
        stamp = np.full((n_tri, 3), -1, dtype=np.int64)
        entry_s = np.zeros((n_tri, 3))
        for i in range(c * MESH_CHUNK, min(n, (c + 1) * MESH_CHUNK)):
            _walk_point(i, x_start, x_end, tri_p, tri_n, adj, eta, h_max, roots, pos, starts, counters, stamp, entry_s,
                        out_tri, out_uv, out_count, stats)


@kernel
def _walk_point(i, x_start, x_end, tri_p, tri_n, adj, eta, h_max, roots, pos, starts, counters, stamp, entry_s,
                out_tri, out_uv, out_count, stats):
    """All walks of receiver point i: every start (line crossing), both directions."""
    n_tri = tri_p.shape[0]
    counters[0] = 0
    counters[1] = 0
    x0 = row(x_start, i)
    x2 = row(x_end, i)
    d = sub(x2, x0)
    ld = norm(d)
    n_starts = 0
    count = 0
    if ld > 0.0:
        for t in range(n_tri):
            p0 = row(tri_p[t], 0)
            e1 = sub(row(tri_p[t], 1), p0)
            e2 = sub(row(tri_p[t], 2), p0)
            pv = cross(d, e2)
            det = dot(e1, pv)
            if not abs(det) > 1e-14 * ld * norm(e1) * norm(e2):
                continue
            inv = 1.0 / det
            tv = sub(x0, p0)
            u = dot(tv, pv) * inv
            if u < -1e-12 or u > 1.0 + 1e-12:
                continue
            qv = cross(tv, e1)
            v = dot(d, qv) * inv
            if v < -1e-12 or u + v > 1.0 + 1e-12:
                continue
            lam = dot(e2, qv) * inv
            if not (0.0 < lam < 1.0):
                continue
            x = madd(x0, d, lam)
            dup = False
            for q in range(n_starts):  # a crossing on a shared edge or corner: one start
                if norm(sub((starts[q, 3], starts[q, 4], starts[q, 5]), x)) <= 1e-9 * ld:
                    dup = True
            if dup or n_starts >= MAX_STARTS:
                continue
            u = max(u, 0.0)
            v = max(v, 0.0)
            if u + v > 1.0:
                u /= u + v
                v = 1.0 - u
            starts[n_starts, 0] = t
            starts[n_starts, 1] = u
            starts[n_starts, 2] = v
            starts[n_starts, 3] = x[0]
            starts[n_starts, 4] = x[1]
            starts[n_starts, 5] = x[2]
            n_starts += 1
    stats[i, MSTAT_STARTS] = n_starts
    for q in range(n_starts):
        t = int(starts[q, 0])
        count, closed = _walk_from(t, starts[q, 1], starts[q, 2], 1.0, x0, x2, tri_p, tri_n, adj, eta[i], h_max,
                                   roots, counters, pos, out_tri[i], out_uv[i], count, stats[i], stamp, entry_s, i)
        if closed:
            stats[i, MSTAT_CLOSED] += 1
        else:
            count, closed = _walk_from(t, starts[q, 1], starts[q, 2], -1.0, x0, x2, tri_p, tri_n, adj, eta[i],
                                       h_max, roots, counters, pos, out_tri[i], out_uv[i], count, stats[i], stamp,
                                       entry_s, i)
    stats[i, MSTAT_SAMPLES] = counters[0]
    stats[i, MSTAT_BRACKETS] = counters[1]
    stats[i, MSTAT_PATHS] = min(count, MAX_PATHS_MESH)
    stats[i, MSTAT_OVERFLOW] = int(count > MAX_PATHS_MESH)
    out_count[i] = min(count, MAX_PATHS_MESH)


@dataclass
class MeshWalkResult:
    point_index: np.ndarray  # (m,) int64, ascending
    triangle_index: np.ndarray  # (m,) int64
    uv: np.ndarray  # (m, 2) barycentrics in that triangle
    report: SolveReport  # tuples = receiver points; skipped = points with no start
    starts: int = 0  # crossings of the line x0 -> x2 with the mesh, summed
    triangle_visits: int = 0
    closed: int = 0  # walks that came back to their start


def walk_mesh(x0, x2_points, tri_p, tri_n, adjacency, eta, steps=MESH_STEPS):
    """Walk the coplanarity curves of a caster mesh for a batch of receiver points (chain T).

    x0: (3,) light position or (n, 3); x2_points: (n, 3) receiver points; tri_p, tri_n:
    (T, 3, 3) vertex positions and (corner) normals of the caster's triangles, normals
    pointing away from the medium of IOR ``eta`` (scalar or (n,)); adjacency: from
    :func:`build_adjacency`; steps: the longest marching step is 1/steps of a triangle.
    Returns a :class:`MeshWalkResult` with one row per path: (point, triangle, u, v).
    """
    t0 = time.perf_counter()
    x2_points = np.asarray(x2_points, dtype=np.float64)
    if x2_points.ndim != 2 or x2_points.shape[1] != 3:
        raise ValueError(f"x2_points must have shape (n, 3), got {x2_points.shape}")
    n = x2_points.shape[0]
    x0 = np.asarray(x0, dtype=np.float64)
    x_start = np.array(np.broadcast_to(x0, (n, 3)) if x0.shape == (3,) else x0)
    tri_p = np.asarray(tri_p, dtype=np.float64)
    tri_n = np.asarray(tri_n, dtype=np.float64)
    if tri_p.ndim != 3 or tri_p.shape[1:] != (3, 3) or tri_n.shape != tri_p.shape:
        raise ValueError(f"tri_p and tri_n must both have shape (T, 3, 3), got {tri_p.shape} and {tri_n.shape}")
    if not (np.all(np.isfinite(tri_p)) and np.all(np.isfinite(tri_n))):
        raise ValueError("tri_p or tri_n contains NaN or Inf")
    n_tri = tri_p.shape[0]
    dummy = np.zeros((n, 1, 3, 3))
    x_start, x2_points, _, _, eta = validate_inputs("T", x_start, x2_points, dummy, dummy, eta)
    adjacency = np.ascontiguousarray(np.asarray(adjacency, dtype=np.int64))
    if adjacency.shape != (n_tri, 3, 3):
        raise ValueError(f"adjacency must have shape ({n_tri}, 3, 3) (build_adjacency), got {adjacency.shape}")
    tri_p = np.ascontiguousarray(tri_p)
    tri_n = np.ascontiguousarray(tri_n)
    if not 1 <= int(steps) <= 100000:
        raise ValueError("steps must be in [1, 100000]")
    report = SolveReport(solver="curve", chain="T", tuples=n)
    out_tri = np.zeros((n, MAX_PATHS_MESH), dtype=np.int64)
    out_uv = np.zeros((n, MAX_PATHS_MESH, 2))
    out_count = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, N_MSTATS), dtype=np.int64)
    t1 = time.perf_counter()
    if n and n_tri:
        walk_mesh_batch(x_start, x2_points, tri_p, tri_n, adjacency, eta, 1.0 / int(steps), out_tri, out_uv, out_count, stats)
    t2 = time.perf_counter()
    point_index = np.repeat(np.arange(n, dtype=np.int64), out_count)
    slot = np.arange(point_index.shape[0]) - np.repeat(np.cumsum(out_count) - out_count, out_count)
    triangle_index = out_tri[point_index, slot]
    uv = out_uv[point_index, slot]
    if uv.shape[0]:
        order = np.lexsort((uv[:, 1], uv[:, 0], triangle_index, point_index))
        point_index, triangle_index, uv = point_index[order], triangle_index[order], uv[order]
    totals = stats.sum(axis=0)
    report.skipped = int(np.count_nonzero(stats[:, MSTAT_STARTS] == 0))
    report.roots = int(totals[MSTAT_BRACKETS])
    report.candidates = int(totals[MSTAT_CANDIDATES])
    report.paths = int(point_index.shape[0])
    report.overflow = int(totals[MSTAT_OVERFLOW])
    report.seconds = {"prepare": t1 - t0, "walk": t2 - t1, "compact": time.perf_counter() - t2}
    return MeshWalkResult(point_index, triangle_index, np.ascontiguousarray(uv), report, int(totals[MSTAT_STARTS]),
                          int(totals[MSTAT_VISITS]), int(totals[MSTAT_CLOSED]))


# --- ray-differential contribution (eq 25-33) ----------------------------------------------


@parallel_range("tuple_index")
def _ray_differential_kernel(from_light, x_start, x_end, P, N, eta, tuple_index, uv, receiver_normal, has_receiver, out, first, last):
    """Per solution: out[:, 0..6] = geometry, fresnel, cos_receiver, direction xyz, D.

    The paper's P (where the differential starts) is the light x0 when ``from_light``, else
    the receiver x2; its L is the other end."""
    for s in range(first, last):
        for k in range(7):
            out[s, k] = 0.0
        t = tuple_index[s]
        x0 = row(x_start, t)
        x2 = row(x_end, t)
        p0, e1, e2, n0, m1, m2 = triangle_frame(P[t, 0], N[t, 0])
        ng, area2 = geometric_normal(e1, e2)
        u = uv[s, 0]
        v = uv[s, 1]
        m_rel = madd(scale(e1, u), e2, v)  # M - p0
        to_light = sub(sub(x0, p0), m_rel)
        to_recv = sub(sub(x2, p0), m_rel)
        to_p = to_light if from_light else to_recv  # P - M
        to_l = to_recv if from_light else to_light  # L - M
        d_p = norm(to_p)  # eq 26
        d_l = norm(to_l)  # eq 27
        n = madd(madd(n0, m1, u), m2, v)
        ln = norm(n)
        if not (d_p > 0.0 and d_l > 0.0 and ln > 0.0 and area2 > 0.0):
            continue
        wp = scale(to_p, 1.0 / d_p)
        wl = scale(to_l, 1.0 / d_l)
        ns = scale(n, 1.0 / ln)
        ngo = ng if dot(ng, ns) >= 0.0 else scale(ng, -1.0)
        light_outside = dot(to_light, ngo) > 0.0
        if light_outside == (dot(to_recv, ngo) > 0.0):
            continue  # not a refraction
        eta_light = 1.0 if light_outside else eta[t]
        eta_recv = eta[t] if light_outside else 1.0
        r = eta_light / eta_recv if from_light else eta_recv / eta_light  # eta_P / eta_L
        cp = dot(wp, ns)
        cl = dot(wl, ns)
        if cp * cl >= 0.0 or cl == 0.0:
            continue
        mu = cl + r * cp  # eq 29: wl = -r wp + mu n̂ (Snell's law, the ray P -> M -> L)
        wpg = dot(wp, ng)
        if wpg == 0.0:
            continue
        # Two unit perturbations q of the direction P -> M (= -ω̂_P), perpendicular to it and
        # to each other; ω̂_P changes by -q.
        a = (1.0, 0.0, 0.0) if abs(wp[0]) < 0.6 else (0.0, 1.0, 0.0)
        qa = cross(wp, a)
        qa = scale(qa, 1.0 / norm(qa))
        qb = cross(wp, qa)
        d11 = dot(e1, e1)
        d12 = dot(e1, e2)
        d22 = dot(e2, e2)
        det = d11 * d22 - d12 * d12
        lp_a = (0.0, 0.0, 0.0)
        lp_b = (0.0, 0.0, 0.0)
        for j in range(2):
            q = qa if j == 0 else qb
            mp = scale(madd(q, wp, -dot(q, ng) / wpg), d_p)  # eq 28: the hit point moves by M'
            du = (dot(mp, e1) * d22 - dot(mp, e2) * d12) / det
            dv = (d11 * dot(mp, e2) - d12 * dot(mp, e1)) / det
            dn = madd(scale(m1, du), m2, dv)
            dns = scale(madd(dn, ns, -dot(ns, dn)), 1.0 / ln)  # n̂'
            dcp = -dot(q, ns) + dot(wp, dns)  # (ω̂_P · n̂)' with ω̂_P' = -q
            dmu = (r * r * cp / cl + r) * dcp  # eq 30
            dwl = madd(madd(scale(q, r), ns, dmu), dns, mu)  # eq 31
            lp = madd(madd(mp, wl, -dot(mp, wl)), dwl, d_l)  # eq 32
            if j == 0:
                lp_a = lp
            else:
                lp_b = lp
        big_d = norm(cross(lp_a, lp_b))  # eq 33
        if not big_d > 0.0:
            continue
        if from_light:
            geometry = 1.0 / big_d  # area at the receiver per solid angle at the light
            cos_i = abs(cp)
        else:
            # area at the light per solid angle at the receiver: by the invariance of
            # n² dA⊥ dΩ along a beam, (eta_recv / eta_light)² / D -- exact only where the
            # shading normal is the surface's normal (see ray_differential_irradiance).
            geometry = r * r / big_d
            cos_i = abs(cl)
        fresnel = 1.0 - fresnel_dielectric(cos_i, eta_light, eta_recv)
        w_arrive = scale(to_recv, 1.0 / norm(to_recv))
        cos_r = 1.0
        if has_receiver:
            nr = row(receiver_normal, t)
            lr = norm(nr)
            cos_r = abs(dot(w_arrive, nr)) / lr if lr > 0.0 else 0.0
        out[s, 0] = geometry
        out[s, 1] = fresnel
        out[s, 2] = cos_r
        out[s, 3] = w_arrive[0]
        out[s, 4] = w_arrive[1]
        out[s, 5] = w_arrive[2]
        out[s, 6] = big_d


def ray_differential_irradiance(x_start, x_end, P, N, eta, tuple_index, uv, receiver_normal=None, from_light=True):
    """Irradiance of solved T paths from the ray differentials of §3.4.5 (eq 26-33).

    Eq 28-33 perturb the direction of the ray leaving the paper's P towards the vertex M
    (eq 28: the hit point moves, eq 29-31: the refracted direction turns, with the shading
    normal's change), carry it to the paper's L (eq 32) and take D = |L'⊥ × L'∥| (eq 33),
    the area swept near L per unit solid angle at P.

    ``from_light=True`` (default) puts P at the light x0 and L at the receiver: then 1/D is
    the project's geometry term (solid angle at the light per unit area at the receiver,
    CONTRACT.md) exactly.  ``from_light=False`` is the paper's orientation (P the shading
    point, L the light): D is then the adjoint quantity and the geometry term follows from
    the invariance of n² dA⊥ dΩ as (eta_receiver / eta_light)² / D, which holds on real
    surfaces (flat normals) but not with interpolated shading normals, where refraction by
    a normal that is not the surface's does not conserve étendue (a 0.2 % difference on a
    gently curved triangle, far more near total internal reflection).
    Same inputs and fields as ``path_irradiance`` for chain "T" (fresnel: dielectric
    transmittance); rows that are not refractions get zeros.  Returns (PathIrradiance, D).
    """
    x_start, x_end, P, N, eta = validate_inputs("T", x_start, x_end, P, N, eta)
    n = x_start.shape[0]
    tuple_index = np.ascontiguousarray(tuple_index, dtype=np.int64)
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    if tuple_index.ndim != 1 or uv.shape != (tuple_index.shape[0], 2):
        raise ValueError(f"tuple_index must be (m,) and uv (m, 2); got {tuple_index.shape} and {uv.shape}")
    if tuple_index.size and (tuple_index.min() < 0 or tuple_index.max() >= n):
        raise ValueError("tuple_index out of range")
    has_receiver = receiver_normal is not None
    rn = np.zeros((n, 3)) if not has_receiver else np.ascontiguousarray(
        np.broadcast_to(np.asarray(receiver_normal, dtype=np.float64), (n, 3)))
    out = np.zeros((tuple_index.shape[0], 7))
    if tuple_index.shape[0]:
        _ray_differential_kernel(bool(from_light), x_start, x_end, P, N, eta, tuple_index, uv, rn, has_receiver, out)
    geometry, fresnel, cos_r = out[:, 0], out[:, 1], out[:, 2]
    return PathIrradiance(geometry * fresnel * cos_r, geometry, fresnel, cos_r, out[:, 3:6].copy()), out[:, 6].copy()
