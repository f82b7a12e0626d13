"""Bounding-volume hierarchy over triangles, for shadow rays (visibility of path segments).

``build_bvh(tri_p)`` builds a binary BVH (binned surface-area heuristic on triangle
centroids, leaves of at most ``LEAF_SIZE`` triangles) in Numba; ``segments_occluded`` answers
any-hit queries for a batch of segments a -> b in parallel.

Closest hits (``ray_closest``) take the smallest t and, at equal t (a ray through an edge two
triangles share), the smallest triangle id: the answer does not depend on the tree's shape, so
a tree refitted to moved triangles (:func:`refit_bvh`) answers as a fresh build of them.

Robustness: a segment is tested on t in [eps / L, 1 - eps / L] (L its length, eps an absolute
offset, typically 1e-6 of the scene size), and up to two triangle ids per segment are ignored
(the specular vertex's own triangle, the receiver triangle), so a segment never hits the
surfaces it starts or ends on.  The triangle test is Möller–Trumbore in float64 with
inclusive edges, so a ray through a shared edge of two occluders is blocked (no leaks).
"""

from collections import namedtuple

import numpy as np

from ..runtime.jit import kernel, parallel_range

LEAF_SIZE = 8  # triangles per leaf at most (a fine caster mesh: fewer node tests per ray than with smaller leaves)
N_BINS = 16

BVH = namedtuple("BVH", "node_min node_max node_child node_start node_count order v0 e1 e2")
"""Flattened BVH.  Node k: box [node_min[k], node_max[k]]; inner nodes have children
node_child[k] and node_child[k] + 1 (node_count[k] == 0); leaves hold triangles
order[node_start[k] : node_start[k] + node_count[k]] (original ids), whose geometry is
v0/e1/e2[node_start[k] : ...] (stored in leaf order)."""


@kernel
def _build(cmin, cmax, cent, order, node_min, node_max, node_child, node_start, node_count):
    n = order.shape[0]
    stack = np.empty((128, 3), dtype=np.int64)  # node, start, count
    sp = 0
    n_nodes = 1
    stack[0, 0] = 0
    stack[0, 1] = 0
    stack[0, 2] = n
    sp = 1
    bin_cnt = np.zeros(N_BINS, dtype=np.int64)
    bin_min = np.empty((N_BINS, 3))
    bin_max = np.empty((N_BINS, 3))
    left_area = np.empty(N_BINS)
    left_cnt = np.empty(N_BINS, dtype=np.int64)
    while sp > 0:
        sp -= 1
        node = stack[sp, 0]
        start = stack[sp, 1]
        count = stack[sp, 2]
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        clo = np.full(3, np.inf)
        chi = np.full(3, -np.inf)
        for q in range(start, start + count):
            t = order[q]
            for a in range(3):
                lo[a] = min(lo[a], cmin[t, a])
                hi[a] = max(hi[a], cmax[t, a])
                clo[a] = min(clo[a], cent[t, a])
                chi[a] = max(chi[a], cent[t, a])
        for a in range(3):
            node_min[node, a] = lo[a]
            node_max[node, a] = hi[a]
        axis = 0
        ext = chi[0] - clo[0]
        for a in range(1, 3):
            if chi[a] - clo[a] > ext:
                ext = chi[a] - clo[a]
                axis = a
        if count <= LEAF_SIZE or not ext > 0.0 or sp >= 126:
            node_child[node] = -1
            node_start[node] = start
            node_count[node] = count
            continue
        # Binned SAH along the widest centroid axis.
        for b in range(N_BINS):
            bin_cnt[b] = 0
            for a in range(3):
                bin_min[b, a] = np.inf
                bin_max[b, a] = -np.inf
        scale = N_BINS / ext
        for q in range(start, start + count):
            t = order[q]
            b = min(N_BINS - 1, int((cent[t, axis] - clo[axis]) * scale))
            bin_cnt[b] += 1
            for a in range(3):
                bin_min[b, a] = min(bin_min[b, a], cmin[t, a])
                bin_max[b, a] = max(bin_max[b, a], cmax[t, a])
        blo = np.full(3, np.inf)
        bhi = np.full(3, -np.inf)
        c = 0
        for b in range(N_BINS - 1):
            c += bin_cnt[b]
            for a in range(3):
                blo[a] = min(blo[a], bin_min[b, a])
                bhi[a] = max(bhi[a], bin_max[b, a])
            dx = max(0.0, bhi[0] - blo[0])
            dy = max(0.0, bhi[1] - blo[1])
            dz = max(0.0, bhi[2] - blo[2])
            left_area[b] = dx * dy + dy * dz + dz * dx
            left_cnt[b] = c
        best = -1
        best_cost = np.inf
        blo[:] = np.inf
        bhi[:] = -np.inf
        c = 0
        for b in range(N_BINS - 1, 0, -1):
            c += bin_cnt[b]
            for a in range(3):
                blo[a] = min(blo[a], bin_min[b, a])
                bhi[a] = max(bhi[a], bin_max[b, a])
            dx = max(0.0, bhi[0] - blo[0])
            dy = max(0.0, bhi[1] - blo[1])
            dz = max(0.0, bhi[2] - blo[2])
            if left_cnt[b - 1] == 0 or c == 0:
                continue
            cost = left_area[b - 1] * left_cnt[b - 1] + (dx * dy + dy * dz + dz * dx) * c
            if cost < best_cost:
                best_cost = cost
                best = b
        mid = start
        if best > 0:
            # Partition: bins < best to the left (stable order inside each side).
            tmp = np.empty(count, dtype=np.int64)
            m = 0
            for q in range(start, start + count):
                t = order[q]
                if min(N_BINS - 1, int((cent[t, axis] - clo[axis]) * scale)) < best:
                    tmp[m] = t
                    m += 1
            mid = start + m
            for q in range(start, start + count):
                t = order[q]
                if min(N_BINS - 1, int((cent[t, axis] - clo[axis]) * scale)) >= best:
                    tmp[m] = t
                    m += 1
            for q in range(count):
                order[start + q] = tmp[q]
        if mid == start or mid == start + count:
            # Degenerate split: object median along the axis.
            seg = order[start:start + count].copy()
            keys = np.empty(count)
            for q in range(count):
                keys[q] = cent[seg[q], axis]
            idx = np.argsort(keys, kind="mergesort")
            for q in range(count):
                order[start + q] = seg[idx[q]]
            mid = start + count // 2
        left = n_nodes
        n_nodes += 2
        node_child[node] = left
        node_count[node] = 0
        node_start[node] = 0
        stack[sp, 0] = left
        stack[sp, 1] = start
        stack[sp, 2] = mid - start
        sp += 1
        stack[sp, 0] = left + 1
        stack[sp, 1] = mid
        stack[sp, 2] = start + count - mid
        sp += 1
    return n_nodes


