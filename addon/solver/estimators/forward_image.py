"""Forward-image seeding of two-bounce chains: where a tuple's light lands, and from where.

The exact two-bounce solver (:mod:`two_bounce`, Fan et al. 2024 §3.4–4.2) costs 1–100 ms per
(tuple, receiver point); a bake asks it for millions of pairs, almost all without a path.
The Bernstein-bounds paper (Fan et al. 2025, §6–7, "Root-finding") does not use it for double
scattering either: it bounds where each tuple's light can land, samples tuples by that bound,
and runs Newton's method inside the bounded region ("Det" initialisation).  This module does
the same with a *forward-traced image* instead of the Bernstein bound:

1. :func:`trace_chain_points` — exact forward rays: a point (u1, v1) of the first caster
   triangle, lit from x0, is scattered there (reflect / refract with the interpolated corner
   normal and the side rules of CONTRACT.md), traced through the scene's BVH to the first hit
   (it must be a caster of the chain's second vertex), scattered again, traced to a receiver:
   its receiver triangle, texture coordinates and second triangle.
2. :func:`refine_image_triangles` — the first triangle's barycentric domain is cut into a
   G0 x G0 grid of sub-triangles; a sub-triangle whose edge midpoints land farther than
   ``tolerance`` (in texels) from the straight image, or whose points do not all land on one
   receiver, is split in four (up to ``max_depth``).  What remains is a set of small
   sub-triangles whose image in the receiver's UV space is a straight triangle to within its
   measured midpoint deviation.  Sub-triangles partly lost (rays missing the receiver, total
   internal reflection) are cut at the border (located by bisection on the crossed edges)
   when it is straight at their size, else approximated by their landed points' hull at
   the deepest level; what is dropped is counted: reported, never hidden.
3. :class:`ImageSeeds` — every receiver sample whose texture coordinates lie within the
   image triangle grown by a margin (base texels + twice the deviation) gets a seed: the
   point of the sub-triangle whose straight image is closest to the sample.
4. :func:`solve_image_seeds` — the seed is traced to its second triangle, then the exact
   two-vertex constraint is solved by the path-space Gauss-Newton of :mod:`two_vertex`
   (eq. 3 of Fan et al. 2024 at both vertices) and accepted by the same validation as the
   exact solver (both vertices inside their triangles, sides, residual ≤ 1e-12 or settled
   within 1e-7).  A Newton step that leaves the second triangle re-traces and tries the
   neighbour the ray now hits (at most ``HOPS`` times).

Every returned path is a validated exact path; completeness is measured, not assumed: the
tests compare the paths with the exact solver's and the bake with a photon reference.
No bpy here; the bake (``addon.bake.estimators``) orchestrates.
"""

import math
import time

import numpy as np

from ..geometry.bvh import ray_closest
from ..runtime.jit import kernel, parallel_range
from ..paths.two_vertex import pack_geometry, polish_and_validate2
from ..geometry.optics import ROLE_BOTH, ROLE_REFLECT, fresnel_dielectric
from ..geometry.optics import scatter_direction as _scatter
from ..geometry.surface import plane_barycentrics as _hit_bary
from ..geometry.surface import triangle_frame
from ..geometry.receiver_planes import beyond_region_rows, extended_landing

POLISH_STEPS = 40
ACCEPT_RESIDUAL = 1e-12  # as the exact solver (two_bounce.ACCEPT_RESIDUAL)
HOPS = 3  # re-traces to a neighbouring second triangle when Newton leaves the first one
INSIDE_HOP = 1e-9
CHUNK = 256
BORDER_STEPS = 5  # bisections locating a straight border on an edge: to 1/64 of the edge
BORDER_TEXELS = 1.0  # a partly landed sub-triangle is cut at its border once its whole image is this small
SLIVER = 4.0  # images stretched beyond this (longest edge² / twice the area) are splatted uniformly
ROUGH_TEXELS = 0.25  # ... or approximated by its landed points once its whole image is this small (1/16: 4x the time on the metal ring, same error)
COARSE_TEXELS = 8.0  # a sub-triangle coarser than the first grid is final only if its image is at most this long (texels) ...
COARSE_LINEAR_TEXELS = 1.0  # ... and, longer than this, its density linear to relative x (this / its length)²


@kernel(inline="always")
def _bary_point(tri_p, tri_n, t, u, v):
    """triangle_frame with ok False also for a zero shading normal."""
    ok, x, y, z, nx, ny, nz, gx, gy, gz, has_normal = triangle_frame(tri_p, tri_n, t, u, v)
    return ok and has_normal, x, y, z, nx, ny, nz, gx, gy, gz


@kernel(inline="always")
def _weight(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract, eta, role):
    """The bake's surface weight of one vertex (see :func:`_trace_one`)."""
    if role == ROLE_REFLECT:
        return 1.0
    outside = dx * gx + dy * gy + dz * gz < 0.0
    ci = abs(dx * nx + dy * ny + dz * nz)
    F = fresnel_dielectric(ci, 1.0, eta) if outside else fresnel_dielectric(ci, eta, 1.0)
    if refract:
        return 1.0 - F
    return F if role == ROLE_BOTH else 1.0


@kernel(inline="always")
def _land(x, y, z, dx, dy, dz, prev, tri_rec, tri_p, tri_n, node_min, node_max, node_child, node_start, node_count, order,
          v0, e1, e2, eps, planes, stack):
    """The last segment: the closest hit must be the front of a receiver.  Returns (receiver
    triangle or -1, barycentrics, cos_shading / cos_geometric there).  A ray that lands on no
    receiver but crosses the front of a flat receiver's plane (a row of ``planes``) outside
    its UV region lands there, extended (:mod:`~addon.solver.geometry.receiver_planes`):
    barycentrics of the row's triangle, factor 1 (flat shading)."""
    tr, th = ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, x, y, z, dx, dy, dz,
                          eps, np.inf, prev, stack)
    if tr < 0 or tri_rec[tr] < 0:
        p = extended_landing(planes, x, y, z, dx, dy, dz, eps)
        if p < 0:
            return -1, 0.0, 0.0, 0.0
        tp = int(planes[p, 12])
        ur, vr = _hit_bary(tri_p, tp, x, y, z, dx, dy, dz)
        return tp, ur, vr, 1.0
    ur, vr = _hit_bary(tri_p, tr, x, y, z, dx, dy, dz)
    ok, hx, hy, hz, nx, ny, nz, gx, gy, gz = _bary_point(tri_p, tri_n, tr, ur, vr)
    cg = -(dx * gx + dy * gy + dz * gz)
    if not ok or cg <= 0.0:
        return -1, 0.0, 0.0, 0.0  # the back of the receiver (the bake's front rule)
    return tr, ur, vr, max(0.0, -(dx * nx + dy * ny + dz * nz)) / cg


