"""The landed part of the forward-image refinement in one kernel, threads over emitters.

:func:`~addon.solver.estimators.forward_image.refine_image_triangles` cuts every emitter's
first triangle into sub-triangles whose images are straight with a near-linear flux density.
Level by level in numpy, almost all of its time on a finely tessellated caster (115k-triangle
water) goes to array bookkeeping around sub-triangles whose 6 points (3 corners, 3 edge
midpoints) all land on one receiver.  :func:`refine_landed` does exactly those decisions per
emitter, depth first, in a kernel:

- a sub-triangle at depth d whose 6 points land on one receiver is final when its image is
  straight to ``tolerance`` texels (the midpoints' deviation from the straight image) and
  its density is linear to ``relative`` (:func:`_density_nonlinearity`: rho = w / |det J| of
  the quadratic element at the 6 points, w the light's flux per barycentric area times the
  transport factor) or its image is within a texel; above depth 0 (the coarse levels) it
  must be linear whatever its size (to ``relative`` x (``coarse_linear_texels`` / its
  length)² when longer than that) and at most ``coarse_texels`` long; at ``max_depth`` it is
  final anyway;
  otherwise it is split in four (children (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca));
- a landed sub-triangle whose 6 points lie beyond one edge of a flat receiver's UV region
  (extended there, :mod:`~addon.solver.geometry.receiver_planes`) by more than twice its
  deviation and a texel is dropped: its image misses the receiver;
- any other sub-triangle (a point lost or on another receiver) is handed back with its
  corners, depth and inherited image scale, and the numpy refinement continues from there
  with the same rules (probes, straight-border cuts, partial hulls).

The decisions are the numpy form's, item by item (tests/bake/test_bake_forward_flux.py,
``test_landed_kernel_refines_as_the_numpy_levels``: the same final sub-triangles per level and
the same texture, in another order).  A point shared by sub-triangles of one emitter (a
corner, an edge midpoint) is traced once through a per-emitter table keyed by its dyadic
coordinates, like :func:`~addon.solver.estimators.forward_image._traced_shared`; tracing is
:func:`~addon.solver.estimators.forward_image._trace_one`, the same arithmetic as
``trace_chain_points``.  The whole triangle's 6 points, shared with the mesh neighbours, are
traced once for all the emitters (:func:`mesh_point_traces`: about 2 points per triangle of
a smooth mesh instead of 6).

Emitters are cut into fixed runs (``EMITTERS_PER_CALL``), each refined by one kernel call on a
worker thread into its own growing record arrays; the runs' records are joined in emitter
order, so the result does not depend on the thread count.
"""

import math
import warnings

import numpy as np

from ..runtime.jit import kernel, run_calls
from ..geometry.receiver_planes import beyond_region
from ..geometry.rows import group_rows
from .forward_image import _trace_one

TABLE_BITS = 13  # per-emitter shared-point table: 8192 slots, filled to half at most (then points are traced unshared)
EMITTERS_PER_CALL = 128  # emitters refined by one kernel call (a unit of work for a thread)
MESH_SHARED = True  # a mesh vertex / edge midpoint shared by emitters' whole triangles is traced once (False: per emitter)
# a child's corners as the parent's points (0-2 its corners, 3-5 its edge midpoints 01, 12, 20)
CHILD_CORNERS = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]], dtype=np.int64)
# record layouts (float64 rows): a final sub-triangle, and one handed back to the numpy refinement
F_EMITTER, F_RECEIVER, F_DEPTH, F_DEV, F_BARY, F_UV, F_MID_UV, F_FACTOR, F_WIDTH = 0, 1, 2, 3, 4, 10, 16, 22, 28
H_EMITTER, H_DEPTH, H_INHERITED, H_BARY, H_REC, H_UV, H_FAC, H_WIDTH = 0, 1, 2, 3, 9, 15, 27, 33  # REC, UV, FAC: 6 points


