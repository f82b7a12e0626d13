"""BVH shadow rays (addon/solver/geometry/bvh.py) against brute-force ray/triangle intersection."""

import numpy as np

from addon.solver.geometry.bvh import box_area, build_bvh, rays_closest, refit_bvh, segments_occluded


def _brute_hits(a, b, tri, eps):
    """(n, T) bool: segment a -> b meets triangle t with t in [eps/L, 1 - eps/L] (textbook Möller–Trumbore)."""
    d = b - a
    L = np.linalg.norm(d, axis=1)
    v0 = tri[:, 0]
    e1 = tri[:, 1] - v0
    e2 = tri[:, 2] - v0
    out = np.zeros((a.shape[0], tri.shape[0]), bool)
    tvals = np.full((a.shape[0], tri.shape[0]), np.inf)
    for s in range(a.shape[0]):
        p = np.cross(d[s], e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(all="ignore"):
            inv = 1.0 / det
            sv = a[s] - v0
            u = np.einsum("ij,ij->i", sv, p) * inv
            q = np.cross(sv, e1)
            v = (q @ d[s]) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= eps / L[s]) & (t <= 1 - eps / L[s])
        out[s] = ok
        tvals[s, ok] = t[ok]
    return out, tvals


def _random_soup(rng, n, spread=5.0, size=0.5):
    c = rng.uniform(-spread, spread, (n, 1, 3))
    return c + rng.normal(scale=size, size=(n, 3, 3))


def test_any_hit_matches_brute_force_on_random_scenes():
    rng = np.random.default_rng(11)
    for n_tri in (1, 7, 300, 2000):
        tri = _random_soup(rng, n_tri)
        bvh = build_bvh(tri)
        assert sorted(bvh.order.tolist()) == list(range(n_tri))
        a = rng.uniform(-6, 6, (1500, 3))
        b = rng.uniform(-6, 6, (1500, 3))
        got = segments_occluded(bvh, a, b, eps=1e-9)
        hits, _ = _brute_hits(a, b, tri, 1e-9)
        np.testing.assert_array_equal(got, hits.any(axis=1))
        assert 0.02 < got.mean() < 0.98 or n_tri < 10
        # Ignoring triangles: ignore the first hit triangle of each blocked segment.
        first = np.where(hits.any(1), hits.argmax(1), -1)
        ig = np.column_stack([first, np.full(first.size, -1)])
        got2 = segments_occluded(bvh, a, b, ig, eps=1e-9)
        hits2 = hits.copy()
        hits2[np.arange(first.size)[first >= 0], first[first >= 0]] = False
        np.testing.assert_array_equal(got2, hits2.any(axis=1))


def test_closest_hit_matches_brute_force():
    rng = np.random.default_rng(5)
    tri = _random_soup(rng, 500)
    bvh = build_bvh(tri)
    o = rng.uniform(-6, 6, (800, 3))
    d = rng.normal(size=(800, 3))
    tri_id, t = rays_closest(bvh, o, d)
    hits, tv = _brute_hits(o, o + 100.0 * d, tri, 0.0)
    expect = np.where(hits.any(1), tv.argmin(1), -1)
    np.testing.assert_array_equal(tri_id, expect)
    ok = expect >= 0
    np.testing.assert_allclose(t[ok], 100.0 * tv.min(1)[ok], rtol=1e-12)


def test_offsets_and_axis_aligned_geometry():
    # A floor of two triangles; segments that start or end on it are not blocked by it.
    floor = np.array([[[-1, -1, 0], [1, -1, 0], [1, 1, 0]], [[-1, -1, 0], [1, 1, 0], [-1, 1, 0]]], float)
    wall = np.array([[[0.5, -1, 0], [0.5, 1, 0], [0.5, 1, 2]]], float)
    tri = np.concatenate([floor, wall])
    bvh = build_bvh(tri)
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.2, 0.3, 1.0], [0.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 1.0], [1.0, 0.5, 1.0], [0.0, 0.0, -1.0], [0.2, 0.3, 0.0], [0.0, 0.0, 0.0]])
    got = segments_occluded(bvh, a, b, eps=1e-7)
    # up from the floor: free; through the wall: blocked; through the floor: blocked;
    # down onto the floor (ends on it): free; zero length: free.
    assert got.tolist() == [False, True, True, False, False]
    # Through the shared diagonal edge of the two floor triangles: blocked (no leak).
    got = segments_occluded(bvh, np.array([[0.25, 0.25, 1.0]]), np.array([[0.25, 0.25, -1.0]]), eps=1e-9)
    assert got.tolist() == [True]
    # Ignoring both floor triangles lets it through.
    got = segments_occluded(bvh, np.array([[0.25, 0.25, 1.0]]), np.array([[0.25, 0.25, -1.0]]), np.array([[0, 1]]), eps=1e-9)
    assert got.tolist() == [False]