@kernel(inline="always")
def _trace_one(x0x, x0y, x0z, t1, u1, v1, bounces, refract1, refract2, second_ok, tri_rec, tri_p, tri_n, tri_ior,
               tri_role, node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, eps, planes, stack):
    """The forward chain of ``bounces`` (1 or 2) vertices from (u1, v1) on t1, lit from x0
    (a point in shadow is lost): (second triangle or -1, its barycentrics, receiver triangle
    or -1, its barycentrics, transport factor).  The factor is the product over the vertices of the bake's surface weights
    (reflect role: 1; 'both' (glass): F for R, 1 - F for T; refract role: 1 - F; unpolarised
    dielectric F at the vertex's cos_i) times cos_shading / cos_geometric at the receiver
    (the bake's irradiance convention)."""
    ok, x, y, z, nx, ny, nz, gx, gy, gz = _bary_point(tri_p, tri_n, t1, u1, v1)
    if not ok:
        return -1, 0.0, 0.0, -1, 0.0, 0.0, 0.0
    dx, dy, dz = x - x0x, y - x0y, z - x0z
    ln = math.sqrt(dx * dx + dy * dy + dz * dz)
    if not ln > 0.0:
        return -1, 0.0, 0.0, -1, 0.0, 0.0, 0.0
    dx, dy, dz = dx / ln, dy / ln, dz / ln
    # the light must reach the point: a shadowed point is lost like a missed receiver, so a
    # shadow's edge across a first triangle is refined and cut as a border, not decided for
    # a whole sub-triangle at its centre
    sh, _sh_t = ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, x0x, x0y, x0z,
                             dx, dy, dz, eps, ln * (1.0 - 1e-9) - eps, t1, stack)
    if sh >= 0:
        return -1, 0.0, 0.0, -1, 0.0, 0.0, 0.0
    fac = _weight(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract1, tri_ior[t1], tri_role[t1])
    ok, dx, dy, dz = _scatter(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract1, tri_ior[t1])
    if not ok:
        return -1, 0.0, 0.0, -1, 0.0, 0.0, 0.0
    if bounces == 1:
        tr, ur, vr, c = _land(x, y, z, dx, dy, dz, t1, tri_rec, tri_p, tri_n, node_min, node_max, node_child, node_start,
                              node_count, order, v0, e1, e2, eps, planes, stack)
        return -1, 0.0, 0.0, tr, ur, vr, fac * c
    t2, th = ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, x, y, z, dx, dy, dz,
                          eps, np.inf, t1, stack)
    if t2 < 0 or not second_ok[t2]:
        return -1, 0.0, 0.0, -1, 0.0, 0.0, 0.0
    u2, v2 = _hit_bary(tri_p, t2, x, y, z, dx, dy, dz)
    u2 = min(max(u2, 0.0), 1.0)
    v2 = min(max(v2, 0.0), 1.0 - u2)
    ok, x, y, z, nx, ny, nz, gx, gy, gz = _bary_point(tri_p, tri_n, t2, u2, v2)
    if not ok:
        return t2, u2, v2, -1, 0.0, 0.0, 0.0
    fac *= _weight(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract2, tri_ior[t1], tri_role[t2])
    ok, dx, dy, dz = _scatter(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract2, tri_ior[t1])
    if not ok:
        return t2, u2, v2, -1, 0.0, 0.0, 0.0
    tr, ur, vr, c = _land(x, y, z, dx, dy, dz, t2, tri_rec, tri_p, tri_n, node_min, node_max, node_child, node_start,
                          node_count, order, v0, e1, e2, eps, planes, stack)
    return t2, u2, v2, tr, ur, vr, fac * c


@parallel_range("emitter", CHUNK, serial_below=8)  # under 2048 points: on the calling thread
def trace_chain_points(emitter, u1, v1, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior,
                       tri_role, node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, eps, planes,
                       out_t2, out_rec, out_uv, out_factor, first, last):
    """Step 1 (see the module docstring) for points (emitter[i], u1[i], v1[i]) of a chain of
    ``bounces`` (1 or 2) vertices: the second
    triangle ``out_t2`` (-1: none), the receiver triangle ``out_rec`` (-1: lost), the
    texture coordinates ``out_uv`` of the landing point and the transport factor
    ``out_factor`` (:func:`_trace_one`).  ``planes``: the flat receivers whose planes take the
    rays that miss them (:mod:`~addon.solver.geometry.receiver_planes`; landing there,
    extended, UV outside the receiver's region; an empty array: none)."""
    n = emitter.shape[0]
    for ch in range(first, last):
        stack = np.empty(256, dtype=np.int64)
        for i in range(ch * CHUNK, min(n, ch * CHUNK + CHUNK)):
            e = emitter[i]
            t2, _u2, _v2, tr, ur, vr, fac = _trace_one(x0[e, 0], x0[e, 1], x0[e, 2], t1_of[e], u1[i], v1[i], bounces, refract1,
                                                       refract2, second_ok, tri_rec, tri_p, tri_n, tri_ior, tri_role,
                                                       node_min, node_max, node_child, node_start, node_count, order, v0,
                                                       e1, e2, eps, planes, stack)
            out_t2[i] = t2
            out_rec[i] = tr
            out_factor[i] = fac
            if tr >= 0:
                out_uv[i, 0] = tri_uv[tr, 0, 0] + ur * (tri_uv[tr, 1, 0] - tri_uv[tr, 0, 0]) + vr * (tri_uv[tr, 2, 0] - tri_uv[tr, 0, 0])
                out_uv[i, 1] = tri_uv[tr, 0, 1] + ur * (tri_uv[tr, 1, 1] - tri_uv[tr, 0, 1]) + vr * (tri_uv[tr, 2, 1] - tri_uv[tr, 0, 1])
            else:
                out_uv[i, 0] = np.nan
                out_uv[i, 1] = np.nan