@kernel(inline="always")
def _trace_uv(e, u, v, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role,
              node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, eps, planes, stack):
    """(receiver triangle or -1, landing u, v (NaN when lost), transport factor) of the
    point (u, v) of emitter e: trace_chain_points for one point."""
    _t2, _u2, _v2, tr, ur, vr, fac = _trace_one(x0[e, 0], x0[e, 1], x0[e, 2], t1_of[e], u, v, bounces, refract1, refract2,
                                                second_ok, tri_rec, tri_p, tri_n, tri_ior, tri_role, node_min, node_max,
                                                node_child, node_start, node_count, order, v0, e1, e2, eps, planes, stack)
    if tr >= 0:
        lu = tri_uv[tr, 0, 0] + ur * (tri_uv[tr, 1, 0] - tri_uv[tr, 0, 0]) + vr * (tri_uv[tr, 2, 0] - tri_uv[tr, 0, 0])
        lv = tri_uv[tr, 0, 1] + ur * (tri_uv[tr, 1, 1] - tri_uv[tr, 0, 1]) + vr * (tri_uv[tr, 2, 1] - tri_uv[tr, 0, 1])
        return tr, lu, lv, fac
    return tr, np.nan, np.nan, fac


@kernel(inline="always")
def _light_weight(parallel, x0, tri_p, t, e, u, v):
    """The light's flux per barycentric area of first triangle t at (u, v), up to a constant
    (:func:`~addon.solver.estimators.forward_image.light_area_density`): 1 for parallel light,
    else |n . (p - x0)| / |p - x0|³, n the cross product of the triangle's edges."""
    if parallel:
        return 1.0
    ax, ay, az = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
    bx, by, bz = tri_p[t, 1, 0] - ax, tri_p[t, 1, 1] - ay, tri_p[t, 1, 2] - az
    cx, cy, cz = tri_p[t, 2, 0] - ax, tri_p[t, 2, 1] - ay, tri_p[t, 2, 2] - az
    nx, ny, nz = by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx
    dx = ax + u * bx + v * cx - x0[e, 0]
    dy = ay + u * by + v * cy - x0[e, 1]
    dz = az + u * bz + v * cz - x0[e, 2]
    ln = math.sqrt(dx * dx + dy * dy + dz * dz)
    return abs(nx * dx + ny * dy + nz * dz) / (ln * ln * ln)


@kernel(inline="always")
def _det(dsx, dsy, dtx, dty):
    return dsx * dty - dsy * dtx


@kernel
def _density_nonlinearity(pu, pv, w):
    """:func:`~addon.solver.estimators.forward_image.density_nonlinearity` of one sub-triangle:
    ``pu``, ``pv`` (6,) the images of its corners 0, 1, 2 and edge midpoints 01, 12, 20, ``w``
    (6,) the flux per barycentric area there; inf where det J changes sign or is not finite."""
    c0u, c1u, c2u, m01u, m12u, m20u = pu[0], pu[1], pu[2], pu[3], pu[4], pu[5]
    c0v, c1v, c2v, m01v, m12v, m20v = pv[0], pv[1], pv[2], pv[3], pv[4], pv[5]
    # d/ds and d/dt of the 6-node quadratic element at the corners, then the midpoints
    ds_u = (-3 * c0u - c1u + 4 * m01u, c0u + 3 * c1u - 4 * m01u, c0u - c1u + 4 * m12u - 4 * m20u,
            c1u - c0u, c0u + c1u - 2 * m01u + 2 * m12u - 2 * m20u, -c0u - c1u + 2 * m01u + 2 * m12u - 2 * m20u)
    ds_v = (-3 * c0v - c1v + 4 * m01v, c0v + 3 * c1v - 4 * m01v, c0v - c1v + 4 * m12v - 4 * m20v,
            c1v - c0v, c0v + c1v - 2 * m01v + 2 * m12v - 2 * m20v, -c0v - c1v + 2 * m01v + 2 * m12v - 2 * m20v)
    dt_u = (-3 * c0u - c2u + 4 * m20u, c0u - c2u - 4 * m01u + 4 * m12u, c0u + 3 * c2u - 4 * m20u,
            -c0u - c2u - 2 * m01u + 2 * m12u + 2 * m20u, c0u + c2u - 2 * m01u + 2 * m12u - 2 * m20u, c2u - c0u)
    dt_v = (-3 * c0v - c2v + 4 * m20v, c0v - c2v - 4 * m01v + 4 * m12v, c0v + 3 * c2v - 4 * m20v,
            -c0v - c2v - 2 * m01v + 2 * m12v + 2 * m20v, c0v + c2v - 2 * m01v + 2 * m12v - 2 * m20v, c2v - c0v)
    pos = 0
    neg = 0
    rho = np.empty(6)
    for k in range(6):
        d = _det(ds_u[k], ds_v[k], dt_u[k], dt_v[k])
        pos += d > 0.0
        neg += d < 0.0
        rho[k] = abs(w[k]) / abs(d)
    if pos != 6 and neg != 6:
        return np.inf  # a fold inside (or a degenerate corner)
    mean = (rho[0] + rho[1] + rho[2]) / 3.0
    worst = 0.0
    for k in range(3):
        lin = 0.5 * (rho[k] + rho[(k + 1) % 3])
        worst = max(worst, abs(rho[3 + k] - lin))
    out = worst / mean
    if not math.isfinite(out) or math.isnan(worst):
        return np.inf
    return out


