"""UV-space rasterisation and seam padding (addon/bake/raster.py), no Blender."""

import numpy as np
import pytest

from addon.bake.raster import TEXEL_BLOCK, bands, grid_side, pad, rasterise, texel_irradiance
from addon.bake.scene import Light, build_scene


def _quad_scene(resolution, uv=None, origin=(0.0, 0.0, 1.0), size=(2.0, 3.0)):
    """A world rectangle [0, 2] x [0, 3] at z = 1 mapped onto the unit UV square."""
    ox, oy, oz = origin
    sx, sy = size
    P = np.array([[[ox, oy, oz], [ox + sx, oy, oz], [ox + sx, oy + sy, oz]],
                  [[ox, oy, oz], [ox + sx, oy + sy, oz], [ox, oy + sy, oz]]])
    UV = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float) if uv is None else uv
    return build_scene([dict(name="quad", tri_p=P, uv=UV, receiver=True, resolution=resolution)], [Light("L", "point", (1, 1, 1), 1.0)])


def test_texel_centres_map_exactly_onto_the_unit_quad():
    sc = _quad_scene((4, 3))
    band = rasterise(sc, sc.receivers[0], samples=1)
    # Every texel is covered exactly once (the diagonal is shared, not doubled).
    assert np.array_equal(np.bincount(band.texel, minlength=12), np.ones(12, dtype=int))
    i = band.texel % 4
    j = band.texel // 4
    expected = np.column_stack([(i + 0.5) / 4 * 2.0, (j + 0.5) / 3 * 3.0, np.ones(12)])
    np.testing.assert_allclose(band.position, expected, atol=1e-14)
    np.testing.assert_allclose(band.uv, np.column_stack([(i + 0.5) / 4, (j + 0.5) / 3]), atol=1e-15)
    np.testing.assert_allclose(band.normal, np.tile([0.0, 0.0, 1.0], (12, 1)))


def test_stratified_supersamples_are_in_their_strata():
    sc = _quad_scene((5, 5))
    for jitter in (False, True):
        band = rasterise(sc, sc.receivers[0], samples=9, seed=3, jitter=jitter)
        assert band.size == 25 * 9
        assert np.array_equal(np.bincount(band.texel), np.full(25, 9))
        # Local coordinates inside the texel, then the stratum of each sample.
        i = band.texel % 5
        j = band.texel // 5
        lu = band.uv[:, 0] * 5 - i
        lv = band.uv[:, 1] * 5 - j
        assert np.all((lu >= 0) & (lu < 1) & (lv >= 0) & (lv < 1))
        for t in range(25):
            sel = band.texel == t
            strata = np.floor(lu[sel] * 3).astype(int) + 3 * np.floor(lv[sel] * 3).astype(int)
            assert sorted(strata) == list(range(9)), "one sample per stratum"
        np.testing.assert_allclose(band.position[:, :2], band.uv * [2.0, 3.0], atol=1e-14)
    # Jitter is deterministic for a seed and changes with it.
    a = rasterise(sc, sc.receivers[0], samples=4, seed=1, jitter=True)
    b = rasterise(sc, sc.receivers[0], samples=4, seed=1, jitter=True)
    c = rasterise(sc, sc.receivers[0], samples=4, seed=2, jitter=True)
    assert np.array_equal(a.uv, b.uv) and not np.array_equal(a.uv, c.uv)


def test_bands_reproduce_the_whole_raster():
    sc = _quad_scene((7, 9))
    whole = rasterise(sc, sc.receivers[0], samples=4, seed=5, jitter=True)
    parts = [rasterise(sc, sc.receivers[0], samples=4, seed=5, jitter=True, rows=r) for r in [(0, 2), (2, 3), (3, 9)]]
    for name in ("texel", "tri", "uv", "position"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts]), getattr(whole, name))
    rows = bands(sc.receivers[0], samples=4, max_samples=7 * 4 * 2)
    assert rows[0] == (0, 2) and rows[-1] == (8, 9) and len(rows) == 5


