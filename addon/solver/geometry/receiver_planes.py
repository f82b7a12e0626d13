"""Flat receivers extended beyond their edges: where a lost ray would have met the receiver's plane.

A receiver that is one plane, with one affine UV map and flat shading normals, and whose UV
region is convex (a floor, a pool bottom, a wall: Blender's plane, subdivided or not) has a
straight border in texture space: the edges of its UV region.  The forward-flux refinement
(:mod:`addon.solver.estimators.forward_image`) otherwise locates the border of what lands on a
receiver by bisection inside the caster's sub-triangles, about 30 traced points per cut
sub-triangle, and probes the lost ones; for such a receiver the tracer instead reports a ray
that lands nowhere but crosses the receiver's plane (from the front) outside its UV region as
landed at that *extended* point (:func:`extended_landing`; up to EXTEND_FRACTION (one) of the
region's size beyond it: farther, rays grazing the plane would give images of any size, which
the refinement could not straighten): the point is not on the receiver,
and no ray through it could be (a ray meets a plane once), so the image of a sub-triangle is
continuous across the border, the refinement treats it as landed, and the splat clips it at
the UV region's edges exactly (:mod:`addon.solver.estimators.splat`), which is where the
bisection converged to.  A sub-triangle whose points all lie beyond one edge of the region by
more than its image's deviation and a texel is dropped (:func:`beyond_region`): its image,
within that margin of the straight triangle through its points, misses the region.

Rows of the ``planes`` array (one per eligible receiver of a pass; an empty (0, PLANE_WIDTH)
array turns the extension off):

- 0-2: the unit normal n of the receiver's front (its triangles' e1 x e2), 3: d with n . p = d;
- 4-7 and 8-11: the UV map u = a . p + b, v = a' . p + b' (exact on every vertex);
- 12: a triangle of the receiver (its barycentrics express an extended point, through its
  UVs), 13: the receiver's index, 14: K, the number of region edges, 15: the reach of the
  extension (UV units: EXTEND_FRACTION of the region's size);
- from PLANE_HEAD on, K rows (a, b, c) with (a, b) unit: a u + b v + c >= 0 inside the region.

No bpy here; tests/solver/test_solver_receiver_planes.py.
"""

import numpy as np

from ..runtime.jit import kernel

PLANE_MAX_EDGES = 32  # a receiver's convex UV region with more edges is not extended
PLANE_HEAD = 16
PLANE_WIDTH = PLANE_HEAD + 3 * PLANE_MAX_EDGES
EXTEND_FRACTION = 1.0  # rays are extended onto the plane up to this fraction of the region's size beyond its edges
FLAT_TOLERANCE = 1e-9  # plane distance (x the receiver's size), normals (1 - cos), UVs (UV units), areas (relative)


def no_planes():
    """The ``planes`` argument that extends no receiver."""
    return np.zeros((0, PLANE_WIDTH))


