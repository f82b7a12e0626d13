"""Building blocks of the forward-image two-bounce modes (addon/solver/estimators/forward_image.py)
against independent answers: exact texel overlap vs dense point sampling, solid angle vs
quadrature, closest point vs brute force, the adaptive refinement on analytic maps, and the
merging of duplicate paths.  The whole bake is checked in test_bake_two_bounce.py (double
image source) and test_bake_caustics.py (photon reference)."""

import numpy as np

from addon.solver.estimators.forward_image import _closest_on_triangle, dedupe_paths, refine_image_triangles, solid_angle
from addon.solver.estimators.splat import splat_triangles


def test_splat_matches_dense_sampling_and_conserves_flux():
    rng = np.random.default_rng(1)
    W, H = 12, 9
    tri = rng.uniform(0.05, 0.95, (40, 3, 2))
    tri[:10] = tri[:10] * 0.1 + 0.4  # small ones (inside a texel or two)
    tri[10:12, 2] = tri[10:12, 0] + 1e-3 * (tri[10:12, 1] - tri[10:12, 0])  # slivers
    flux = rng.uniform(0.5, 2.0, (40, 3))
    out = np.zeros((W * H, 3))
    splat_triangles(tri, flux, W, H, out, np.ones((40, 3)))  # uniform density
    assert abs(out.sum() - flux.sum()) <= 1e-9 * flux.sum()  # every triangle inside [0, 1]²
    # per triangle: the fractions of its area in each texel against dense point sampling
    n = 1500
    g = (np.arange(n) + 0.5) / n
    X, Y = np.meshgrid(g, g)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    tex = (np.floor(pts[:, 1] * H) * W + np.floor(pts[:, 0] * W)).astype(int)
    checked = 0
    for t in range(40):
        a, b, c = tri[t]
        d = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])
        l1 = ((b[0] - pts[:, 0]) * (c[1] - pts[:, 1]) - (c[0] - pts[:, 0]) * (b[1] - pts[:, 1])) / d
        l2 = ((c[0] - pts[:, 0]) * (a[1] - pts[:, 1]) - (a[0] - pts[:, 0]) * (c[1] - pts[:, 1])) / d
        inside = (l1 >= 0) & (l2 >= 0) & (1 - l1 - l2 >= 0)
        cnt = np.bincount(tex[inside], minlength=W * H)
        if cnt.sum() < 5000:
            continue
        one = np.zeros((W * H, 3))
        splat_triangles(tri[t:t + 1], np.ones((1, 3)), W, H, one, np.ones((1, 3)))
        assert np.abs(one[:, 0] - cnt / cnt.sum()).sum() <= 30.0 / np.sqrt(cnt.sum())
        checked += 1
    assert checked >= 20
    # in parallel bands of rows: bit for bit one band, triangles reaching over the texture's edges included
    big = rng.uniform(-0.2, 1.2, (300, 3, 2))
    big[:40] = big[:40] * 0.01 + 0.5  # inside a texel
    fl = rng.uniform(0.1, 1.0, (300, 3))
    dens = rng.uniform(0.5, 1.5, (300, 3))
    one_band = np.zeros((W * H, 3))
    splat_triangles(big, fl, W, H, one_band, dens, bands=1)
    for bands in (2, 5, 9, 40):
        banded = np.zeros((W * H, 3))
        splat_triangles(big, fl, W, H, banded, dens, bands=bands)
        assert np.array_equal(banded, one_band)


def test_solid_angle_matches_quadrature():
    rng = np.random.default_rng(2)
    x0 = rng.normal(size=(20, 3)) * 0.3
    corners = rng.normal(size=(20, 3, 3)) + np.array([0.0, 0.0, 2.0])
    omega = solid_angle(x0, corners)
    # midpoint quadrature of omega = ∫ |n . (x - x0)| / |x - x0|³ dA over the m² sub-triangles
    m = 300
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    up = i + j < m
    down = i + j < m - 1
    u = np.concatenate([(i[up] + 1 / 3) / m, (i[down] + 2 / 3) / m])
    v = np.concatenate([(j[up] + 1 / 3) / m, (j[down] + 2 / 3) / m])
    for k in range(20):
        a, b, c = corners[k]
        nrm = np.cross(b - a, c - a)
        area = 0.5 * np.linalg.norm(nrm)
        nrm /= 2 * area
        p = a + u[:, None] * (b - a) + v[:, None] * (c - a) - x0[k]
        r = np.linalg.norm(p, axis=1)
        tot = np.sum(np.abs(p @ nrm) / r ** 3) * area / (m * m)
        assert abs(tot / omega[k] - 1) <= 2e-3, (k, tot, omega[k])