@kernel(inline="always")
def _table_slot(t_key, key, mask):
    """The slot of ``key`` in the open-addressing table, or the empty slot where it goes."""
    slot = (key * 40503) & mask
    while t_key[slot] != -1 and t_key[slot] != key:
        slot = (slot + 1) & mask
    return slot


@kernel(inline="always")
def _grown(rows, n, width):
    """``rows`` with room for at least one more row after its first n (doubled when full)."""
    if n < rows.shape[0]:
        return rows
    out = np.empty((2 * rows.shape[0], width))
    out[:n] = rows[:n]
    return out


@kernel(error_model="numpy")
def refine_emitters(e_first, e_last, base, depth0, dyadic, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec,
                    tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count, order,
                    v0, e1, e2, eps, planes, receiver_of_tri, texel_size, tolerance, relative, coarse_texels, coarse_linear_texels,
                    max_depth, density, parallel, top_rec, top_uv, top_fac):
    """The landed part of the refinement (see the module doc) of emitters [e_first, e_last)
    from the start grid ``base`` (k, 3, 2) at depth ``depth0``, points on the 1 / ``dyadic``
    grid.  Returns (final records (nf, F_WIDTH), handed-back records (nh, H_WIDTH), points
    traced).  ``density``: test the flux density's linearity (``relative`` applies to the
    midpoint shift alone when False); ``parallel``: the light is parallel (a uniform flux per
    area of the first triangle).  ``top_rec`` / ``top_uv`` / ``top_fac`` (n, 6[, 2]): when ``base``
    is the whole triangle and they have a row per emitter, its 6 points' traces (corners, edge
    midpoints; :func:`mesh_point_traces`), used instead of tracing them."""
    has_top = base.shape[0] == 1 and top_rec.shape[0] == t1_of.shape[0]
    bvh_stack = np.empty(256, dtype=np.int64)
    size = 1 << TABLE_BITS
    mask = size - 1
    t_key = np.full(size, -1, dtype=np.int64)
    t_rec = np.empty(size, dtype=np.int64)
    t_u = np.empty(size)
    t_v = np.empty(size)
    t_fac = np.empty(size)
    used = np.empty(size // 2, dtype=np.int64)
    depth_room = max(0, max_depth - depth0) + 1
    n_stack = base.shape[0] + 3 * depth_room + 4
    s_bary = np.empty((n_stack, 3, 2))
    s_rec = np.empty((n_stack, 3), dtype=np.int64)
    s_uv = np.empty((n_stack, 3, 2))
    s_fac = np.empty((n_stack, 3))
    s_depth = np.empty(n_stack, dtype=np.int64)
    s_inh = np.empty(n_stack)
    p_bary = np.empty((6, 2))  # the current sub-triangle's 6 points: corners, then edge midpoints 01, 12, 20
    p_rec = np.empty(6, dtype=np.int64)
    p_uv = np.empty((6, 2))
    p_fac = np.empty(6)
    pu = np.empty(6)
    pv = np.empty(6)
    w6 = np.empty(6)
    robj = np.empty(6, dtype=np.int64)
    finals = np.empty((max(64, 8 * (e_last - e_first)), F_WIDTH))
    hands = np.empty((16, H_WIDTH))
    nf = 0
    nh = 0
    traced = 0
    s1 = dyadic + 1
    for e in range(e_first, e_last):
        n_used = 0
        t1 = t1_of[e]
        top = 0
        for k in range(base.shape[0] - 1, -1, -1):  # the start grid, first triangle on top
            for c in range(3):
                s_bary[top, c, 0] = base[k, c, 0]
                s_bary[top, c, 1] = base[k, c, 1]
            s_depth[top] = depth0
            s_inh[top] = np.inf
            top += 1
        while top > 0:
            top -= 1
            depth = s_depth[top]
            inherited = np.inf if depth == 0 else s_inh[top]
            for c in range(3):
                p_bary[c, 0] = s_bary[top, c, 0]
                p_bary[c, 1] = s_bary[top, c, 1]
                c2 = (c + 1) % 3
                p_bary[3 + c, 0] = 0.5 * (s_bary[top, c, 0] + s_bary[top, c2, 0])
                p_bary[3 + c, 1] = 0.5 * (s_bary[top, c, 1] + s_bary[top, c2, 1])
            # the start grid's corners are traced here (table-shared); a child's come from its parent
            k0 = 0 if depth == depth0 else 3
            for k in range(3):
                if k0 == 3:
                    p_rec[k], p_uv[k, 0], p_uv[k, 1], p_fac[k] = s_rec[top, k], s_uv[top, k, 0], s_uv[top, k, 1], s_fac[top, k]
            if k0 == 0 and has_top:  # the whole triangle: its points traced once for the mesh
                for k in range(6):
                    p_rec[k], p_uv[k, 0], p_uv[k, 1], p_fac[k] = top_rec[e, k], top_uv[e, k, 0], top_uv[e, k, 1], top_fac[e, k]
                k0 = 6
            for k in range(k0, 6):
                u = p_bary[k, 0]
                v = p_bary[k, 1]
                key = int(np.rint(u * dyadic)) * s1 + int(np.rint(v * dyadic))
                slot = _table_slot(t_key, key, mask)
                if t_key[slot] == key:
                    p_rec[k], p_uv[k, 0], p_uv[k, 1], p_fac[k] = t_rec[slot], t_u[slot], t_v[slot], t_fac[slot]
                    continue
                r, lu, lv, fac = _trace_uv(e, u, v, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p,
                                           tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count,
                                           order, v0, e1, e2, eps, planes, bvh_stack)
                traced += 1
                p_rec[k], p_uv[k, 0], p_uv[k, 1], p_fac[k] = r, lu, lv, fac
                if n_used < size // 2:
                    t_key[slot], t_rec[slot], t_u[slot], t_v[slot], t_fac[slot] = key, r, lu, lv, fac
                    used[n_used] = slot
                    n_used += 1
            for k in range(6):
                robj[k] = receiver_of_tri[p_rec[k]] if p_rec[k] >= 0 else -1
            landed = robj[0] >= 0
            for k in range(1, 6):
                landed = landed and robj[k] == robj[0]
            if not landed:  # the numpy refinement goes on from here
                hands = _grown(hands, nh, H_WIDTH)
                row = hands[nh]
                row[H_EMITTER] = e
                row[H_DEPTH] = depth
                row[H_INHERITED] = inherited
                for c in range(3):
                    row[H_BARY + 2 * c] = p_bary[c, 0]
                    row[H_BARY + 2 * c + 1] = p_bary[c, 1]
                for k in range(6):  # corners, then edge midpoints (traced: the numpy levels need not again)
                    row[H_REC + k] = p_rec[k]
                    row[H_UV + 2 * k] = p_uv[k, 0]
                    row[H_UV + 2 * k + 1] = p_uv[k, 1]
                    row[H_FAC + k] = p_fac[k]
                nh += 1
                continue
            dev = 0.0
            edge = 0.0
            for c in range(3):
                c2 = (c + 1) % 3
                for a in range(2):
                    dev = max(dev, abs(p_uv[3 + c, a] - 0.5 * (p_uv[c, a] + p_uv[c2, a])))
                    edge = max(edge, abs(p_uv[c, a] - p_uv[c2, a]))
            tex = texel_size[robj[0]]
            if planes.shape[0]:  # beyond an edge of a flat receiver's region: lands nowhere (receiver_planes)
                for k in range(6):
                    pu[k] = p_uv[k, 0]
                    pv[k] = p_uv[k, 1]
                if beyond_region(planes, robj[0], pu, pv, 2.0 * dev + tex):
                    continue
            rel = relative
            if depth < 0:
                rel = relative * min(1.0, (coarse_linear_texels * tex / max(edge, 1e-300)) ** 2)
            linear = dev <= rel * edge
            if linear and density:
                for k in range(6):
                    pu[k] = p_uv[k, 0]
                    pv[k] = p_uv[k, 1]
                    w6[k] = _light_weight(parallel, x0, tri_p, t1, e, p_bary[k, 0], p_bary[k, 1]) * p_fac[k]
                linear = _density_nonlinearity(pu, pv, w6) <= rel
            if depth < 0:
                final = dev <= tolerance * tex and linear and edge <= coarse_texels * tex
            else:
                final = dev <= tolerance * tex and (linear or edge <= tex)
            if final or depth >= max_depth:
                finals = _grown(finals, nf, F_WIDTH)
                row = finals[nf]
                row[F_EMITTER] = e
                row[F_RECEIVER] = robj[0]
                row[F_DEPTH] = depth
                row[F_DEV] = dev
                for c in range(3):
                    row[F_BARY + 2 * c] = p_bary[c, 0]
                    row[F_BARY + 2 * c + 1] = p_bary[c, 1]
                    row[F_UV + 2 * c] = p_uv[c, 0]
                    row[F_UV + 2 * c + 1] = p_uv[c, 1]
                    row[F_MID_UV + 2 * c] = p_uv[3 + c, 0]
                    row[F_MID_UV + 2 * c + 1] = p_uv[3 + c, 1]
                    row[F_FACTOR + c] = p_fac[c]
                    row[F_FACTOR + 3 + c] = p_fac[3 + c]
                nf += 1
                continue
            # split in four; child 0 ends on top of the stack (popped first), child 3 takes the
            # parent's row (its corners are all midpoints, held in p_*)
            scale = 0.5 * edge / tex
            for child in range(4):
                dst = top + 3 - child
                for c in range(3):
                    p = CHILD_CORNERS[child, c]
                    s_bary[dst, c, 0] = p_bary[p, 0]
                    s_bary[dst, c, 1] = p_bary[p, 1]
                    s_rec[dst, c] = p_rec[p]
                    s_uv[dst, c, 0] = p_uv[p, 0]
                    s_uv[dst, c, 1] = p_uv[p, 1]
                    s_fac[dst, c] = p_fac[p]
                s_depth[dst] = depth + 1
                s_inh[dst] = scale
            top += 4
        for k in range(n_used):
            t_key[used[k]] = -1
    return finals[:nf], hands[:nh], traced


def refine_landed(n_emitters, base, depth0, dyadic, trace_args, receiver_of_tri, texel_size, tolerance, relative,
                  coarse_texels, coarse_linear_texels, max_depth, density, parallel, mesh_points=None, device=None):
    """:func:`refine_emitters` over emitters [0, ``n_emitters``) in runs of
    ``EMITTERS_PER_CALL`` on the solver's threads, joined in emitter order.  ``trace_args``:
    the arguments of ``trace_chain_points`` from ``x0`` to ``planes`` (x0, t1_of, bounces,
    refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, the BVH's
    9 arrays, eps, planes).  Returns dict: the final sub-triangles' emitter, receiver, depth,
    deviation, bary, uv, mid_uv (m, 3, 2) and factor (m, 6); the handed-back ones' emitter,
    depth, inherited image scale, bary, and rec (scene triangle, -1 lost), uv, fac of its 6
    points (corners, then edge midpoints 01, 12, 20); and the points traced.  When ``base`` is
    the whole triangle its 6 points are ``mesh_points`` (:func:`mesh_point_traces` of these
    emitters, traced by the caller) or, with ``MESH_SHARED``, traced here that way.  ``device``: an
    OpenCL tracer of this scene and these emitters (``opencl.tracing.OpenCLPointTracer``) refines
    them on its device instead (refine.cl: the same records in the same order; only the count of
    traced points differs, its shared-point table being smaller)."""
    runs = [(a, min(int(n_emitters), a + EMITTERS_PER_CALL)) for a in range(0, int(n_emitters), EMITTERS_PER_CALL)]
    base = np.ascontiguousarray(base, dtype=np.float64)
    top, top_traced = (np.zeros((0, 6), dtype=np.int64), np.zeros((0, 6, 2)), np.zeros((0, 6))), 0
    whole = base.shape[0] == 1 and np.array_equal(base[0], CORNER_BARY)
    if whole and mesh_points is not None:
        top = tuple(mesh_points)  # traced by the caller (counted there)
    elif whole and MESH_SHARED:
        top, top_traced = mesh_point_traces(int(n_emitters), trace_args,
                                            trace=device.trace_points if device is not None else None)
    if device is not None:
        from ..opencl.backend import OpenCLUnavailable

        try:
            f, h, traced = device.refine_emitters(int(n_emitters), base, int(depth0), int(dyadic), receiver_of_tri,
                                                  texel_size, tolerance, relative, coarse_texels, coarse_linear_texels,
                                                  int(max_depth), bool(density), bool(parallel), top)
        except OpenCLUnavailable as ex:  # a program the driver rejects, no room: the same records on Numba
            warnings.warn(f"OpenCL unavailable ({ex}); refining on Numba instead", RuntimeWarning, stacklevel=2)
            device.refined_here = False  # for the bake's report
            device = None
    if device is None:
        fixed = (base, int(depth0), int(dyadic)) + tuple(trace_args) + (
            np.ascontiguousarray(receiver_of_tri, dtype=np.int64), np.ascontiguousarray(texel_size, dtype=np.float64),
            float(tolerance), float(relative), float(coarse_texels), float(coarse_linear_texels), int(max_depth),
            bool(density), bool(parallel)) + top
        results = run_calls(lambda r: refine_emitters(r[0], r[1], *fixed), runs)
        f = np.concatenate([r[0] for r in results]) if results else np.zeros((0, F_WIDTH))
        h = np.concatenate([r[1] for r in results]) if results else np.zeros((0, H_WIDTH))
        traced = int(sum(r[2] for r in results))
    return dict(emitter=f[:, F_EMITTER].astype(np.int64), receiver=f[:, F_RECEIVER].astype(np.int64),
                depth=f[:, F_DEPTH].astype(np.int64), deviation=f[:, F_DEV].copy(),
                bary=f[:, F_BARY:F_UV].reshape(-1, 3, 2).copy(), uv=f[:, F_UV:F_MID_UV].reshape(-1, 3, 2).copy(),
                mid_uv=f[:, F_MID_UV:F_FACTOR].reshape(-1, 3, 2).copy(), factor=f[:, F_FACTOR:F_WIDTH].copy(),
                hand_emitter=h[:, H_EMITTER].astype(np.int64), hand_depth=h[:, H_DEPTH].astype(np.int64),
                hand_inherited=h[:, H_INHERITED].copy(), hand_bary=h[:, H_BARY:H_REC].reshape(-1, 3, 2).copy(),
                hand_rec=h[:, H_REC:H_UV].astype(np.int64), hand_uv=h[:, H_UV:H_FAC].reshape(-1, 6, 2).copy(),
                hand_fac=h[:, H_FAC:H_WIDTH].copy(), traced=top_traced + traced)


CORNER_BARY = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def mesh_point_traces(n_emitters, trace_args, trace=None):
    """The traces (rec (n, 6), uv (n, 6, 2), fac (n, 6)) of every emitter's whole first triangle
    at its 3 corners and 3 edge midpoints (01, 12, 20), each mesh point traced once
    (:func:`mesh_points`); ``trace(e, u, v) -> (t2, rec, uv, fac)`` traces them instead of
    ``trace_chain_points`` (a device's tracer: the same points).  Returns ((rec, uv, fac),
    points traced)."""
    from .forward_image import trace_chain_points

    e, u, v, index = mesh_points(n_emitters, trace_args)
    m = e.size
    out = (np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64), np.empty((m, 2)), np.empty(m))
    if m and trace is not None:
        out = trace(e, u, v)
    elif m:
        trace_chain_points(e, u, v, *trace_args, *out)
    return gather_mesh_points(out, index), m


