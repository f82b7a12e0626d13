"""The forward-flux splat on OpenCL (addon/solver/opencl/splat.cl, PoCL on the CPU in CI) against
the Numba splat it ports (addon/solver/estimators/splat.py): the same texture bit for bit, for
triangles of every kind a bake splats (large, sub-texel, slivers, degenerate points, partly
off the texture, zero flux, linear densities), with and without a flat receiver's region, added
over several calls; and the flux it deposits is the flux sent (conservation, independent of
either splat)."""

import numpy as np
import pytest

from addon.solver.estimators.splat import splat_triangles
from fixtures.opencl import opencl_device_or_skip


def _triangles(rng, m):
    tri = rng.uniform(-0.1, 1.1, (m, 3, 2))
    k = m // 5
    tri[:k] = tri[:k] * 0.02 + rng.uniform(0.1, 0.9, (k, 1, 2))  # within a texel or a few
    tri[k:k + 10, 2] = tri[k:k + 10, 0] + 1e-3 * (tri[k:k + 10, 1] - tri[k:k + 10, 0])  # slivers
    tri[k + 10:k + 20] = tri[k + 10:k + 20, :1]  # points: deposited at their texel
    flux = rng.uniform(0.1, 2.0, (m, 3))
    flux[k + 20:k + 30] = 0.0
    density = rng.uniform(0.2, 3.0, (m, 3))
    return tri, flux, density


@pytest.mark.opencl
@pytest.mark.parametrize("gpu", [False, True])
@pytest.mark.parametrize("shape", [(37, 29), (64, 64), (5, 300)])
def test_device_splat_is_numbas_bit_for_bit(shape, gpu, monkeypatch):
    """gpu: the device taken for a GPU (a band per row, small work-groups): the same bits."""
    from addon.solver.opencl import backend
    from addon.solver.opencl.splatting import OpenCLSplat

    index = opencl_device_or_skip()
    if gpu:
        monkeypatch.setattr(backend._context(index), "is_cpu", False)
    W, H = shape
    rng = np.random.default_rng(W * H)
    region = np.array([[1.0, 0.0, -0.05], [-1.0, -1.0, 1.6], [0.0, 1.0, 0.02]])  # u >= 0.05, u + v <= 1.6, v >= -0.02
    target = OpenCLSplat(index, [(W, H), (W, H)])
    host = [np.zeros((W * H, 3)), np.zeros((W * H, 3))]
    for call in range(3):
        tri, flux, density = _triangles(rng, 400)
        r = call % 2
        reg = region if r == 1 else None
        splat_triangles(tri, flux, W, H, host[r], density, region=reg)
        target.add(r, tri, flux, density, region=reg)
    got = target.arrays()
    for a, b in zip(host, got):
        assert a.max() > 0
        np.testing.assert_array_equal(b, a)


@pytest.mark.opencl
def test_device_splat_conserves_flux():
    """Triangles inside the texture deposit all their flux, whatever the density."""
    from addon.solver.opencl.splatting import OpenCLSplat

    index = opencl_device_or_skip()
    rng = np.random.default_rng(3)
    tri = rng.uniform(0.0, 1.0, (500, 3, 2))
    flux = rng.uniform(0.1, 2.0, (500, 3))
    target = OpenCLSplat(index, [(48, 40)])
    target.add(0, tri, flux, rng.uniform(0.2, 3.0, (500, 3)))
    out = target.arrays()[0]
    np.testing.assert_allclose(out.sum(axis=0), flux.sum(axis=0), rtol=1e-12)