def test_empty_and_degenerate():
    bvh = build_bvh(np.zeros((0, 3, 3)))
    assert segments_occluded(bvh, np.zeros((2, 3)), np.ones((2, 3))).tolist() == [False, False]
    # A zero-area triangle never blocks; identical triangles are fine.
    tri = np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2]]] + [[[-1, -1, 0.5], [1, -1, 0.5], [0, 1, 0.5]]] * 20, float)
    bvh = build_bvh(tri)
    got = segments_occluded(bvh, np.array([[0, 0, 1.0], [1, 1, -1.0]]), np.array([[0, 0, -1.0], [1, 1, 3.0]]), eps=1e-9)
    assert got.tolist() == [True, False]


def _grid(n, z):
    """An n x n grid of quads (2 n² triangles) over [0, 1]², heights z (n + 1, n + 1)."""
    s = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(s, s, indexing="ij")
    V = np.stack([X, Y, z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    q = (a, a + n + 1, a + n + 2, a + 1)
    idx = np.concatenate([np.stack([q[0], q[1], q[2]], 1), np.stack([q[0], q[2], q[3]], 1)])
    return V[idx]


def test_refit_answers_as_a_fresh_build():
    """A tree refitted to moved triangles gives every query the answer of a tree built on them:
    closest hits (ties on shared edges go to the smallest id, whatever the tree) and any-hits;
    its boxes hold their triangles; a far move costs box area (what scene_bvh watches)."""
    rng = np.random.default_rng(7)
    n = 24
    flat = _grid(n, np.zeros((n + 1, n + 1)))
    moved = _grid(n, 0.05 * rng.normal(size=(n + 1, n + 1)))
    old = build_bvh(flat)
    fresh = build_bvh(moved)
    refit = refit_bvh(old, moved)
    for k in range(refit.node_min.shape[0]):
        if refit.node_child[k] < 0:
            tri = moved[refit.order[refit.node_start[k]:refit.node_start[k] + refit.node_count[k]]]
            assert np.all(tri.min(axis=(0, 1)) >= refit.node_min[k]) and np.all(tri.max(axis=(0, 1)) <= refit.node_max[k])
    # rays from above: random, and straight down through grid vertices and edge midpoints (ties)
    o = np.column_stack([rng.uniform(0, 1, (3000, 2)), np.full(3000, 2.0)])
    g = np.arange(n + 1) / n
    X, Y = np.meshgrid(g, (np.arange(2 * n + 1) / (2 * n)), indexing="ij")
    o = np.concatenate([o, np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 2.0)])])
    d = np.tile([0.0, 0.0, -1.0], (o.shape[0], 1))
    d[:3000] += rng.normal(scale=0.1, size=(3000, 3))
    a_tri, a_t = rays_closest(fresh, o, d)
    b_tri, b_t = rays_closest(refit, o, d)
    np.testing.assert_array_equal(a_tri, b_tri)
    np.testing.assert_array_equal(a_t, b_t)
    assert (a_tri >= 0).mean() > 0.7
    # on the flat grid, vertical rays through shared edges and vertices hit several triangles at
    # the same t: the smallest id, as a brute-force search with that rule
    flat_o = o[3000:]
    tri_id, _ = rays_closest(old, flat_o, d[3000:])
    hits, tv = _brute_hits(flat_o, flat_o + 4.0 * d[3000:], flat, 0.0)
    best = tv.min(axis=1)
    expect = np.where(hits.any(1), np.argmax(hits & (tv == best[:, None]), axis=1), -1)
    np.testing.assert_array_equal(tri_id, expect)
    assert (hits.sum(axis=1) > 1).sum() > 100  # ties were tested
    b = o + 3.0 * d
    np.testing.assert_array_equal(segments_occluded(fresh, o, b), segments_occluded(refit, o, b))
    far = moved + rng.uniform(-5, 5, (moved.shape[0], 1, 3))  # scattered far apart: the old shape is poor
    assert box_area(refit_bvh(old, far)) > 3.0 * box_area(build_bvh(far))