def test_closest_point_on_triangle_matches_brute_force():
    rng = np.random.default_rng(3)
    s = np.linspace(0, 1, 401)
    for k in range(200):
        t = rng.uniform(-1, 1, (3, 2))
        if k % 5 == 0:
            t[2] = t[0] + rng.uniform(0, 1) * (t[1] - t[0]) + 1e-9 * rng.normal(size=2)  # sliver
        p = rng.uniform(-1.5, 1.5, 2)
        wa, wb, wc, d2 = _closest_on_triangle(p[0], p[1], *t[0], *t[1], *t[2])
        assert min(wa, wb, wc) >= -1e-12 and abs(wa + wb + wc - 1) <= 1e-12
        q = wa * t[0] + wb * t[1] + wc * t[2]
        assert abs(np.sum((q - p) ** 2) - d2) <= 1e-12
        # brute force over the triangle (edges and interior grid)
        U, V = np.meshgrid(s, s)
        ok = U + V <= 1
        pts = t[0] + U[ok][:, None] * (t[1] - t[0]) + V[ok][:, None] * (t[2] - t[0])
        best = np.min(np.sum((pts - p) ** 2, axis=1))
        assert d2 <= best + 1e-12
        # and no farther than the grid's best by more than the grid's resolution
        h = 1.5 * max(np.linalg.norm(t[1] - t[0]), np.linalg.norm(t[2] - t[0])) / 400
        assert np.sqrt(d2) >= np.sqrt(best) - h


def _analytic_trace(kind):
    """A trace function for refine_image_triangles: emitter e maps (u, v) -> UV analytically."""

    def trace(e, u, v):
        if kind == "affine":
            uv = np.column_stack([0.1 + 0.5 * u + 0.1 * v, 0.2 + 0.3 * v])
        else:  # a lens-like quadratic map
            uv = np.column_stack([0.5 + 0.4 * (u - 0.3) * (1 + 0.8 * (u + v)), 0.5 + 0.4 * (v - 0.3) * (1 + 0.8 * (u + v))])
        rec = np.where((u >= 0) & (v >= 0) & (u + v <= 1 + 1e-12), 0, -1)
        if kind == "half":  # points with u > 0.6 are lost (a receiver edge)
            uv = np.column_stack([0.1 + 0.5 * u, 0.2 + 0.3 * v])
            rec = np.where(u > 0.6, -1, rec)
        return np.zeros(e.size, dtype=np.int64), rec, uv

    return trace


def test_refinement_on_analytic_maps():
    texel = np.array([1.0 / 256])
    rot = np.zeros(10, dtype=np.int64)  # one receiver: scene triangle 0 is receiver 0
    aff = refine_image_triangles(_analytic_trace("affine"), 3, rot, texel, grid=4, max_depth=6)
    assert aff["final_per_depth"][0] == 3 * 16 and aff["uv"].shape[0] == 3 * 16  # straight at once
    quad = refine_image_triangles(_analytic_trace("quad"), 2, rot, texel, grid=4, max_depth=6)
    area = 0.5 * np.abs(np.cross(quad["bary_full"][:, 1] - quad["bary_full"][:, 0], quad["bary_full"][:, 2] - quad["bary_full"][:, 0]))
    assert abs(area.sum() - 2 * 0.5) <= 1e-12  # the final sub-triangles tile both domains
    assert quad["deviation"].max() <= 0.5 * texel[0] and quad["dropped"] == 0
    assert sum(quad["final_per_depth"][1:]) > 0  # it had to split
    # the midpoint shift test is real: the true image of each final triangle's centroid lies
    # within half a texel of the straight image's centroid
    _, _, cuv = _analytic_trace("quad")(np.zeros(len(area), dtype=np.int64), quad["bary"].mean(1)[:, 0], quad["bary"].mean(1)[:, 1])
    assert np.abs(cuv - quad["uv"].mean(1)).max() <= 0.5 * texel[0]
    half = refine_image_triangles(_analytic_trace("half"), 1, rot, texel, grid=4, max_depth=5)
    area = 0.5 * np.abs(np.cross(half["bary_full"][:, 1] - half["bary_full"][:, 0], half["bary_full"][:, 2] - half["bary_full"][:, 0]))
    landed_area = np.sum(area * half["landed"])
    # the landed part of the domain {u <= 0.6} has area 0.5 - 0.5 * 0.4² = 0.42; its border
    # is straight, so the partly landed sub-triangles are cut there (bisected to 1/128 of an
    # edge) instead of being approximated by their landed points (measured 4.1e-5 off; the
    # hull approximation was 1e-2 off)
    assert abs(landed_area - 0.42) <= 2e-4 and half["border"] > 0 and half["partial"] == 0