def refine_image_triangles(trace, n_emitters, receiver_of_tri, texel_size, grid=4, max_depth=6, tolerance=0.5,
                           keep_lost_depth=1, partial_depth=None, relative=0.01, weight=None, coarse=0,
                           coarse_texels=COARSE_TEXELS, shared=True, kernel_scene=None, top_points=None, planes=None,
                           coarse_linear_texels=COARSE_LINEAR_TEXELS):
    """Step 2: adaptive sub-triangles of every emitter's first triangle.

    ``trace(emitter, u1, v1) -> (t2, rec_tri, uv[, factor])`` traces points
    (:func:`trace_chain_points`; ``factor`` the transport factor, 1 when not given);
    ``receiver_of_tri`` (n_triangles,) receiver index per scene triangle (-1: not a receiver);
    ``texel_size`` (receivers,) the UV size of one texel (1 / max(W, H)); ``weight(emitter,
    bary (m, k, 2)) -> (m, k)`` the light's flux per area of the first triangle at those
    points (None: uniform).  A sub-triangle is final when its 3 corners and 3 edge midpoints
    land on one receiver and every midpoint's UV lies within ``tolerance`` texels of its
    edge's straight midpoint and (images larger than a texel) its flux density is linear over
    the image to within ``relative``: the midpoint shift within ``relative`` x its longest
    edge, and the density (weight x factor / |det J|, J the quadratic element's Jacobian) at
    each edge midpoint within ``relative`` of the mean of its corners' (a fold, where det J
    changes sign, is never linear) — or at ``max_depth``.  Partly landed sub-triangles (on
    the border of what lands) whose points fit one straight border are cut there once their
    whole image is within ``BORDER_TEXELS`` of a texel (:func:`_image_size`; or at
    ``max_depth``): the border is bisected on both crossed edges (``BORDER_STEPS``) and the
    landed polygon's fan triangles are final (landed 1; a border curved at their size splits
    them further).  Other partly landed ones are split down to ``partial_depth`` (default:
    ``max_depth`` + 2), or until their whole image is within ``ROUGH_TEXELS`` of a texel, and
    then seeded / splatted over the hull of their landed points with the landed fraction of
    the 6 points and 7 probes as their share of the flux.  A sub-triangle none of whose 6
    points lands is dropped from depth ``keep_lost_depth`` on, unless one of the 7 probes
    (edge quarter points, centroid) lands: the corner of a landed region can poke into it
    between the 6 points (the corner of a slab's image did).

    ``coarse`` > 0 starts ``coarse`` levels above the grid (the G/2^coarse grid at depth
    -coarse; G must be divisible by 2^coarse): a sub-triangle there is final when it passes
    the tests above, its density is linear even if its image is within a texel (a focus
    inside a texel: the glass sphere's, tests/bake/test_bake_caustics.py) and its image is at
    most ``coarse_texels`` long (texels), an image longer than ``coarse_linear_texels`` being
    linear to ``relative`` x (coarse_linear_texels / its length)² (a linear splat's error
    shows texel by texel on a large image), else it is split
    (never cut above depth 0; probed and dropped there only where ``keep_lost_depth``, which
    may be given per emitter, is negative).  The midpoint split of the coarse grid gives
    exactly the G x G grid (the same triangles, the same corner order, the same traced
    points), so what is not final above depth 0 is refined as with ``coarse`` = 0; the coarse
    levels only let small images (a finely tessellated caster: 115k-triangle water) stop
    early, with far fewer sub-triangles, each still straight to ``tolerance`` with a linear
    density (tests/solver/test_solver_forward_image.py, tests/bake/test_bake_forward_flux.py).
    ``shared``: a corner or edge midpoint shared by sub-triangles of one emitter is traced
    once (:func:`_traced_shared`; the same result as tracing it for each, which False does).
    ``planes`` (:mod:`~addon.solver.geometry.receiver_planes`, the ones ``trace`` extends rays
    onto): a landed sub-triangle whose 6 points lie beyond one edge of its flat receiver's UV
    region by more than twice its deviation and a texel is dropped (its image misses the
    region); one reaching across an edge is refined and kept like any landed one (the splat
    clips it at the edge).
    ``top_points`` (rec (n, 6), uv (n, 6, 2), factor (n, 6)): when the start is the whole
    triangle (G = 2^coarse), the traces of its corners and edge midpoints (01, 12, 20), used
    instead of tracing them (:func:`~addon.solver.estimators.refine_kernel.mesh_point_traces`:
    a mesh's shared points traced once; counted by the caller).
    ``kernel_scene`` (with ``shared``): (``trace_chain_points``' arguments from x0 to planes,
    parallel, device) of the scene ``trace`` traces, ``weight`` then being :func:`light_area_density`
    (or uniform for parallel light): the sub-triangles whose 6 points land on one receiver are
    refined by :func:`~addon.solver.estimators.refine_kernel.refine_landed` in one kernel (on
    ``device``, an OpenCL tracer, when it is not None), the others handed back to the levels
    below with the same rules (the same final sub-triangles, in another order); without a
    device the straight borders are cut in a Numba kernel too.

    Returns dict, the sub-triangles in emitter order: emitter (m,), bary (m, 3, 2) corners in the first triangle's (u1, v1),
    uv (m, 3, 2) their landing UVs, receiver (m,), deviation (m,) UV units, landed (m,) the
    share of the flux that lands (1 but for the approximated partly landed ones), bary_full
    (m, 3, 2) the sub-triangle itself (``bary`` of a partly landed one is shrunk to landed
    points), mid_uv (m, 3, 2) the landing UVs of the edge midpoints (01, 12, 20; NaN for partly
    landed ones), factor (m, 6) the transport factor at the corners and midpoints, and counts
    (traced points, dropped sub-triangles at the deepest level, partly landed ones seeded
    over their landed points' hull (``partial``), partly landed ones cut at a straight
    border (``border``), final per depth from depth 0 on, ``final_coarse`` per level above it)."""
    g = int(grid)
    c0 = int(coarse)
    if c0 < 0 or g % (1 << c0):
        raise ValueError("the grid must be divisible by 2^coarse")
    partial_depth = int(max_depth) + 2 if partial_depth is None else max(int(partial_depth), int(max_depth))
    dyadic = g << (partial_depth + 1) if shared else 0  # every corner and midpoint is a multiple of 1 / dyadic
    g >>= c0
    corners = []
    for i in range(g):
        for j in range(g - i):
            a, b, c = (i, j), (i + 1, j), (i, j + 1)
            corners.append((a, b, c))
            if i + j + 1 < g:
                corners.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
    base = np.array(corners, dtype=np.float64) / g  # (g², 3, 2)
    ne = int(n_emitters)
    keep_lost = np.broadcast_to(np.asarray(keep_lost_depth, dtype=np.int64), (ne,))  # per emitter
    out = {k: [] for k in ("emitter", "bary", "uv", "receiver", "deviation", "landed", "bary_full", "mid_uv", "factor")}
    kernel_seconds = 0.0  # in the refine and border kernels (they trace and decide in one)
    # depth -> sub-triangles joining that level (emitter, bary, rec, uv, fac, inherited) with their
    # edge midpoints' (rec, uv, fac), traced already: the kernel's handed-back ones, or the given
    # whole triangles' midpoints (top_points)
    handed = {}
    kernel_finals = None
    # the border kernel traces on Numba: with a device, the border rows are traced through ``trace``
    border_scene = kernel_scene[0] if kernel_scene is not None and kernel_scene[2] is None else None
    whole = base.shape[0] == 1 and top_points is not None and np.asarray(top_points[0]).shape[0] == ne
    if kernel_scene is not None and dyadic:
        from .refine_kernel import refine_landed

        trace_args, parallel, device = kernel_scene
        kernel_clock = time.perf_counter()
        k = refine_landed(ne, base, -c0, dyadic, trace_args, receiver_of_tri, texel_size, tolerance, relative, coarse_texels,
                          coarse_linear_texels, max_depth, weight is not None, parallel, top_points if whole else None,
                          device=device)
        traced = k["traced"]
        kernel_seconds += time.perf_counter() - kernel_clock
        kernel_finals = k["depth"]
        nk = k["emitter"].size
        out["emitter"].append(k["emitter"])
        out["bary"].append(k["bary"])
        out["uv"].append(k["uv"])
        out["receiver"].append(k["receiver"])
        out["deviation"].append(k["deviation"])
        out["bary_full"].append(k["bary"])
        out["mid_uv"].append(k["mid_uv"])
        out["landed"].append(np.ones(nk))
        out["factor"].append(k["factor"])
        for d in np.unique(k["hand_depth"]):
            sel = np.flatnonzero(k["hand_depth"] == d)
            handed[int(d)] = (k["hand_emitter"][sel], k["hand_bary"][sel], k["hand_rec"][sel, :3], k["hand_uv"][sel, :3],
                              k["hand_fac"][sel, :3], k["hand_inherited"][sel],
                              (k["hand_rec"][sel, 3:], k["hand_uv"][sel, 3:], k["hand_fac"][sel, 3:]))
        emitter = np.zeros(0, dtype=np.int64)
        bary, rec, uv, fac = np.zeros((0, 3, 2)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3, 2)), np.zeros((0, 3))
        inherited = np.zeros(0)
    elif whole:  # the whole triangles' points are given
        emitter = np.arange(ne, dtype=np.int64)
        bary = np.tile(base, (ne, 1, 1))
        t_rec, t_uv, t_fac = (np.asarray(a) for a in top_points)
        rec, uv, fac = t_rec[:, :3].astype(np.int64), t_uv[:, :3].copy(), t_fac[:, :3].copy()
        handed[-c0] = (emitter[:0], bary[:0], rec[:0], uv[:0], fac[:0], np.zeros(0),
                       (t_rec[:, 3:].astype(np.int64), t_uv[:, 3:].copy(), t_fac[:, 3:].copy()))
        traced = 0
        inherited = np.full(ne, np.inf)
    else:
        emitter = np.repeat(np.arange(ne, dtype=np.int64), base.shape[0])
        bary = np.tile(base, (ne, 1, 1))
        # corner records: a corner shared by sub-triangles of one emitter is traced once
        _t2, rec, uv, fac, traced = _traced_shared(trace, emitter, bary, dyadic)
        rec = rec.reshape(-1, 3)
        uv = uv.reshape(-1, 3, 2)
        fac = fac.reshape(-1, 3)
        inherited = np.full(emitter.size, np.inf)
    dropped = 0
    partial_count = 0
    border_count = 0
    final_per_depth = []
    final_coarse = []
    for depth in range(-c0, partial_depth + 1):
        known = None  # the level's last rows' midpoints, traced already
        if depth in handed:
            he, hb, hr, hu, hf, hi, known = handed.pop(depth)
            emitter = np.concatenate([emitter, he])
            bary = np.concatenate([bary, hb])
            rec = np.concatenate([rec, hr])
            uv = np.concatenate([uv, hu])
            fac = np.concatenate([fac, hf])
            inherited = np.concatenate([inherited, hi])
        m = emitter.size
        if depth == 0:
            inherited = np.full(m, np.inf)  # as without coarse levels
        if m == 0:
            (final_per_depth if depth >= 0 else final_coarse).append(0)
            continue
        mid = 0.5 * (bary + bary[:, [1, 2, 0]])  # midpoints of edges (0,1), (1,2), (2,0)
        nk = 0 if known is None else known[0].shape[0]  # the last nk rows' midpoints: traced by the kernel
        _mt2, mrec, muv, mfac, count = _traced_shared(trace, emitter[:m - nk], mid[:m - nk], dyadic)  # an edge's midpoint once
        if nk:
            mrec = np.concatenate([mrec.reshape(-1, 3), known[0]]).reshape(-1)
            muv = np.concatenate([muv.reshape(-1, 3, 2), known[1]]).reshape(-1, 2)
            mfac = np.concatenate([mfac.reshape(-1, 3), known[2]]).reshape(-1)
        traced += count
        mrec = mrec.reshape(-1, 3)
        muv = muv.reshape(-1, 3, 2)
        mfac = mfac.reshape(-1, 3)
        rall = np.concatenate([rec, mrec], axis=1)
        robj = np.where(rall >= 0, receiver_of_tri[np.maximum(rall, 0)], -1)
        landed = (robj[:, 0] >= 0) & np.all(robj == robj[:, :1], axis=1)
        lost = np.all(robj < 0, axis=1)
        kl = keep_lost[emitter]
        probe = np.flatnonzero(lost & (depth >= kl) & (depth < partial_depth))
        if probe.size:
            lost[probe[_probe_lands(trace, emitter[probe], bary[probe], receiver_of_tri)]] = False
            traced += 7 * probe.size
        straight = 0.5 * (uv + uv[:, [1, 2, 0]])
        dev = np.where(landed, np.nan_to_num(np.abs(muv - straight).max(axis=(1, 2)), nan=np.inf), np.inf)
        tex = texel_size[np.maximum(robj[:, 0], 0)]
        # Straight to within `tolerance` texels, and (for images larger than a texel) a flux
        # density nearly uniform over the image: the midpoint shift, relative to the edge,
        # measures the density's variation (zero for an affine map).
        edge = np.nan_to_num(np.abs(uv - uv[:, [1, 2, 0]]).max(axis=(1, 2)), nan=np.inf)
        # coarse levels: images longer than coarse_linear_texels must be linear to `relative`
        # x (coarse_linear_texels / length)² (a linear splat's error shows texel by texel
        # once the image spans several texels)
        rel = relative
        if depth < 0:
            rel = relative * np.minimum(1.0, (coarse_linear_texels * tex / np.maximum(edge, 1e-300)) ** 2)
        with np.errstate(invalid="ignore"):  # 0 x inf where nothing landed: not linear
            linear = dev <= rel * edge
        if weight is not None and landed.any():
            li = np.flatnonzero(landed & linear)
            if li.size:
                w6 = weight(emitter[li], np.concatenate([bary[li], mid[li]], axis=1))
                w6 = w6 * np.concatenate([fac[li], mfac[li]], axis=1)
                linear[li] = density_nonlinearity(uv[li], muv[li], w6) <= (rel[li] if depth < 0 else rel)
        final = landed & (dev <= tolerance * tex) & (linear | (edge <= tex))
        if depth < 0:  # coarse: small, and a linear density whatever its size (a focus inside a texel is not)
            final = landed & (dev <= tolerance * tex) & linear & (edge <= coarse_texels * tex)
        if depth >= int(max_depth):
            final = landed  # as straight as the depth allows: its deviation widens its margin
        # an image beyond an edge of a flat receiver's region (its points extended there) by
        # more than its deviation and a texel lands nowhere: dropped (receiver_planes)
        outside = np.zeros(m, dtype=np.bool_)
        if planes is not None and planes.shape[0] and landed.any():
            li = np.flatnonzero(landed)
            outside[li] = beyond_region_rows(planes, robj[li, 0], np.concatenate([uv[li], muv[li]], axis=1),
                                             2.0 * dev[li] + tex[li])
            final &= ~outside
        last = depth == partial_depth
        # Partly landed (an edge of the receiver, a silhouette, total internal reflection):
        # when its 6 points fit one straight border (one receiver, one or two corners landed,
        # every midpoint agreeing with its edge's corners) and its whole image is within
        # BORDER_TEXELS (or at ``max_depth``), the border is located on both crossed edges by
        # bisection and the landed polygon becomes final (_straight_border: its flux then
        # is exact but for the border's curvature inside the sub-triangle).  Any other is
        # split further and, from ``partial_depth`` on, seeded / splatted over the hull of
        # its landed points with their fraction of the flux (see _partial).
        cand = ~landed & ~lost & (depth >= 0)
        # image size per item in texels, handed down to the children (halved)
        scale = np.where(landed, edge / tex, inherited)
        border = np.zeros(m, dtype=np.bool_)
        small = np.zeros(m, dtype=np.bool_)
        ci = np.flatnonzero(cand)
        if ci.size:
            rc = np.max(robj[ci], axis=1)
            okc = (robj[ci] == rc[:, None]) & (robj[ci] >= 0)  # none for a probed 'lost' one
            size = _image_size(okc, bary[ci], mid[ci], uv[ci], muv[ci]) / texel_size[np.maximum(rc, 0)]
            # fewer than two landed points: half the parent's size (its image scale)
            size = np.where(np.isfinite(size), size, inherited[ci])
            scale[ci] = size
            border[ci] = _single_border(robj[ci]) & ((size <= BORDER_TEXELS) | (depth >= int(max_depth)))
            small[ci] = size <= ROUGH_TEXELS
        bi = np.flatnonzero(border)
        kernel_clock = time.perf_counter()
        b_em, b_bary, b_uv, b_rec, b_dev, b_take, b_traced = _straight_border(
            trace, emitter[bi], bary[bi], mid[bi], uv[bi], muv[bi], robj[bi], receiver_of_tri, BORDER_STEPS,
            depth >= int(max_depth), border_scene)
        traced += b_traced
        if border_scene is not None:
            kernel_seconds += time.perf_counter() - kernel_clock
        border[bi[~b_take]] = False  # a curved border: split further
        bi = bi[b_take]
        # a border that is not straight where the whole image is within ROUGH_TEXELS (a thin
        # sliver landed or lost, a corner): splitting further would only follow it at
        # sub-texel size (the metal ring's ragged self-shadow took millions of sub-triangles)
        # (a probed 'lost' one has no landed point to approximate from: it is split, or
        # dropped at the last level)
        partial = cand & ~border & ((depth >= partial_depth) | small) & np.any(robj >= 0, axis=1)
        drop = (~final & ~partial & ~border & last) | (lost & (depth >= kl)) | outside
        dropped += int(np.count_nonzero(~final & ~partial & ~border & last & ~lost & ~outside))
        fi = np.flatnonzero(final)
        pi = np.flatnonzero(partial)
        p_bary, p_uv, p_rec, p_dev = _partial(bary[pi], mid[pi], uv[pi], muv[pi], robj[pi])
        (final_per_depth if depth >= 0 else final_coarse).append(int(fi.size + pi.size + bi.size))
        nb = b_em.size
        out["emitter"].append(np.concatenate([emitter[fi], emitter[pi], b_em]))
        out["bary"].append(np.concatenate([bary[fi], p_bary, b_bary]))
        out["uv"].append(np.concatenate([uv[fi], p_uv, b_uv]))
        out["receiver"].append(np.concatenate([robj[fi, 0], p_rec, b_rec]))
        out["deviation"].append(np.concatenate([dev[fi], p_dev, b_dev]))
        out["bary_full"].append(np.concatenate([bary[fi], bary[pi], b_bary]))
        out["mid_uv"].append(np.concatenate([muv[fi], np.full((pi.size + nb, 3, 2), np.nan)]))
        # the share of a partly landed one: of its 6 points and 7 probes (13 points halve the
        # bias of 6 on thin slivers, which a fraction of 6 counts as 1/6 or 5/6)
        p_share = np.zeros(pi.size)
        if pi.size:
            probes = _probe_receivers(trace, emitter[pi], bary[pi], receiver_of_tri)
            traced += 7 * pi.size
            p_share = ((robj[pi] == p_rec[:, None]).sum(axis=1) + (probes == p_rec[:, None]).sum(axis=1)) / 13.0
        out["landed"].append(np.concatenate([np.ones(fi.size), p_share, np.ones(nb)]))
        out["factor"].append(np.concatenate([np.concatenate([fac[fi], mfac[fi]], axis=1), np.full((pi.size + nb, 6), np.nan)]))
        partial_count += int(pi.size)
        border_count += int(bi.size)
        final = final | partial | border
        split = np.flatnonzero(~final & ~drop)
        if split.size == 0:
            emitter, bary, rec, uv, fac, inherited = emitter[:0], bary[:0], rec[:0], uv[:0], fac[:0], inherited[:0]
            continue
        b, mb = bary[split], mid[split]
        r, mr = rec[split], mrec[split]
        u, mu = uv[split], muv[split]
        f, mf = fac[split], mfac[split]
        # children: (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)
        def kids(c, mc):
            a_, b_, c_ = c[:, 0], c[:, 1], c[:, 2]
            ab, bc, ca = mc[:, 0], mc[:, 1], mc[:, 2]
            return np.concatenate([np.stack(s, axis=1) for s in ((a_, ab, ca), (ab, b_, bc), (ca, bc, c_), (ab, bc, ca))])
        bary = kids(b, mb)
        rec = kids(r[:, :, None], mr[:, :, None])[:, :, 0]
        uv = kids(u, mu)
        fac = kids(f[:, :, None], mf[:, :, None])[:, :, 0]
        inherited = np.tile(0.5 * scale[split], 4)
        emitter = np.tile(emitter[split], 4)
    if kernel_finals is not None:  # the kernel's finals per level
        counts = np.bincount(kernel_finals + c0, minlength=c0 + partial_depth + 1)
        final_coarse = [a + int(b) for a, b in zip(final_coarse, counts[:c0])]
        final_per_depth = [a + int(b) for a, b in zip(final_per_depth, counts[c0:])]
    cat = {k: (np.concatenate(v) if v else None) for k, v in out.items()}
    if cat["emitter"] is None or cat["emitter"].size == 0:
        cat = dict(emitter=np.zeros(0, dtype=np.int64), bary=np.zeros((0, 3, 2)), uv=np.zeros((0, 3, 2)),
                   receiver=np.zeros(0, dtype=np.int64), deviation=np.zeros(0), landed=np.zeros(0),
                   bary_full=np.zeros((0, 3, 2)), mid_uv=np.zeros((0, 3, 2)), factor=np.zeros((0, 6)))
    # emitter order (stable: an emitter's own sub-triangles in the order its refinement made
    # them, which the other emitters do not change), so that flux splatted run after run of
    # emitters is summed in one order whatever the runs
    order = np.argsort(cat["emitter"], kind="stable")
    cat = {k: v[order] for k, v in cat.items()}
    cat["traced"] = traced
    cat["kernel_seconds"] = kernel_seconds
    cat["dropped"] = dropped
    cat["partial"] = partial_count
    cat["border"] = border_count
    cat["final_per_depth"] = final_per_depth
    cat["final_coarse"] = final_coarse
    return cat


