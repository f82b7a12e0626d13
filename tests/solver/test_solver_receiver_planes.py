"""Flat receivers extended beyond their edges (addon/solver/geometry/receiver_planes.py) and the
splat's clip to their UV region (addon/solver/estimators/splat.py): which receivers qualify,
where an extended ray lands (against the ray-plane intersection worked out here), and that the
splat deposits exactly the part of an image inside the region (against areas computed by hand
and a brute-force integral)."""

import numpy as np
import pytest

from addon.solver.estimators.splat import region_shares, splat_triangles
from addon.solver.geometry.receiver_planes import (EXTEND_FRACTION, PLANE_HEAD, beyond_region, beyond_region_rows, extended_landing,
                                                   receiver_plane_row, region_of)


def _frame():
    """A tilted plane: origin, unit axes s, t in it, unit normal n (= s x t)."""
    a = np.radians(25.0)
    s = np.array([np.cos(a), 0.0, np.sin(a)])
    t = np.array([0.0, 1.0, 0.0])
    return np.array([0.3, -0.2, 0.5]), s, t, np.cross(s, t)


def _quad(nx=2, ny=2, uv_lo=(0.2, 0.1), uv_size=0.5, side=2.0):
    """A side x side square in the tilted plane cut into nx x ny quads (2 triangles each, e1 x e2
    along n), corner normals n, UV = uv_lo + uv_size x (position / side)."""
    o, s, t, n = _frame()
    tris, uvs = [], []
    for i in range(nx):
        for j in range(ny):
            q = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]
            for a, b, c in ((0, 1, 2), (0, 2, 3)):
                pts = [(q[k][0] / nx, q[k][1] / ny) for k in (a, b, c)]
                tris.append([o + side * (x * s + y * t) for x, y in pts])
                uvs.append([(uv_lo[0] + uv_size * x, uv_lo[1] + uv_size * y) for x, y in pts])
    P = np.array(tris)
    return P, np.broadcast_to(n, P.shape).copy(), np.array(uvs)


def test_a_flat_quad_gets_its_plane_uv_map_and_region():
    P, N, UV = _quad()
    row = receiver_plane_row(P, N, UV, np.arange(P.shape[0]), 3)
    o, s, t, n = _frame()
    np.testing.assert_allclose(row[0:3], n, atol=1e-12)
    assert abs(row[3] - n @ o) <= 1e-12
    pts = P.reshape(-1, 3)
    np.testing.assert_allclose(pts @ row[4:7] + row[7], UV.reshape(-1, 2)[:, 0], atol=1e-12)
    np.testing.assert_allclose(pts @ row[8:11] + row[11], UV.reshape(-1, 2)[:, 1], atol=1e-12)
    assert row[13] == 3 and row[14] == 4 and abs(row[15] - EXTEND_FRACTION * 0.5) <= 1e-12
    region = region_of(row[None], 3)
    corners = np.array([[0.2, 0.1], [0.7, 0.1], [0.7, 0.6], [0.2, 0.6]])
    values = corners @ region[:, :2].T + region[:, 2]
    assert np.all(values >= -1e-12) and np.all(np.abs(values).min(axis=1) <= 1e-12)
    np.testing.assert_allclose(np.linalg.norm(region[:, :2], axis=1), 1.0)
    centre = np.array([0.45, 0.35])
    np.testing.assert_allclose(np.sort(centre @ region[:, :2].T + region[:, 2]), 0.25)


def test_receivers_that_are_not_one_flat_convex_uv_plane_are_not_extended():
    P, N, UV = _quad()
    ids = np.arange(P.shape[0])
    bent = P.copy()
    bent[bent[:, :, 1] > 1.7] += 0.01 * _frame()[3]  # the far edge lifted off the plane
    assert receiver_plane_row(bent, N, UV, ids, 0) is None
    warped = UV.copy()
    warped[0, 1] += 1e-4  # one corner's UV off the affine map
    assert receiver_plane_row(P, N, warped, ids, 0) is None
    smooth = N.copy()
    smooth[0, 0] = smooth[0, 0] + 0.05 * _frame()[1]
    assert receiver_plane_row(P, smooth, UV, ids, 0) is None
    P3, N3, UV3 = _quad(nx=2, ny=2)
    keep = np.ones(P3.shape[0], dtype=bool)
    keep[6:8] = False  # an L: one quad of four left out, the UV region is not convex
    assert receiver_plane_row(P3[keep], N3[keep], UV3[keep], np.arange(keep.sum()), 0) is None
    assert receiver_plane_row(P, N, UV, ids, 0) is not None


def test_a_ray_missing_the_receiver_lands_on_its_plane_within_reach():
    P, N, UV = _quad()
    planes = receiver_plane_row(P, N, UV, np.arange(P.shape[0]), 0)[None]
    o, s, t, n = _frame()
    start = o + 3.0 * n

    def land(target):
        d = target - start
        d /= np.linalg.norm(d)
        return extended_landing(planes, *start, *d, 1e-9), d

    reach = EXTEND_FRACTION * 0.5  # of the UV region [0.2, 0.7] x [0.1, 0.6]
    # just beyond the edge x = side (u = 0.7): UV (0.7 + 0.5 * 0.1 / 2, 0.35), inside the reach
    p, d = land(o + 2.1 * s + 1.0 * t)
    assert p == 0
    tt = (planes[0, 3] - planes[0, :3] @ start) / (planes[0, :3] @ d)
    hit = start + tt * d
    np.testing.assert_allclose([hit @ planes[0, 4:7] + planes[0, 7], hit @ planes[0, 8:11] + planes[0, 11]],
                               [0.725, 0.35], atol=1e-12)
    assert land(o + 1.0 * s + 1.0 * t)[0] == -1  # inside the region: a ray that misses it there is blocked, not extended
    assert land(o + (2.0 + (reach - 0.01) / 0.25) * s + 1.0 * t)[0] == 0  # just inside the reach (u = 0.7 + reach - 0.0025)
    assert land(o + (2.0 + (reach + 0.01) / 0.25) * s + 1.0 * t)[0] == -1  # beyond it
    behind = o - 3.0 * n  # from the back: the bake's front rule
    d = (o + 2.1 * s + t) - behind
    assert extended_landing(planes, *behind, *(d / np.linalg.norm(d)), 1e-9) == -1
    d = s + 0.0 * n  # parallel to the plane
    assert extended_landing(planes, *start, *d, 1e-9) == -1