def test_partial_uv_layout_coverage_and_affine_map():
    # One triangle covering the lower-left half of UV space, world: a sheared triangle.
    P = np.array([[[1.0, 2.0, 0.0], [3.0, 2.0, 1.0], [1.0, 5.0, 2.0]]])
    UV = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    sc = build_scene([dict(name="t", tri_p=P, uv=UV, receiver=True, resolution=(8, 8))], [Light("L", "point", (1, 1, 1), 1.0)])
    band = rasterise(sc, sc.receivers[0], samples=1)
    i = band.texel % 8
    j = band.texel // 8
    # Texel centres with u + v <= 1 are covered: i + j + 1 <= 8.
    assert set(zip(i.tolist(), j.tolist())) == {(a, b) for a in range(8) for b in range(8) if a + b + 1 <= 8}
    u = (i + 0.5) / 8
    v = (j + 0.5) / 8
    expected = P[0, 0] + u[:, None] * (P[0, 1] - P[0, 0]) + v[:, None] * (P[0, 2] - P[0, 0])
    np.testing.assert_allclose(band.position, expected, atol=1e-14)
    ng = np.cross(P[0, 1] - P[0, 0], P[0, 2] - P[0, 0])
    np.testing.assert_allclose(band.geo_normal, np.tile(ng / np.linalg.norm(ng), (band.size, 1)), atol=1e-15)


def test_interpolated_normals_follow_the_barycentrics():
    P = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    N = np.array([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]]) / np.array([1.0, np.sqrt(2), np.sqrt(2)])[None, :, None]
    sc = build_scene([dict(name="t", tri_p=P, tri_n=N, uv=P[:, :, :2], receiver=True, resolution=(4, 4))], [Light("L", "point", (1, 1, 1), 1.0)])
    band = rasterise(sc, sc.receivers[0], samples=1)
    u, v = band.bary[:, 0], band.bary[:, 1]
    n = N[0, 0] + u[:, None] * (N[0, 1] - N[0, 0]) + v[:, None] * (N[0, 2] - N[0, 0])
    np.testing.assert_allclose(band.normal, n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-15)
    np.testing.assert_allclose(band.bary, band.uv, atol=1e-15)


def test_overlapping_uvs_first_triangle_wins():
    P = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 5], [1, 0, 5], [0, 1, 5]]], float)
    UV = np.array([[[0, 0], [1, 0], [0, 1]]] * 2, float)
    sc = build_scene([dict(name="t", tri_p=P, uv=UV, receiver=True, resolution=(6, 6))], [Light("L", "point", (1, 1, 1), 1.0)])
    band = rasterise(sc, sc.receivers[0], samples=4)
    assert band.size == np.unique(band.texel * 4 + np.arange(band.size) % 4).size
    assert np.all(band.tri == 0) and np.all(band.position[:, 2] == 0.0)


def test_grid_side():
    assert [grid_side(s) for s in (1, 2, 4, 5, 9, 16, 17)] == [1, 2, 2, 3, 3, 4, 5]
    with pytest.raises(ValueError):
        grid_side(0)


def test_pad_extends_like_bake_margin():
    img = np.zeros((9, 9, 3))
    cov = np.zeros((9, 9), bool)
    img[4, 4] = (1.0, 2.0, 3.0)
    cov[4, 4] = True
    out, done = pad(img, cov, margin=2)
    # A single texel grows into a 5x5 square of its own value, nothing further.
    assert np.array_equal(done, np.pad(np.ones((5, 5), bool), 2))
    np.testing.assert_array_equal(out[done], np.tile([1.0, 2.0, 3.0], (25, 1)))
    assert np.all(out[~done] == 0)
    # Two regions: a texel between them takes the mean of its covered neighbours.
    img = np.zeros((1, 3))
    cov = np.array([[True, False, True]])
    img[0, 0], img[0, 2] = 2.0, 6.0
    out, done = pad(img, cov, margin=1)
    assert out[0, 1] == 4.0 and done.all()
    # Uncovered values are ignored; margin 0 leaves the image alone but zeroes them.
    out, done = pad(np.full((2, 2), 7.0), np.array([[True, False], [False, False]]), margin=0)
    assert out.tolist() == [[7.0, 0.0], [0.0, 0.0]]
    # Distances grow one ring per pass (8-neighbourhood): a corner seed reaches (k, k) after k passes.
    cov = np.zeros((6, 6), bool)
    cov[0, 0] = True
    _, done = pad(np.ones((6, 6)), cov, margin=3)
    assert done[3, 3] and not done[4, 0] and done[3, 0]