def _convex_hull(points):
    """Counter-clockwise convex hull (Andrew's monotone chain) of 2-D points (n, 2), without
    collinear points.  Points strictly inside the polygon of the extreme points in 8 directions
    (Akl-Toussaint) are no hull vertices and are left out first: a subdivided floor's UVs keep
    only their border."""
    pts = points
    d = np.stack([pts[:, 0], pts[:, 0] + pts[:, 1], pts[:, 1], pts[:, 1] - pts[:, 0]], axis=1)
    ext = pts[np.concatenate([np.argmin(d, axis=0), np.argmax(d, axis=0)])]  # angles 180..315, then 0..135
    inside = np.ones(pts.shape[0], dtype=np.bool_)
    edges = 0
    for i in range(8):
        a, b = ext[i], ext[(i + 1) % 8]
        if np.array_equal(a, b):
            continue
        edges += 1
        inside &= (b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0]) > 0.0
    if edges >= 3:
        pts = pts[~inside]
    pts = np.unique(pts, axis=0)
    if pts.shape[0] < 3:
        return pts

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0.0:
                out.pop()
            out.append(p)
        return out

    lower = half(pts)
    upper = half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def receiver_plane_row(tri_p, tri_n, tri_uv, tri_ids, receiver):
    """The ``planes`` row (PLANE_WIDTH,) of a receiver whose triangles ``tri_ids`` (global
    indices into ``tri_p`` / ``tri_n`` (T, 3, 3); ``tri_uv`` (len(tri_ids), 3, 2) their UVs)
    lie in one plane (within FLAT_TOLERANCE of its size), face one way, have shading normals
    equal to that plane's normal, one affine UV map, and a convex UV region (the triangles'
    UV areas add up to their convex hull's) of at most PLANE_MAX_EDGES edges; None otherwise."""
    tri_ids = np.asarray(tri_ids, dtype=np.int64)
    if tri_ids.size == 0:
        return None
    P = np.asarray(tri_p, dtype=np.float64)[tri_ids]
    N = np.asarray(tri_n, dtype=np.float64)[tri_ids]
    UV = np.asarray(tri_uv, dtype=np.float64)
    g = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    area2 = np.linalg.norm(g, axis=1)
    k = int(np.argmax(area2))  # the best-conditioned triangle defines the plane and the map
    if not area2[k] > 0.0:
        return None
    n = g[k] / area2[k]
    pts = P.reshape(-1, 3)
    size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    d = float(n @ P[k, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        gn = g / area2[:, None]
        nn = N / np.linalg.norm(N, axis=2, keepdims=True)
    if (np.abs(pts @ n - d).max() > FLAT_TOLERANCE * size or not np.all(gn @ n >= 1.0 - FLAT_TOLERANCE)
            or not np.all(nn @ n >= 1.0 - FLAT_TOLERANCE)):
        return None
    # UV map of triangle k: p = p0 + s e1 + t e2 (+ w n) -> uv = uv0 + s (uv1 - uv0) + t (uv2 - uv0)
    e = np.stack([P[k, 1] - P[k, 0], P[k, 2] - P[k, 0], n], axis=1)  # columns e1, e2, n
    inv = np.linalg.inv(e)  # rows: the linear forms giving s, t, w
    duv = np.stack([UV[k, 1] - UV[k, 0], UV[k, 2] - UV[k, 0]], axis=1)  # (2, 2): columns d(uv)/ds, d(uv)/dt
    a = duv @ inv[:2]  # (2, 3)
    b = UV[k, 0] - a @ P[k, 0]
    if np.abs(pts @ a.T + b - UV.reshape(-1, 2)).max() > FLAT_TOLERANCE:
        return None
    hull = _convex_hull(UV.reshape(-1, 2))
    if hull.shape[0] < 3 or hull.shape[0] > PLANE_MAX_EDGES:
        return None
    hx, hy = hull[:, 0], hull[:, 1]
    hull_area = 0.5 * abs(np.sum(hx * np.roll(hy, -1) - np.roll(hx, -1) * hy))
    e1, e2 = UV[:, 1] - UV[:, 0], UV[:, 2] - UV[:, 0]
    uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    if not hull_area > 0.0 or abs(uv_area - hull_area) > FLAT_TOLERANCE * hull_area:
        return None
    row = np.zeros(PLANE_WIDTH)
    row[0:3], row[3] = n, d
    row[4:7], row[7] = a[0], b[0]
    row[8:11], row[11] = a[1], b[1]
    row[12], row[13], row[14] = tri_ids[k], receiver, hull.shape[0]
    row[15] = EXTEND_FRACTION * float((hull.max(axis=0) - hull.min(axis=0)).max())
    for i in range(hull.shape[0]):  # counter-clockwise: the inside is on the left of each edge
        p, q = hull[i], hull[(i + 1) % hull.shape[0]]
        ex, ey = q - p
        ln = np.hypot(ex, ey)
        row[PLANE_HEAD + 3 * i: PLANE_HEAD + 3 * i + 3] = (-ey / ln, ex / ln, (ey * p[0] - ex * p[1]) / ln)
    return row


def receiver_planes(tri_p, tri_n, receivers):
    """The ``planes`` array (P, PLANE_WIDTH) of the eligible receivers among ``receivers``, a
    list of (receiver index, its global triangle ids, their UVs (n, 3, 2))."""
    rows = [receiver_plane_row(tri_p, tri_n, uv, ids, r) for r, ids, uv in receivers]
    rows = [r for r in rows if r is not None]
    return np.array(rows) if rows else no_planes()


@kernel(inline="always")
def region_value(planes, p, u, v):
    """The smallest signed distance (UV units, negative outside) of (u, v) to the edges of
    plane row ``p``'s region."""
    lo = np.inf
    for k in range(int(planes[p, 14])):
        j = PLANE_HEAD + 3 * k
        lo = min(lo, planes[p, j] * u + planes[p, j + 1] * v + planes[p, j + 2])
    return lo


@kernel(inline="always")
def extended_landing(planes, x, y, z, dx, dy, dz, eps):
    """For a ray (x + t d) that lands on no receiver: the plane row whose front it crosses
    nearest (t > eps) outside that receiver's UV region, within the row's reach of it (-1:
    none).  See the module doc."""
    best = -1
    best_t = np.inf
    for p in range(planes.shape[0]):
        den = planes[p, 0] * dx + planes[p, 1] * dy + planes[p, 2] * dz
        if not den < 0.0:  # parallel, or arriving on the back (the bake's front rule)
            continue
        t = (planes[p, 3] - (planes[p, 0] * x + planes[p, 1] * y + planes[p, 2] * z)) / den
        if not (t > eps and t < best_t):
            continue
        hx, hy, hz = x + t * dx, y + t * dy, z + t * dz
        u = planes[p, 4] * hx + planes[p, 5] * hy + planes[p, 6] * hz + planes[p, 7]
        v = planes[p, 8] * hx + planes[p, 9] * hy + planes[p, 10] * hz + planes[p, 11]
        value = region_value(planes, p, u, v)
        if value < 0.0 and value >= -planes[p, 15]:
            best = p
            best_t = t
    return best


@kernel(inline="always")
def beyond_region(planes, receiver, pu, pv, margin):
    """Whether the points (pu[k], pv[k]) (UV) all lie beyond one edge of ``receiver``'s region
    (when it has a plane row) by more than ``margin`` (UV units)."""
    for p in range(planes.shape[0]):
        if int(planes[p, 13]) != receiver:
            continue
        for k in range(int(planes[p, 14])):
            j = PLANE_HEAD + 3 * k
            hi = -np.inf
            for q in range(pu.shape[0]):
                hi = max(hi, planes[p, j] * pu[q] + planes[p, j + 1] * pv[q] + planes[p, j + 2])
            if hi < -margin:
                return True
    return False


def beyond_region_rows(planes, receiver, uv, margin):
    """:func:`beyond_region` for rows: ``receiver`` (m,), ``uv`` (m, k, 2), ``margin`` (m,)."""
    out = np.zeros(receiver.shape[0], dtype=np.bool_)
    for row in planes:
        sel = np.flatnonzero(receiver == int(row[13]))
        if sel.size == 0:
            continue
        for k in range(int(row[14])):
            a, b, c = row[PLANE_HEAD + 3 * k: PLANE_HEAD + 3 * k + 3]
            hi = (a * uv[sel, :, 0] + b * uv[sel, :, 1] + c).max(axis=1)
            out[sel] |= hi < -margin[sel]
    return out


def region_of(planes, receiver):
    """The region edges (K, 3) of ``receiver``'s row in ``planes`` (None: not extended)."""
    for row in planes:
        if int(row[13]) == int(receiver):
            k = int(row[14])
            return row[PLANE_HEAD:PLANE_HEAD + 3 * k].reshape(k, 3).copy()
    return None