def test_dedupe_paths():
    sample = np.array([3, 3, 3, 1, 1, 3])
    t1 = np.array([5, 5, 5, 5, 5, 5])
    t2 = np.array([7, 7, 8, 7, 7, 7])
    uv = np.array([[0.1, 0.2, 0.3, 0.4], [0.1, 0.2 + 1e-9, 0.3, 0.4], [0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 0.3, 0.4],
                   [0.5, 0.2, 0.3, 0.4], [0.1 + 1e-3, 0.2, 0.3, 0.4]])
    keep = dedupe_paths(sample, t1, t2, uv)
    assert keep.tolist() == [0, 2, 3, 4, 5]


def test_lost_sub_triangles_are_probed_before_they_are_dropped():
    """Light landing only in a small disk that no corner or edge midpoint of the first two
    levels hits (the corner of a landed region poking between the 6 points, as at the corner
    of a glass slab's image): without the 7 probes the disk's flux was dropped as 'lost'."""
    centre, radius = np.array([0.28, 0.28]), 0.03

    def trace(e, u, v):
        inside = (u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius ** 2
        uv = np.column_stack([0.1 + 0.5 * u, 0.2 + 0.3 * v])
        return np.zeros(e.size, dtype=np.int64), np.where(inside, 0, -1), uv

    texel = np.array([1.0 / 64])
    rot = np.zeros(10, dtype=np.int64)
    out = refine_image_triangles(trace, 1, rot, texel, grid=4, max_depth=5)
    area = 0.5 * np.abs(np.cross(out["bary_full"][:, 1] - out["bary_full"][:, 0], out["bary_full"][:, 2] - out["bary_full"][:, 0]))
    landed_area = np.sum(area * out["landed"])
    # measured -0.57 % (the cut's polygons inside a circle 2 texels across)
    assert abs(landed_area / (np.pi * radius ** 2) - 1.0) <= 0.01
    # and the points sampled at depths 0 and 1 do miss it (the case is the one described)
    g = np.arange(0, 1 + 1e-12, 1 / 16)
    uu, vv = np.meshgrid(g, g)
    assert np.all((uu - centre[0]) ** 2 + (vv - centre[1]) ** 2 > radius ** 2)


def test_density_nonlinearity_on_analytic_cases():
    """Zero for an affine map with a constant density; for an affine map with density w(u) =
    1 / (0.2 + u)² the midpoint value against the mean of the corners, exactly; inf at a fold."""
    from addon.solver.estimators.forward_image import density_nonlinearity

    corners = np.array([[[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]]])
    mids = 0.5 * (corners + corners[:, [1, 2, 0]])
    A = np.array([[0.3, 0.1], [-0.05, 0.2]])
    uv, muv = corners @ A.T, mids @ A.T
    assert density_nonlinearity(uv, muv, np.ones((1, 6)))[0] <= 1e-12
    pts = np.concatenate([corners, mids], axis=1)
    w = 1.0 / (0.2 + pts[..., 0]) ** 2
    lin = 0.5 * (w[0, :3] + w[0, [1, 2, 0]])
    expect = np.abs(w[0, 3:] - lin).max() / w[0, :3].mean()
    assert abs(density_nonlinearity(uv, muv, w)[0] - expect) <= 1e-12 * expect
    fold = muv.copy()
    fold[0, 0] = uv[0, 0] + 1.5 * (uv[0, 1] - uv[0, 0])  # the 01 midpoint beyond corner 1: det J changes sign
    assert np.isinf(density_nonlinearity(uv, fold, np.ones((1, 6)))[0])


def test_refinement_follows_a_nonlinear_light_density():
    """An affine map is straight at once, but with the light's density 1 / (0.2 + u)² the
    sub-triangles are split until the density is linear to ``relative`` over each: at every
    final sub-triangle's centroid the true density is within ~relative of the linear
    interpolation of its corners'."""
    texel = np.array([1.0 / 256])
    rot = np.zeros(10, dtype=np.int64)

    def weight(e, bary):
        return 1.0 / (0.2 + bary[..., 0]) ** 2

    plain = refine_image_triangles(_analytic_trace("affine"), 1, rot, texel, grid=4, max_depth=6)
    assert plain["final_per_depth"][0] == 16
    out = refine_image_triangles(_analytic_trace("affine"), 1, rot, texel, grid=4, max_depth=6, relative=0.01, weight=weight)
    assert sum(out["final_per_depth"][1:]) > 0
    b = out["bary_full"]
    wc = weight(None, b)  # corners
    cen = weight(None, b.mean(axis=1, keepdims=True))[:, 0]
    err = np.abs(cen - wc.mean(axis=1)) / wc.mean(axis=1)
    # images larger than a texel obey the bound (smaller ones are final anyway)
    big = np.abs(out["uv"] - out["uv"][:, [1, 2, 0]]).max(axis=(1, 2)) > texel[0]
    assert big.any() and err[big].max() <= 0.01


def test_ragged_landing_is_not_followed_below_a_texel():
    """Landing in a checkerboard far finer than a texel (a ragged self-shadow, as on the
    metal ring): partly landed sub-triangles are approximated once their image is within
    ROUGH_TEXELS of a texel instead of being split to ``partial_depth`` (16 x 4^8 = 1M
    sub-triangles here; the ring's bake took 24 GB: measured 23,770).  The landed share
    (truly 1/2) comes out 0.63: a pattern finer than the points sampled aliases (items whose
    6 points all land count whole; all-lost ones are probed and split) — any deterministic
    sampling errs here; the bound is on the cost, the share only sanity-checked."""
    def trace(e, u, v):
        on = np.sin(2000.0 * u) * np.sin(2000.0 * v) > 0
        uv = np.column_stack([0.1 + 0.5 * u, 0.2 + 0.5 * v])
        return np.zeros(e.size, dtype=np.int64), np.where(on, 0, -1), uv

    texel = np.array([1.0 / 64])
    out = refine_image_triangles(trace, 1, np.zeros(10, dtype=np.int64), texel, grid=4, max_depth=6)
    assert out["emitter"].size < 60_000 and out["partial"] > 10_000
    assert sum(out["final_per_depth"][7:]) < 1_000  # stopped near depth 6, not at partial_depth 8
    area = 0.5 * np.abs(np.cross(out["bary_full"][:, 1] - out["bary_full"][:, 0], out["bary_full"][:, 2] - out["bary_full"][:, 0]))
    assert 0.4 <= np.sum(area * out["landed"]) / 0.5 <= 0.7


def test_sliver_images_take_the_uniform_splat():
    """corner_densities: a well-shaped image of an affine map with a light close by gets the
    light's solid-angle ramp; the same corners squeezed into a sliver (aspect above SLIVER,
    where det J is a small difference of nearly parallel derivatives) get (1, 1, 1)."""
    from addon.solver.estimators.forward_image import SLIVER, corner_densities

    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    bary = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    x0 = np.array([[0.0, 0.0, 1.5]])  # the solid angle per area falls 1.7x from corner 0 to 1
    uv = np.array([[[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]]])
    mid = 0.5 * (uv + uv[:, [1, 2, 0]])
    good = corner_densities(uv, mid, x0, tri, bary)
    w = np.array([1.5 / 1.5 ** 3, 1.5 / 3.25 ** 1.5, 1.5 / 3.25 ** 1.5])  # |n.(p - x0)| / |p - x0|³
    np.testing.assert_allclose(good[0], w / w.mean(), rtol=1e-12)  # affine map: det J constant
    sliver = uv * np.array([1.0, 0.02])  # aspect (0.5² + 0.01²) / (0.5 * 0.01) ≈ 50
    smid = 0.5 * (sliver + sliver[:, [1, 2, 0]])
    e = sliver[0] - sliver[0][[1, 2, 0]]
    assert (e ** 2).sum(axis=1).max() / abs(e[0, 0] * e[2, 1] - e[0, 1] * e[2, 0]) > SLIVER
    np.testing.assert_array_equal(corner_densities(sliver, smid, x0, tri, bary), np.ones((1, 3)))