def build_bvh(tri_p):
    """BVH over triangles ``tri_p`` (n,3,3); degenerate triangles are kept (they never hit)."""
    tri_p = np.ascontiguousarray(tri_p, dtype=np.float64).reshape(-1, 3, 3)
    n = tri_p.shape[0]
    cmin = tri_p.min(axis=1)
    cmax = tri_p.max(axis=1)
    cent = tri_p.mean(axis=1)
    order = np.arange(n, dtype=np.int64)
    cap = max(1, 2 * n)
    node_min = np.zeros((cap, 3))
    node_max = np.zeros((cap, 3))
    node_child = np.full(cap, -1, dtype=np.int64)
    node_start = np.zeros(cap, dtype=np.int64)
    node_count = np.zeros(cap, dtype=np.int64)
    if n:
        m = _build(cmin, cmax, np.ascontiguousarray(cent), order, node_min, node_max, node_child, node_start, node_count)
    else:
        m = 1
        node_min[0] = np.inf
        node_max[0] = -np.inf
    p = tri_p[order]
    return BVH(node_min[:m].copy(), node_max[:m].copy(), node_child[:m].copy(), node_start[:m].copy(), node_count[:m].copy(),
               order, np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1] - p[:, 0]), np.ascontiguousarray(p[:, 2] - p[:, 0]))


@kernel
def _refit(tri_p, order, node_min, node_max, node_child, node_start, node_count):
    """Boxes of every node for the triangles ``tri_p``, the tree's shape kept: leaves around
    their triangles, inner nodes around their children (children are numbered after their
    parent, so a reverse sweep meets them first)."""
    for k in range(node_min.shape[0] - 1, -1, -1):
        c = node_child[k]
        for a in range(3):
            lo = np.inf
            hi = -np.inf
            if c < 0:
                for q in range(node_start[k], node_start[k] + node_count[k]):
                    t = order[q]
                    for j in range(3):
                        lo = min(lo, tri_p[t, j, a])
                        hi = max(hi, tri_p[t, j, a])
            else:
                lo = min(node_min[c, a], node_min[c + 1, a])
                hi = max(node_max[c, a], node_max[c + 1, a])
            node_min[k, a] = lo
            node_max[k, a] = hi


