"""The forward-flux kernels (addon/solver/estimators/flux_kernel.py) against the numpy forms
they replace (forward_image.solid_angle, forward_image.corner_densities)."""

import numpy as np

from addon.solver.estimators.flux_kernel import corner_densities_kernel, subtriangle_geometry
from addon.solver.estimators.forward_image import corner_densities, solid_angle


def _case(seed=0, n=4000, emitters=50):
    rng = np.random.default_rng(seed)
    tri_p = rng.normal(size=(emitters + 7, 3, 3))
    t1_of = rng.permutation(emitters + 7)[:emitters].astype(np.int64)
    x0 = rng.normal(size=(emitters, 3)) + np.array([0.0, 0.0, 4.0])
    e = rng.integers(0, emitters, n).astype(np.int64)
    a = rng.random((n, 2)) * 0.8
    h = 0.05 + 0.1 * rng.random((n, 1))
    bary = np.stack([a, a + h * np.array([1.0, 0.0]), a + h * np.array([0.0, 1.0])], axis=1)
    # images: an affine map plus a small quadratic bend, some folds, slivers and NaN midpoints
    A = rng.normal(size=(n, 2, 2))
    uv = np.einsum("nij,nkj->nki", A, bary)
    mid = 0.5 * (bary + bary[:, [1, 2, 0]])
    mid_uv = np.einsum("nij,nkj->nki", A, mid) + 0.01 * rng.normal(size=(n, 3, 2)) * h[:, :, None]
    mid_uv[rng.random(n) < 0.05] = np.nan
    fold = rng.random(n) < 0.05
    mid_uv[fold] = uv[fold][:, [2, 0, 1]]
    factor = 0.5 + rng.random((n, 6))
    factor[rng.random(n) < 0.1] = np.nan
    return tri_p, t1_of, x0, e, bary, uv, mid_uv, factor


def test_geometry_kernel_matches_the_numpy_solid_angle_and_sun_area():
    tri_p, t1_of, x0, e, bary, *_ = _case()
    P = tri_p[t1_of[e]]
    corners = P[:, None, 0] + bary[:, :, :1] * (P[:, None, 1] - P[:, None, 0]) + bary[:, :, 1:] * (P[:, None, 2] - P[:, None, 0])
    x1 = np.empty((e.size, 3))
    power = np.empty(e.size)
    subtriangle_geometry(tri_p, t1_of, e, bary, x0, False, np.zeros(3), x1, power)
    np.testing.assert_allclose(x1, corners.mean(axis=1), rtol=0, atol=1e-14)
    np.testing.assert_allclose(power, solid_angle(x0[e], corners), rtol=1e-12, atol=0)
    d = np.array([0.2, -0.3, -0.9]) / np.linalg.norm([0.2, -0.3, -0.9])
    subtriangle_geometry(tri_p, t1_of, e, bary, x0, True, d, x1, power)
    g = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_allclose(power, 0.5 * np.abs(g @ d), rtol=1e-12, atol=0)


def test_density_kernel_matches_corner_densities():
    tri_p, t1_of, x0, e, bary, uv, mid_uv, factor = _case(1)
    P = tri_p[t1_of[e]]
    cf = np.nan_to_num(factor[:, :3], nan=1.0)
    ref = corner_densities(uv, mid_uv, x0[e], P, bary, cf)
    out = np.empty((e.size, 3))
    corner_densities_kernel(uv, mid_uv, tri_p, t1_of, e, bary, x0, False, np.zeros(3), 0.0, factor, out)
    uniform = np.all(ref == 1.0, axis=1)
    assert 0.05 < uniform.mean() < 0.95  # both kinds of rows are exercised
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=0)
    # sun: the light point far behind each sub-triangle's centroid
    d = np.array([0.1, 0.2, -1.0]) / np.linalg.norm([0.1, 0.2, -1.0])
    corners = P[:, None, 0] + bary[:, :, :1] * (P[:, None, 1] - P[:, None, 0]) + bary[:, :, 1:] * (P[:, None, 2] - P[:, None, 0])
    far = corners.mean(axis=1) - 1e6 * 3.0 * d
    ref = corner_densities(uv, mid_uv, far, P, bary, cf)
    corner_densities_kernel(uv, mid_uv, tri_p, t1_of, e, bary, x0, True, d, 1e6 * 3.0, factor, out)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=0)