def mesh_points(n_emitters, trace_args):
    """The points of the emitters' whole first triangles, each mesh point once: corners are
    the same point when their position, shading normal, light point, IOR and role are equal
    (an emitter's neighbours in a smooth mesh under one light), edge midpoints when both ends
    are; a point is traced as its first emitter's (``trace_chain_points``), which for the
    others differs from their own only by rounding in the barycentric interpolation.
    Returns (emitter (m,), u (m,), v (m,), index (n, 6) of each emitter's corners and edge
    midpoints 01, 12, 20 into the m points)."""
    x0, t1_of = trace_args[0], trace_args[1]
    tri_p, tri_n, tri_ior, tri_role = trace_args[8], trace_args[9], trace_args[10], trace_args[11]
    n = int(n_emitters)
    t = t1_of[:n]
    # the light point, IOR and role join the key only where they vary (one point light over
    # one material: they do not, and equal columns decide nothing)
    extra = [c for c in (np.ascontiguousarray(x0[:n], dtype=np.float64), tri_ior[t][:, None].astype(np.float64),
                         tri_role[t][:, None].astype(np.float64))
             if n and not np.array_equal(c.view(np.uint64), np.broadcast_to(c[:1].view(np.uint64), c.shape))]
    width = 6 + sum(c.shape[1] for c in extra)
    rows = np.empty((n, 3, width))
    rows[:, :, 0:3] = tri_p[t]
    rows[:, :, 3:6] = tri_n[t]
    k = 6
    for c in extra:
        rows[:, :, k:k + c.shape[1]] = c[:, None, :]
        k += c.shape[1]
    vid, vfirst = group_rows(rows.reshape(n * 3, width).view(np.uint64))
    vid = vid.reshape(n, 3)
    a, b = vid, vid[:, [1, 2, 0]]
    nv = np.int64(vfirst.size)
    ekey = (np.minimum(a, b) * nv + np.maximum(a, b)).reshape(-1, 1)
    eid, efirst = group_rows(ekey.view(np.uint64))
    # representatives: (emitter, u, v) of each vertex's and edge midpoint's first occurrence
    ve, vk = vfirst // 3, vfirst % 3
    ee, ek = efirst // 3, efirst % 3
    mid = 0.5 * (CORNER_BARY + CORNER_BARY[[1, 2, 0]])
    e = np.concatenate([ve, ee]).astype(np.int64)
    uv = np.concatenate([CORNER_BARY[vk], mid[ek]])
    index = np.concatenate([vid, vfirst.size + eid.reshape(n, 3)], axis=1)  # (n, 6): corners, then edges 01, 12, 20
    return e, np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1]), index


def gather_mesh_points(traces, index):
    """Per emitter (rec (n, 6), uv (n, 6, 2), fac (n, 6)) from the traces (t2, rec, uv, fac) of
    :func:`mesh_points`' points and its ``index``."""
    _t2, rec, luv, fac = traces
    return np.ascontiguousarray(rec[index]), np.ascontiguousarray(luv[index]), np.ascontiguousarray(fac[index])
