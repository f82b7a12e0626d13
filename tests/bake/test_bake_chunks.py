"""The forward-flux estimator refines and splats its first casters in chunks
(addon/bake/estimators/forward_flux.py, forward_images.image_chunks): memory and the time
between progress steps follow the chunk.  A caster's sub-triangles do not depend on the other
casters, so any cut gives the same sub-triangles and the same texture up to the order of the
flux sums."""

import numpy as np
import pytest

from addon.bake.estimators import forward_flux
from addon.bake.estimators.forward_images import caster_chunks
from addon.bake.pipeline import BakeSettings, bake

from fixtures.bake_scenes import glass_sphere_scene


def test_caster_chunks_cut_by_work_and_count():
    work = [1, 1, 1, 5, 1, 1, 1, 1]
    assert caster_chunks(work, 3, 2) == [(0, 2), (2, 3), (3, 4), (4, 5), (5, 7), (7, 8)]
    assert caster_chunks(work, 100, 100) == [(0, 8)]
    assert caster_chunks([], 3, 2) == []
    rng = np.random.default_rng(4)
    w = rng.uniform(0.0, 50.0, 1000)
    runs = caster_chunks(w, 400.0, 16)
    assert runs[0][0] == 0 and runs[-1][1] == 1000 and all(a[1] == b[0] for a, b in zip(runs, runs[1:]))
    assert all(0 < b - a <= 16 for a, b in runs)
    # a run holds the casters whose work starts in one max_work slice of the running total
    start = np.cumsum(w) - w
    for a, b in runs:
        assert np.unique(np.floor(start[a:b] / 400.0)).size == 1


@pytest.mark.parametrize("chunk", [1, 37])
def test_chunked_bake_equals_one_chunk(monkeypatch, chunk):
    sc = glass_sphere_scene(resolution=48, segments=16, rings=8)
    settings = BakeSettings(resolution=48, samples=1)
    monkeypatch.setattr(forward_flux, "CASTER_CHUNK", 10 ** 9)
    monkeypatch.setattr(forward_flux, "CHUNK_WORK", 1e18)
    whole = bake(sc, settings)
    monkeypatch.setattr(forward_flux, "CASTER_CHUNK", chunk)
    cut = bake(sc, settings)
    passes_whole = whole.report["estimators"]["forward-flux"]["passes"]
    passes_cut = cut.report["estimators"]["forward-flux"]["passes"]
    assert [p["chunks"] for p in passes_whole] == [1] * len(passes_whole)
    for pw, pc in zip(passes_whole, passes_cut):
        assert pc["chunks"] == -(-pw["emitters"] // chunk) > 1
        for key in ("emitters", "sub_triangles", "points_traced", "dropped", "partial", "border", "final_per_depth"):
            assert pc[key] == pw[key], key
    a, b = whole.raw["floor"], cut.raw["floor"]
    assert a.max() > 0
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * a.max())
    assert np.array_equal(bake(sc, settings).raw["floor"], b)  # the same cut, the same bits