def refit_bvh(bvh, tri_p):
    """The BVH of ``bvh``'s shape (nodes, leaves, triangle order) around the triangles
    ``tri_p`` (the same triangles moved: as many, in the same order), in O(nodes) instead of a
    build.  Queries give the same answers as on ``build_bvh(tri_p)`` (see the module doc); only
    their speed depends on how far the triangles moved from the ones the shape was built for."""
    tri_p = np.ascontiguousarray(tri_p, dtype=np.float64).reshape(-1, 3, 3)
    if tri_p.shape[0] != bvh.order.shape[0]:
        raise ValueError(f"refit_bvh: {tri_p.shape[0]} triangles for a tree of {bvh.order.shape[0]}")
    node_min = np.empty_like(bvh.node_min)
    node_max = np.empty_like(bvh.node_max)
    if tri_p.shape[0]:
        _refit(tri_p, bvh.order, node_min, node_max, bvh.node_child, bvh.node_start, bvh.node_count)
    else:
        node_min[:] = np.inf
        node_max[:] = -np.inf
    p = tri_p[bvh.order]
    return BVH(node_min, node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order, np.ascontiguousarray(p[:, 0]),
               np.ascontiguousarray(p[:, 1] - p[:, 0]), np.ascontiguousarray(p[:, 2] - p[:, 0]))


def box_area(bvh):
    """The summed surface area of the tree's node boxes (its SAH traversal cost up to a
    constant): how much a refitted tree lost against its build."""
    d = np.maximum(bvh.node_max - bvh.node_min, 0.0)
    return float(np.sum(d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]))