def _pad_by_definition(img, cov, margin):
    """pad's rule written plainly: each pass, every uncovered texel touching a texel done
    before the pass (8-neighbourhood) takes their mean."""
    img = np.where(cov[:, :, None], img, 0.0)
    done = cov.copy()
    H, W = cov.shape
    for _ in range(margin):
        out, new = img.copy(), done.copy()
        for j in range(H):
            for i in range(W):
                if not done[j, i]:
                    near = [(jj, ii) for jj in range(j - 1, j + 2) for ii in range(i - 1, i + 2)
                            if 0 <= jj < H and 0 <= ii < W and done[jj, ii]]
                    if near:
                        acc = np.zeros(img.shape[2])
                        for jj, ii in near:
                            acc += img[jj, ii]
                        out[j, i], new[j, i] = acc / len(near), True
        img, done = out, new
    return img, done


def test_pad_reads_only_the_texels_done_before_each_pass():
    out, done = pad(np.array([[2.0, 0.0, 0.0, 6.0]]), np.array([[True, False, False, True]]), margin=1)
    assert out.tolist() == [[2.0, 2.0, 6.0, 6.0]] and done.all()  # not 2, 4 (a pass reading its own results)
    rng = np.random.default_rng(5)
    for _ in range(12):
        H, W = rng.integers(1, 14, 2)
        img = rng.random((H, W, 3))
        cov = rng.random((H, W)) < rng.uniform(0.02, 0.6)
        margin = int(rng.integers(0, 6))
        got, got_done = pad(img, cov, margin)
        want, want_done = _pad_by_definition(img, cov, margin)
        assert np.array_equal(got_done, want_done)
        np.testing.assert_array_equal(got, want)  # the same sums in the same order


def test_texel_irradiance_is_sample_means_plus_flux_over_area():
    rng = np.random.default_rng(9)
    n = 3 * TEXEL_BLOCK + 17  # blocks and a partial one
    cover = rng.integers(0, 5, n)
    sums = rng.random((n, 3)) * cover[:, None]
    flux = rng.random((n, 3))
    area = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(1e-4, 1e-2, n))
    covered = cover > 0
    want = np.zeros((n, 3))
    want[covered] = sums[covered] / cover[covered, None]
    ok = covered & (area > 0)
    want[ok] += flux[ok] / area[ok, None]
    img, stats = texel_irradiance(sums, cover, flux, area)
    np.testing.assert_array_equal(img, want)
    assert stats["texels_covered"] == covered.sum()
    assert stats["texels_touched"] == np.count_nonzero((want > 0).any(axis=1))
    assert stats["max_irradiance"] == want.max()
    assert stats["mean_irradiance_covered"] == pytest.approx(want[covered].mean(), rel=1e-13)
    img, stats = texel_irradiance(sums, cover)  # no flux estimator: the sample means alone
    np.testing.assert_array_equal(img[covered], sums[covered] / cover[covered, None])
    assert not img[~covered].any() and stats["max_irradiance"] == img.max()
    flux[7] = np.nan
    cover[7], area[7] = 1, 1.0
    assert np.isnan(texel_irradiance(sums, cover, flux, area)[1]["max_irradiance"])  # as ndarray.max
    assert texel_irradiance(np.zeros((0, 3)), np.zeros(0, np.int64))[1] == {
        "texels_covered": 0, "texels_touched": 0, "max_irradiance": 0.0, "mean_irradiance_covered": 0.0}