def _traced(trace, e, u, v):
    """(t2, rec, uv, factor) of a trace function that may leave out the factor."""
    res = trace(e, u, v)
    if len(res) > 3:
        return res[0], res[1], res[2], np.asarray(res[3], dtype=np.float64)
    return res[0], res[1], res[2], np.ones(e.shape[0])


def _traced_shared(trace, emitter, pts, scale):
    """:func:`_traced` of the points ``pts`` (m, k, 2) of ``emitter`` (m,) (flattened, m k),
    each distinct (emitter, point) traced once (neighbouring sub-triangles share corners and
    edge midpoints), and the number of points traced.  The points are multiples of 1 /
    ``scale`` (the dyadic grid of the refinement), so equal points have equal integer keys;
    the result is the same as tracing every point (a point's trace is deterministic), which
    ``scale`` 0 does."""
    k = pts.shape[1]
    e = np.repeat(emitter, k)
    u = pts[:, :, 0].reshape(-1)
    v = pts[:, :, 1].reshape(-1)
    if not scale:
        t2, rec, uv, fac = _traced(trace, e, u, v)  # every point
        return t2, rec, uv, fac, e.size
    if e.size == 0:
        t2, rec, uv, fac = _traced(trace, e, u, v)
        return t2, rec, uv, fac, 0
    iu = np.rint(u * scale)
    iv = np.rint(v * scale)
    s1 = int(scale) + 1
    if (int(e.max()) + 1) * s1 * s1 >= 1 << 62 or not (np.array_equal(iu, u * scale) and np.array_equal(iv, v * scale)):
        t2, rec, uv, fac = _traced(trace, e, u, v)  # not on the grid (or too fine to key): every point
        return t2, rec, uv, fac, e.size
    key = (e * s1 + iu.astype(np.int64)) * s1 + iv.astype(np.int64)
    _uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    t2, rec, uv, fac = _traced(trace, e[first], np.ascontiguousarray(u[first]), np.ascontiguousarray(v[first]))
    inverse = inverse.reshape(-1)
    return t2[inverse], rec[inverse], uv[inverse], fac[inverse], first.size