def test_beyond_region_needs_every_point_past_one_edge_by_the_margin():
    P, N, UV = _quad()
    planes = receiver_plane_row(P, N, UV, np.arange(P.shape[0]), 2)[None]
    pts = np.array([[0.80, 0.3], [0.85, 0.4], [0.82, 0.5]])  # past u = 0.7 by 0.10 .. 0.15
    assert beyond_region(planes, 2, pts[:, 0].copy(), pts[:, 1].copy(), 0.09)
    assert not beyond_region(planes, 2, pts[:, 0].copy(), pts[:, 1].copy(), 0.11)
    assert not beyond_region(planes, 1, pts[:, 0].copy(), pts[:, 1].copy(), 0.0)  # another receiver: no row
    corner = np.array([[0.75, 0.15], [0.65, 0.05], [0.8, 0.0]])  # around the corner: no single edge has them all
    assert not beyond_region(planes, 2, corner[:, 0].copy(), corner[:, 1].copy(), 0.0)
    rows = beyond_region_rows(planes, np.array([2, 2, 1]), np.stack([pts, corner, pts]), np.array([0.09, 0.0, 0.0]))
    np.testing.assert_array_equal(rows, [True, False, False])


def test_the_splat_deposits_only_the_part_inside_the_region():
    """A triangle across the region's edge u = 0.5 (texture 8 x 8, region the left half): with a
    uniform density the texture gets the flux times the area fraction inside (by hand: 3/4 of
    the triangle (0.3, 0.2), (0.7, 0.2), (0.3, 0.6) lies left of u = 0.5), none right of the edge;
    with a linear density, region_shares and the deposit match a brute-force integral."""
    region = np.array([[-1.0, 0.0, 0.5], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 1.0]])  # 0 <= u <= 0.5, 0 <= v <= 1
    tri = np.array([[[0.3, 0.2], [0.7, 0.2], [0.3, 0.6]]])
    W = H = 8
    out = np.zeros((W * H, 3))
    splat_triangles(tri, np.ones((1, 3)), W, H, out, np.ones((1, 3)), region=region)
    img = out[:, 0].reshape(H, W)
    assert abs(img.sum() - 0.75) <= 1e-12
    assert img[:, 4:].sum() == 0.0
    assert abs(region_shares(tri, np.ones((1, 3)), region)[0] - 0.75) <= 1e-12
    dens = np.array([[1.0, 3.0, 0.5]])
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(2, 400_000))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    p = tri[0, 0] + a[:, None] * (tri[0, 1] - tri[0, 0]) + b[:, None] * (tri[0, 2] - tri[0, 0])
    rho = dens[0, 0] + a * (dens[0, 1] - dens[0, 0]) + b * (dens[0, 2] - dens[0, 0])
    brute = (rho * (p[:, 0] <= 0.5)).sum() / rho.sum()
    share = region_shares(tri, dens, region)[0]
    assert abs(share - brute) <= 3e-3
    out = np.zeros((W * H, 3))
    splat_triangles(tri, np.ones((1, 3)), W, H, out, dens, region=region)
    assert abs(out[:, 0].sum() - share) <= 1e-12
    inside = np.zeros((W * H, 3))
    splat_triangles(np.array([[[0.1, 0.1], [0.4, 0.2], [0.2, 0.5]]]), np.ones((1, 3)), W, H, inside, dens, region=region)
    plain = np.zeros((W * H, 3))
    splat_triangles(np.array([[[0.1, 0.1], [0.4, 0.2], [0.2, 0.5]]]), np.ones((1, 3)), W, H, plain, dens)
    np.testing.assert_array_equal(inside, plain)  # an image inside the region: the splat as without one


@pytest.mark.parametrize("edges", [4, 7])
def test_region_edges_are_unit_half_planes_of_the_hull(edges):
    """A fan of triangles over a convex polygon with ``edges`` sides: K = edges, each row's (a, b)
    unit, every polygon vertex inside all of them (on two)."""
    ang = 2 * np.pi * np.arange(edges) / edges
    ring = np.column_stack([0.5 + 0.4 * np.cos(ang), 0.5 + 0.4 * np.sin(ang)])
    uv = np.array([[[0.5, 0.5], ring[k], ring[(k + 1) % edges]] for k in range(edges)])
    P = np.concatenate([uv, np.zeros((edges, 3, 1))], axis=2)
    N = np.zeros_like(P)
    N[..., 2] = 1.0
    row = receiver_plane_row(P, N, uv, np.arange(edges), 0)
    assert row is not None and row[14] == edges
    region = row[PLANE_HEAD:PLANE_HEAD + 3 * edges].reshape(edges, 3)
    np.testing.assert_allclose(np.linalg.norm(region[:, :2], axis=1), 1.0)
    values = ring @ region[:, :2].T + region[:, 2]
    assert values.min() >= -1e-12
    assert np.all((np.abs(values) <= 1e-12).sum(axis=1) == 2)