@kernel(inline="always")
def _hit_triangle(ox, oy, oz, dx, dy, dz, v0, e1, e2, q, tmin, tmax):
    """Möller–Trumbore, inclusive edges; True when the ray hits triangle q with t in [tmin, tmax]."""
    e1x, e1y, e1z = e1[q, 0], e1[q, 1], e1[q, 2]
    e2x, e2y, e2z = e2[q, 0], e2[q, 1], e2[q, 2]
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return False, 0.0
    inv = 1.0 / det
    sx = ox - v0[q, 0]
    sy = oy - v0[q, 1]
    sz = oz - v0[q, 2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return False, 0.0
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return False, 0.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t < tmin or t > tmax:
        return False, t
    return True, t


@kernel(inline="always")
def _slab(lo, hi, o, inv, t0, t1):
    """Clip [t0, t1] by one slab; a zero direction component (inv = inf) keeps or empties it."""
    if inv == np.inf:
        if o < lo or o > hi:
            return 1.0, 0.0
        return t0, t1
    a = (lo - o) * inv
    b = (hi - o) * inv
    if a > b:
        a, b = b, a
    if a > t0:
        t0 = a
    if b < t1:
        t1 = b
    return t0, t1


@kernel(inline="always")
def _box_hit(node_min, node_max, k, ox, oy, oz, ix, iy, iz, tmin, tmax):
    t0, t1 = _slab(node_min[k, 0], node_max[k, 0], ox, ix, tmin, tmax)
    t0, t1 = _slab(node_min[k, 1], node_max[k, 1], oy, iy, t0, t1)
    t0, t1 = _slab(node_min[k, 2], node_max[k, 2], oz, iz, t0, t1)
    # Slack for rounding in the slab products (boxes are tight around the triangles).
    return t0 <= t1 + 1e-12 * (abs(t1) + 1.0)


@kernel
def _segment_blocked(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                     ox, oy, oz, dx, dy, dz, tmin, tmax, ig0, ig1, stack):
    ix = 1.0 / dx if dx != 0.0 else np.inf
    iy = 1.0 / dy if dy != 0.0 else np.inf
    iz = 1.0 / dz if dz != 0.0 else np.inf
    sp = 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        k = stack[sp]
        if not _box_hit(node_min, node_max, k, ox, oy, oz, ix, iy, iz, tmin, tmax):
            continue
        c = node_child[k]
        if c < 0:
            s = node_start[k]
            for q in range(s, s + node_count[k]):
                tid = order[q]
                if tid == ig0 or tid == ig1:
                    continue
                hit, t = _hit_triangle(ox, oy, oz, dx, dy, dz, v0, e1, e2, q, tmin, tmax)
                if hit:
                    return True
        else:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
    return False


@parallel_range("a", 256)
def _segments_occluded(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, a, b, ignore, eps, out, first, last):
    n = a.shape[0]
    for ch in range(first, last):
        stack = np.empty(256, dtype=np.int64)
        for s in range(ch * 256, min(n, ch * 256 + 256)):
            dx = b[s, 0] - a[s, 0]
            dy = b[s, 1] - a[s, 1]
            dz = b[s, 2] - a[s, 2]
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            if not length > 2.0 * eps:
                out[s] = False
                continue
            tmin = eps / length
            tmax = 1.0 - eps / length
            out[s] = _segment_blocked(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                                      a[s, 0], a[s, 1], a[s, 2], dx, dy, dz, tmin, tmax, ignore[s, 0], ignore[s, 1], stack)


def segments_occluded(bvh, a, b, ignore=None, eps=1e-6):
    """For each segment a[i] -> b[i]: True when a triangle (other than ``ignore[i]``) blocks it.

    ``a``, ``b``: (n,3); ``ignore``: (n,2) int triangle ids (original indices) to skip, -1 for
    none; ``eps``: absolute offset at both ends (segments shorter than 2 eps are unblocked).
    """
    a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
    b = np.ascontiguousarray(b, dtype=np.float64).reshape(-1, 3)
    n = a.shape[0]
    if ignore is None:
        ignore = np.full((n, 2), -1, dtype=np.int64)
    ignore = np.array(np.broadcast_to(np.asarray(ignore, dtype=np.int64).reshape(-1, 2) if np.ndim(ignore) == 2 else np.asarray(ignore, dtype=np.int64).reshape(-1, 1).repeat(2, 1), (n, 2)))
    out = np.zeros(n, dtype=np.bool_)
    if n and bvh.order.shape[0]:
        _segments_occluded(bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order,
                           bvh.v0, bvh.e1, bvh.e2, a, b, ignore, float(eps), out)
    return out


@kernel
def ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                 ox, oy, oz, dx, dy, dz, tmin, tmax, ig, stack):
    ix = 1.0 / dx if dx != 0.0 else np.inf
    iy = 1.0 / dy if dy != 0.0 else np.inf
    iz = 1.0 / dz if dz != 0.0 else np.inf
    best_t = tmax
    best = -1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        k = stack[sp]
        if not _box_hit(node_min, node_max, k, ox, oy, oz, ix, iy, iz, tmin, best_t):
            continue
        c = node_child[k]
        if c < 0:
            s = node_start[k]
            for q in range(s, s + node_count[k]):
                tid = order[q]
                if tid == ig:
                    continue
                hit, t = _hit_triangle(ox, oy, oz, dx, dy, dz, v0, e1, e2, q, tmin, best_t)
                if hit and (t < best_t or best < 0 or (t == best_t and tid < best)):  # ties: the smallest id
                    best_t = t
                    best = tid
        else:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
    return best, best_t


@parallel_range("o", 256)
def _rays_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, o, d, tmin, ignore, out_tri, out_t, first, last):
    n = o.shape[0]
    for ch in range(first, last):
        stack = np.empty(256, dtype=np.int64)
        for s in range(ch * 256, min(n, ch * 256 + 256)):
            tri, t = ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                                  o[s, 0], o[s, 1], o[s, 2], d[s, 0], d[s, 1], d[s, 2], tmin, np.inf, ignore[s], stack)
            out_tri[s] = tri
            out_t[s] = t


def rays_closest(bvh, origin, direction, ignore=None, tmin=0.0):
    """Closest hit of each ray origin + t direction (t > tmin): (triangle id or -1, t)."""
    o = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(direction, dtype=np.float64).reshape(-1, 3)
    n = o.shape[0]
    ig = np.full(n, -1, dtype=np.int64) if ignore is None else np.array(np.broadcast_to(np.asarray(ignore, dtype=np.int64), (n,)))
    out_tri = np.full(n, -1, dtype=np.int64)
    out_t = np.full(n, np.inf)
    if n and bvh.order.shape[0]:
        _rays_closest(bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order,
                      bvh.v0, bvh.e1, bvh.e2, o, d, float(tmin), ig, out_tri, out_t)
    out_t[out_tri < 0] = np.inf
    return out_tri, out_t