def _single_border(robj):
    """For partly landed sub-triangles (robj (m, 6): receiver per corner then edge midpoint
    01, 12, 20; -1 lost): whether the points fit one straight border (landed on one
    receiver; one or two corners landed; each edge's midpoint landed when both its corners
    did and lost when neither did)."""
    rec = np.max(robj, axis=1)
    ok = (robj == rec[:, None]) & (robj >= 0)
    c = ok[:, :3]
    mid = ok[:, 3:]
    nc = c.sum(axis=1)
    a, b = c, c[:, [1, 2, 0]]
    agree = np.all(np.where(a == b, mid == a, True), axis=1)
    one_receiver = np.all((robj < 0) | ok, axis=1)
    return one_receiver & agree & (nc >= 1) & (nc <= 2)


def _image_size(ok, bary, mid, uv, muv):
    """(m,) an estimate of the size (UV) of whole partly landed sub-triangles' images: the
    largest UV / barycentric distance ratio among pairs of landed points times the longest
    edge (inf with fewer than two landed points)."""
    pb = np.concatenate([bary, mid], axis=1)
    pu = np.concatenate([uv, muv], axis=1)
    i, j = np.triu_indices(6, 1)
    db = np.linalg.norm(pb[:, i] - pb[:, j], axis=2)
    du = np.linalg.norm(np.nan_to_num(pu[:, i] - pu[:, j]), axis=2)
    ratio = np.where(ok[:, i] & ok[:, j], du / np.maximum(db, 1e-300), -1.0).max(axis=1)
    edge = np.linalg.norm(bary - bary[:, [1, 2, 0]], axis=2).max(axis=1)
    return np.where(ratio >= 0, ratio * edge, np.inf)


def _landed_span(ok, uv, muv):
    """(m, 2) the extent in u and v of the points flagged ``ok`` (m, 6) (inf where none)."""
    q = np.concatenate([uv, muv], axis=1)
    hi = np.where(ok[:, :, None], q, -np.inf).max(axis=1)
    lo = np.where(ok[:, :, None], q, np.inf).min(axis=1)
    return np.where(np.isfinite(hi - lo), hi - lo, np.inf)


def _landed_point(trace, emitter, h, rec, receiver_of_tri):
    """(landed on receiver ``rec``, uv) of the points ``h`` (n, 2)."""
    _t2, r, huv, _f = _traced(trace, emitter, np.ascontiguousarray(h[:, 0]), np.ascontiguousarray(h[:, 1]))
    return (r >= 0) & (np.where(r >= 0, receiver_of_tri[np.maximum(r, 0)], -1) == rec), huv


def _bisect_border(trace, emitter, lb, luv, xb, rec, receiver_of_tri, steps):
    """Bisect between landed points ``lb`` (uv ``luv``) and lost points ``xb``: (the border's
    estimate, the uv of the last landed point)."""
    for _ in range(steps):
        h = 0.5 * (lb + xb)
        hit, huv = _landed_point(trace, emitter, h, rec, receiver_of_tri)
        lb = np.where(hit[:, None], h, lb)
        luv = np.where(hit[:, None], huv, luv)
        xb = np.where(hit[:, None], xb, h)
    return 0.5 * (lb + xb), luv


def _border_point(trace, emitter, a, b, landed_c, rec, receiver_of_tri, steps):
    """The border point on the perpendicular to the chord a-b through its midpoint, bisected
    ``steps`` times within a quarter of the chord either side: (bary, uv of the last landed
    point, found (the landed side landed and the lost side did not), offset from the
    midpoint in chord lengths)."""
    mc = 0.5 * (a + b)
    d = b - a
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    toward_lost = np.where((np.einsum("ij,ij->i", landed_c - mc, nrm) > 0)[:, None], -nrm, nrm)
    a_b = mc - 0.25 * toward_lost
    b_b = mc + 0.25 * toward_lost
    m = a.shape[0]
    hit, huv = _landed_point(trace, np.concatenate([emitter, emitter]), np.concatenate([a_b, b_b]),
                             np.concatenate([rec, rec]), receiver_of_tri)
    found = hit[:m] & ~hit[m:]
    pb, puv = _bisect_border(trace, emitter, a_b, huv[:m], b_b, rec, receiver_of_tri, steps)
    t = np.einsum("ij,ij->i", pb - mc, toward_lost) / np.maximum(np.einsum("ij,ij->i", toward_lost, toward_lost), 1e-300)
    return pb, puv, found, t


def _straight_border(trace, emitter, bary, mid, uv, muv, robj, receiver_of_tri, steps, accept_all, kernel_scene=None):
    """The landed polygon of sub-triangles whose points fit one straight border
    (:func:`_single_border`).  The border is bisected ``steps`` times on the edge where the
    run of landed corners ends (X_exit) and where it starts (X_enter), starting from the half
    the edge midpoint leaves; then on the perpendicular through the chord's midpoint to a
    point P of the border itself, and likewise through the midpoints of the half-chords
    X_exit-P and P-X_enter (P_a, P_c; :func:`_border_point`): the border is straight enough
    when each is within 1/16 of its chord (one sample alone is fooled by a corner of the
    border, as at the corner of a slab's image).  Polygon: the landed corners, X_exit, P_a,
    P, P_c, X_enter (points left out where the perpendicular does not cross the border), cut
    into a fan from the first landed corner.  Rows that are not straight enough are
    returned for splitting unless ``accept_all``.  With ``kernel_scene`` (the arguments of
    ``trace_chain_points`` from x0 to planes, of the scene ``trace`` traces) the rows are traced
    in one kernel (:func:`~addon.solver.estimators.border_kernel.border_polygons`: the same points).

    Returns (emitter, bary (k, 3, 2), uv (k, 3, 2), receiver (k,), deviation (k,) 1/16 of the
    landed UV span (a seeding margin), rows (m,) taken, points traced)."""
    m = emitter.shape[0]
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 3, 2)), np.zeros((0, 3, 2)), np.zeros(0, dtype=np.int64), np.zeros(0))
    if m == 0:
        return empty + (np.zeros(0, dtype=np.bool_), 0)
    traced = 2 * steps * m + 3 * (steps + 2) * m
    if kernel_scene is not None:
        from .border_kernel import border_polygons

        straight = np.zeros(m, dtype=np.bool_)
        count = np.zeros(m, dtype=np.int64)
        poly_b = np.zeros((m, 7, 2))
        poly_uv = np.zeros((m, 7, 2))
        span = np.zeros(m)
        border_polygons(np.ascontiguousarray(emitter, dtype=np.int64), np.ascontiguousarray(bary), np.ascontiguousarray(mid),
                        np.ascontiguousarray(uv), np.ascontiguousarray(muv), np.ascontiguousarray(robj, dtype=np.int64),
                        np.ascontiguousarray(receiver_of_tri, dtype=np.int64), int(steps), *kernel_scene, straight, count,
                        poly_b, poly_uv, span)
        rec = np.max(robj, axis=1)
    else:
        rec, straight, count, poly_b, poly_uv, span = _border_polygons_numpy(trace, emitter, bary, mid, uv, muv, robj,
                                                                             receiver_of_tri, steps)
    take = straight | accept_all
    fan_b, fan_uv, fan_row = [], [], []
    for k in range(1, 6):
        sel = np.flatnonzero(take & (count >= k + 2))
        fan_b.append(poly_b[sel][:, [0, k, k + 1]])
        fan_uv.append(poly_uv[sel][:, [0, k, k + 1]])
        fan_row.append(sel)
    fr = np.concatenate(fan_row)
    return emitter[fr], np.concatenate(fan_b), np.concatenate(fan_uv), rec[fr], span[fr], take, traced


def _border_polygons_numpy(trace, emitter, bary, mid, uv, muv, robj, receiver_of_tri, steps):
    """The rows of :func:`_straight_border` in numpy: (receiver, straight, polygon point count,
    polygon bary, polygon uv, seeding margin)."""
    m = emitter.shape[0]
    rows = np.arange(m)
    rec = np.max(robj, axis=1)
    ok = robj == rec[:, None]
    c, cm = ok[:, :3], ok[:, 3:]
    nc = c.sum(axis=1)
    start = np.argmax(c & ~c[:, [2, 0, 1]], axis=1)  # the landed corner after a lost one
    last = (start + nc - 1) % 3

    def crossing(land, lost_, mid_index):
        mid_ok = cm[rows, mid_index]
        lb = np.where(mid_ok[:, None], mid[rows, mid_index], bary[rows, land])
        luv = np.where(mid_ok[:, None], muv[rows, mid_index], uv[rows, land])
        xb = np.where(mid_ok[:, None], bary[rows, lost_], mid[rows, mid_index])
        return _bisect_border(trace, emitter, lb, luv, xb, rec, receiver_of_tri, steps)

    x_exit, uv_exit = crossing(last, (last + 1) % 3, last)  # edge (last, last + 1): midpoint index last
    x_enter, uv_enter = crossing(start, (start + 2) % 3, (start + 2) % 3)  # edge (start - 1, start)
    landed_c = (bary * c[:, :, None]).sum(axis=1) / nc[:, None]
    # the border between the crossings, sampled at the chord's midpoint and then at the two
    # half-chords' (a single sample is fooled by a corner of the border: the slab image's)
    pb, puv, ok0, t0 = _border_point(trace, emitter, x_exit, x_enter, landed_c, rec, receiver_of_tri, steps)
    pa_b, pa_uv, ok1, t1 = _border_point(trace, emitter, x_exit, pb, landed_c, rec, receiver_of_tri, steps)
    pc_b, pc_uv, ok2, t2 = _border_point(trace, emitter, pb, x_enter, landed_c, rec, receiver_of_tri, steps)
    straight = ok0 & ok1 & ok2 & (np.maximum(np.maximum(np.abs(t0), np.abs(t1)), np.abs(t2)) <= 1.0 / 16.0)
    ok1 &= ok0
    ok2 &= ok0
    # polygon: landed corners from `start`, X_exit, [P_a, P, P_c], X_enter
    poly_b = np.zeros((m, 7, 2))
    poly_uv = np.zeros((m, 7, 2))
    count = np.zeros(m, dtype=np.int64)
    for k in range(2):
        sel = nc > k
        ck = (start + k) % 3
        poly_b[rows[sel], count[sel]] = bary[rows[sel], ck[sel]]
        poly_uv[rows[sel], count[sel]] = uv[rows[sel], ck[sel]]
        count += sel
    every = np.ones(m, dtype=np.bool_)
    for pt_b, pt_uv, sel in ((x_exit, uv_exit, every), (pa_b, pa_uv, ok1), (pb, puv, ok0), (pc_b, pc_uv, ok2),
                             (x_enter, uv_enter, every)):
        poly_b[rows[sel], count[sel]] = pt_b[sel]
        poly_uv[rows[sel], count[sel]] = pt_uv[sel]
        count += sel
    # seeding margin: the polygon's points are traced, its sides straight to ~1/16 of a chord
    span = np.sqrt((_landed_span(ok, uv, muv) ** 2).sum(axis=1)) / 16.0
    return rec, straight, count, poly_b, poly_uv, span


def _probe_receivers(trace, emitter, bary, receiver_of_tri):
    """(m, 7) the receiver (-1: lost) of 7 probes of each sub-triangle: the quarter points of
    its edges and its centroid."""
    pts = np.concatenate([0.75 * bary + 0.25 * bary[:, [1, 2, 0]], 0.25 * bary + 0.75 * bary[:, [1, 2, 0]],
                          bary.mean(axis=1, keepdims=True)], axis=1)  # (m, 7, 2)
    _t2, rec, _uv, _f = _traced(trace, np.repeat(emitter, 7), pts[:, :, 0].reshape(-1), pts[:, :, 1].reshape(-1))
    return np.where(rec >= 0, receiver_of_tri[np.maximum(rec, 0)], -1).reshape(-1, 7)


def _probe_lands(trace, emitter, bary, receiver_of_tri):
    """(m,) whether any of the 7 probes of each sub-triangle (:func:`_probe_receivers`) lands."""
    return (_probe_receivers(trace, emitter, bary, receiver_of_tri) >= 0).any(axis=1)


def quadratic_jacobian_dets(uv, mid_uv):
    """det of the Jacobian d(uv)/d(s, t) of the quadratic triangle through the corner images
    ``uv`` (m, 3, 2) and edge-midpoint images ``mid_uv`` (m, 3, 2; edges 01, 12, 20), at the
    3 corners and the 3 edge midpoints: (m, 6).  From the derivatives of the 6-node shape
    functions N0 = (1-s-t)(1-2s-2t), N1 = s(2s-1), N2 = t(2t-1), N01 = 4s(1-s-t), N12 = 4st,
    N20 = 4t(1-s-t)."""
    c0, c1, c2 = uv[:, 0], uv[:, 1], uv[:, 2]
    m01, m12, m20 = mid_uv[:, 0], mid_uv[:, 1], mid_uv[:, 2]
    ds = (-3 * c0 - c1 + 4 * m01, c0 + 3 * c1 - 4 * m01, c0 - c1 + 4 * m12 - 4 * m20,  # corners 0, 1, 2
          c1 - c0, c0 + c1 - 2 * m01 + 2 * m12 - 2 * m20, -c0 - c1 + 2 * m01 + 2 * m12 - 2 * m20)  # midpoints
    dt = (-3 * c0 - c2 + 4 * m20, c0 - c2 - 4 * m01 + 4 * m12, c0 + 3 * c2 - 4 * m20,
          -c0 - c2 - 2 * m01 + 2 * m12 + 2 * m20, c0 + c2 - 2 * m01 + 2 * m12 - 2 * m20, c2 - c0)
    return np.stack([a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] for a, b in zip(ds, dt)], axis=1)


def density_nonlinearity(uv, mid_uv, w6):
    """How far the flux density over each sub-triangle's image is from linear: with
    rho = w6 / |det J| at the 3 corners and 3 edge midpoints (w6 (m, 6) the flux per
    barycentric area there, J from :func:`quadratic_jacobian_dets`), the largest
    |rho(midpoint) - mean(rho(its corners))| relative to the corners' mean rho; inf where
    det J changes sign (a fold) or is not finite."""
    det = quadratic_jacobian_dets(uv, mid_uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.abs(w6) / np.abs(det)
        lin = 0.5 * (rho[:, [0, 1, 2]] + rho[:, [1, 2, 0]])
        out = np.abs(rho[:, 3:] - lin).max(axis=1) / rho[:, :3].mean(axis=1)
    same = np.all(det > 0, axis=1) | np.all(det < 0, axis=1)
    return np.where(same & np.isfinite(out), out, np.inf)


def light_area_density(x0, tri, bary):
    """The light's solid angle per barycentric area of the first triangles ``tri`` (m, 3, 3)
    seen from ``x0`` (m, 3), at the points ``bary`` (m, k, 2): |n . (p - x0)| / |p - x0|³ with
    n the (unnormalised) cross product of the triangle's edges.  (m, k)."""
    p = tri[:, None, 0] + bary[..., :1] * (tri[:, None, 1] - tri[:, None, 0]) + bary[..., 1:] * (tri[:, None, 2] - tri[:, None, 0])
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    d = p - x0[:, None, :]
    return np.abs(np.einsum("nj,nij->ni", nrm, d)) / np.linalg.norm(d, axis=2) ** 3


def corner_densities(uv, mid_uv, x0, tri, bary, factor=None):
    """Relative flux density (per UV area) at the three corners of each sub-triangle's image,
    for a splat whose density varies linearly over the image instead of being uniform (second
    order in the sub-triangle's size instead of first).  The image is the quadratic triangle
    through the corner and edge-midpoint images: at corner i its Jacobian J_i (2x2, from the
    quadratic shape functions' derivatives, :func:`quadratic_jacobian_dets`), and the light's
    solid angle per barycentric area there w_i (:func:`light_area_density`; ``bary`` (m, 3, 2)
    the sub-triangle's corners in its first triangle ``tri`` (m, 3, 3)) times the transport
    factor there (``factor`` (m, 3), optional); density_i = w_i / |det J_i|.  Rows where the
    Jacobians change sign or differ by more than 4x (near a fold), without midpoints, or whose
    image is a sliver (``SLIVER``), get (1, 1, 1): the uniform splat."""
    det = quadratic_jacobian_dets(uv, mid_uv)[:, :3]
    w = light_area_density(x0, tri, bary)
    if factor is not None:
        w = w * factor
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = w / np.abs(det)
        ratio = rho.max(axis=1) / rho.min(axis=1)
        # a sliver image (longest edge² / twice its area above SLIVER) takes the uniform
        # splat: its det J is a small difference of nearly parallel derivatives, whose
        # second-order error the aspect ratio amplifies (the metal ring's outer reflections,
        # aspect 5.7: a ±13 % ramp where the true density is flat, texels 6 % off)
        e = uv - uv[:, [1, 2, 0]]
        area2 = np.abs(e[:, 0, 0] * e[:, 2, 1] - e[:, 0, 1] * e[:, 2, 0])
        aspect = (e ** 2).sum(axis=2).max(axis=1) / area2
    same = ((np.all(det > 0, axis=1) | np.all(det < 0, axis=1)) & np.isfinite(ratio) & (ratio <= 4.0)
            & np.isfinite(aspect) & (aspect <= SLIVER))
    return np.where(same[:, None], rho / np.where(same, rho.mean(axis=1), 1.0)[:, None], 1.0)


def solid_angle(x0, corners):
    """Solid angle (sr) of the triangles ``corners`` (n, 3, 3) seen from ``x0`` (n, 3)
    (Van Oosterom & Strackee 1983)."""
    a = corners[:, 0] - x0
    b = corners[:, 1] - x0
    c = corners[:, 2] - x0
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = np.abs(np.sum(a * np.cross(b, c), axis=1))
    den = la * lb * lc + np.sum(a * b, axis=1) * lc + np.sum(a * c, axis=1) * lb + np.sum(b * c, axis=1) * la
    return 2.0 * np.arctan2(num, den)


def _partial(bary, mid, uv, muv, robj):
    """Partly landed sub-triangles as seeding triangles: the receiver of the most landed points;
    lost corners replaced by the landed point (corner or midpoint) nearest in (u1, v1); the
    deviation (margin) grown to the largest UV distance between the landed points, so the
    grown image covers the landed part."""
    m = bary.shape[0]
    if m == 0:
        return np.zeros((0, 3, 2)), np.zeros((0, 3, 2)), np.zeros(0, dtype=np.int64), np.zeros(0)
    pts_b = np.concatenate([bary, mid], axis=1)  # (m, 6, 2)
    pts_uv = np.concatenate([uv, muv], axis=1)
    rec = robj[np.arange(m), np.argmax(robj >= 0, axis=1)]  # the first landed point's receiver
    for i in np.flatnonzero(np.any((robj >= 0) & (robj != rec[:, None]), axis=1)):  # rare: two receivers
        vals, cnt = np.unique(robj[i][robj[i] >= 0], return_counts=True)
        rec[i] = vals[np.argmax(cnt)]
    ok = robj == rec[:, None]  # (m, 6) landed on the chosen receiver
    d = np.linalg.norm(pts_b[:, :3, None, :] - pts_b[:, None, :, :], axis=-1)  # (m, 3, 6)
    d = np.where(ok[:, None, :], d, np.inf)
    nearest = np.argmin(d, axis=2)  # (m, 3)
    rows = np.arange(m)[:, None]
    nb = pts_b[rows, nearest]
    nuv = pts_uv[rows, nearest]
    dev = np.sqrt((_landed_span(ok, uv, muv) ** 2).sum(axis=1))
    return nb, nuv, rec, dev


@kernel(inline="always")
def _closest_on_triangle(px, py, ax, ay, bx, by, cx, cy):
    """Closest point of triangle abc (2-D) to p as barycentric weights (wa, wb, wc) and the
    squared distance (Ericson, Real-Time Collision Detection §5.1.5); robust for slivers."""
    abx, aby = bx - ax, by - ay
    acx, acy = cx - ax, cy - ay
    apx, apy = px - ax, py - ay
    d1 = abx * apx + aby * apy
    d2 = acx * apx + acy * apy
    if d1 <= 0.0 and d2 <= 0.0:
        wa, wb, wc = 1.0, 0.0, 0.0
    else:
        bpx, bpy = px - bx, py - by
        d3 = abx * bpx + aby * bpy
        d4 = acx * bpx + acy * bpy
        cpx, cpy = px - cx, py - cy
        d5 = abx * cpx + aby * cpy
        d6 = acx * cpx + acy * cpy
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            wa, wb, wc = 0.0, 1.0, 0.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            t = d1 / (d1 - d3)
            wa, wb, wc = 1.0 - t, t, 0.0
        elif d6 >= 0.0 and d5 <= d6:
            wa, wb, wc = 0.0, 0.0, 1.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            t = d2 / (d2 - d6)
            wa, wb, wc = 1.0 - t, 0.0, t
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            wa, wb, wc = 0.0, 1.0 - t, t
        else:
            den = va + vb + vc
            if den > 0.0:
                wb = vb / den
                wc = vc / den
                wa = 1.0 - wb - wc
            else:
                wa, wb, wc = 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0
    qx = wa * ax + wb * bx + wc * cx
    qy = wa * ay + wb * by + wc * cy
    return wa, wb, wc, (qx - px) * (qx - px) + (qy - py) * (qy - py)


@parallel_range("tri_uv")
def _emit(fill, tri_uv, tri_bary, tri_emitter, margin, W, H, row0, row1, tex_start, tex_order, sample_uv, offset, count,
          out_e, out_seed, out_s, first, last):
    for t in range(first, last):
        c = 0
        o = offset[t] if fill else 0
        ax, ay = tri_uv[t, 0, 0], tri_uv[t, 0, 1]
        bx, by = tri_uv[t, 1, 0], tri_uv[t, 1, 1]
        cx, cy = tri_uv[t, 2, 0], tri_uv[t, 2, 1]
        mg = margin[t]
        i0 = max(0, int(math.floor((min(ax, bx, cx) - mg) * W)))
        i1 = min(W - 1, int(math.floor((max(ax, bx, cx) + mg) * W)))
        j0 = max(row0, int(math.floor((min(ay, by, cy) - mg) * H)))
        j1 = min(row1 - 1, int(math.floor((max(ay, by, cy) + mg) * H)))
        m2 = mg * mg
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                tex = (j - row0) * W + i
                for z in range(tex_start[tex], tex_start[tex + 1]):
                    s = tex_order[z]
                    wa, wb, wc, d2 = _closest_on_triangle(sample_uv[s, 0], sample_uv[s, 1], ax, ay, bx, by, cx, cy)
                    if d2 > m2:
                        continue
                    if fill:
                        out_e[o] = tri_emitter[t]
                        out_seed[o, 0] = wa * tri_bary[t, 0, 0] + wb * tri_bary[t, 1, 0] + wc * tri_bary[t, 2, 0]
                        out_seed[o, 1] = wa * tri_bary[t, 0, 1] + wb * tri_bary[t, 1, 1] + wc * tri_bary[t, 2, 1]
                        out_s[o] = s
                        o += 1
                    c += 1
        count[t] = c


class ImageSeeds:
    """Step 3 for one receiver band: (emitter, seed (u1, v1), sample) for every sample within
    ``margin`` (UV units, per sub-triangle) of a sub-triangle's straight image; the seed is the
    point of the sub-triangle whose straight image is closest to the sample.  ``sample_texel``:
    flat texel index j W + i of each band sample, ``sample_uv`` its texture coordinates.
    :meth:`batches` yields the seeds in batches of about ``max_seeds`` (whole sub-triangles)."""

    def __init__(self, tri_uv, tri_bary, tri_emitter, margin, width, height, row0, row1, sample_texel, sample_uv):
        W, H = int(width), int(height)
        tex = np.asarray(sample_texel, dtype=np.int64) - int(row0) * W
        order = np.argsort(tex, kind="stable").astype(np.int64)
        tex_start = np.searchsorted(tex[order], np.arange((int(row1) - int(row0)) * W + 1)).astype(np.int64)
        self.n = tri_uv.shape[0]
        self.count = np.zeros(self.n, dtype=np.int64)
        self._args = (np.ascontiguousarray(tri_uv, dtype=np.float64), np.ascontiguousarray(tri_bary, dtype=np.float64),
                      np.ascontiguousarray(tri_emitter, dtype=np.int64), np.ascontiguousarray(margin, dtype=np.float64), W,
                      H, int(row0), int(row1), tex_start, order, np.ascontiguousarray(sample_uv, dtype=np.float64))
        z = np.zeros(0, dtype=np.int64)
        if self.n:
            _emit(False, *self._args, z, self.count, z, np.zeros((0, 2)), z)

    @property
    def total(self):
        return int(self.count.sum())

    def batches(self, max_seeds=1 << 20):
        csum = np.cumsum(self.count)
        q = 0
        while q < self.n:
            base = csum[q - 1] if q else 0
            q1 = max(q + 1, int(np.searchsorted(csum, base + max_seeds, side="right")))
            a = self._args
            cnt = np.zeros(q1 - q, dtype=np.int64)
            offset = np.concatenate([[0], np.cumsum(self.count[q:q1])[:-1]]).astype(np.int64)
            total = int(self.count[q:q1].sum())
            out_e = np.empty(total, dtype=np.int64)
            out_seed = np.empty((total, 2))
            out_s = np.empty(total, dtype=np.int64)
            if total:
                _emit(True, a[0][q:q1], a[1][q:q1], a[2][q:q1], a[3][q:q1], *a[4:], offset, cnt, out_e, out_seed, out_s)
                yield out_e, out_seed, out_s
            q = q1


@parallel_range("emitter", CHUNK)
def solve_image_seeds(emitter, seed, sample, x0, t1_of, x_end, refract1, refract2, second_ok, tri_rec, tri_p, tri_n,
                      tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, eps, planes,
                      out_ok, out_t2, out_uv, stats, first, last):
    """Step 4: per seed, the exact path through (t1, t2) to the sample point, t2 found by
    tracing the seed (and re-traced after a Newton step that leaves it).  ``stats`` (chunks,
    3): polish calls, hops, accepted."""
    n = emitter.shape[0]
    for ch in range(first, last):
        stack = np.empty(256, dtype=np.int64)
        geo = np.empty((15, 3))
        work = np.zeros((25, 6))
        th = np.empty(4)
        p1 = np.empty((3, 3))
        n1 = np.empty((3, 3))
        p2 = np.empty((3, 3))
        n2 = np.empty((3, 3))
        xs = np.empty(3)
        xe = np.empty(3)
        for i in range(ch * CHUNK, min(n, ch * CHUNK + CHUNK)):
            out_ok[i] = False
            out_t2[i] = -1
            e = emitter[i]
            t1 = t1_of[e]
            u1 = seed[i, 0]
            v1 = seed[i, 1]
            s = sample[i]
            for a in range(3):
                xs[a] = x0[e, a]
                xe[a] = x_end[s, a]
                for b in range(3):
                    p1[a, b] = tri_p[t1, a, b]
                    n1[a, b] = tri_n[t1, a, b]
            eta = tri_ior[t1]
            last = -1
            for hop in range(HOPS + 1):
                t2, u2, v2, _tr, _ur, _vr, _f = _trace_one(xs[0], xs[1], xs[2], t1, u1, v1, 2, refract1, refract2, second_ok,
                                                          tri_rec, tri_p, tri_n, tri_ior, tri_role, node_min, node_max,
                                                          node_child, node_start, node_count, order, v0, e1, e2, eps, planes,
                                                          stack)
                if t2 < 0 or t2 == last:
                    break
                if hop > 0:
                    stats[ch, 1] += 1
                last = t2
                for a in range(3):
                    for b in range(3):
                        p2[a, b] = tri_p[t2, a, b]
                        n2[a, b] = tri_n[t2, a, b]
                if not pack_geometry(xs, xe, p1, n1, p2, n2, geo):
                    break
                th[0] = u1
                th[1] = v1
                th[2] = u2
                th[3] = v2
                stats[ch, 0] += 1
                acc, err, sig = polish_and_validate2(th, geo, refract1, refract2, eta, POLISH_STEPS, ACCEPT_RESIDUAL, work)
                if acc:
                    out_ok[i] = True
                    out_t2[i] = t2
                    for a in range(4):
                        out_uv[i, a] = th[a]
                    stats[ch, 2] += 1
                    break
                # Left triangle 2 (or failed): re-trace from where Newton went, if still on t1.
                if not (th[0] >= -INSIDE_HOP and th[1] >= -INSIDE_HOP and th[0] + th[1] <= 1.0 + INSIDE_HOP
                        and np.isfinite(th[0]) and np.isfinite(th[1])):
                    break
                u1 = min(max(th[0], 0.0), 1.0)
                v1 = min(max(th[1], 0.0), 1.0 - u1)


def dedupe_paths(sample, t1, t2, uv, tolerance=1e-7):
    """Indices of the distinct paths among (sample, t1, t2, uv) rows: rows of one (sample, t1,
    t2) whose (u1, v1, u2, v2) agree within ``tolerance`` are one path (several seeds of
    overlapping images converge to it); the first of each is kept, in a stable order."""
    n = sample.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((uv[:, 1], uv[:, 0], t2, t1, sample))
    keep = np.ones(n, dtype=bool)
    _dedupe_sorted(order, sample, t1, t2, uv, tolerance, keep)
    return np.sort(order[keep])


@kernel
def _dedupe_sorted(order, sample, t1, t2, uv, tol, keep):
    n = order.shape[0]
    g0 = 0
    for a in range(n):
        i = order[a]
        if a > 0:
            j = order[a - 1]
            if sample[i] != sample[j] or t1[i] != t1[j] or t2[i] != t2[j]:
                g0 = a
        # compare with the kept rows of the same key (few: one per distinct path)
        for b in range(g0, a):
            k = order[b]
            if not keep[b]:
                continue
            if (abs(uv[i, 0] - uv[k, 0]) <= tol and abs(uv[i, 1] - uv[k, 1]) <= tol and abs(uv[i, 2] - uv[k, 2]) <= tol
                    and abs(uv[i, 3] - uv[k, 3]) <= tol):
                keep[a] = False
                break
