"""The forward-flux estimator refines and splats its first casters in chunks
(addon/bake/estimators/forward_flux.py, forward_images.image_chunks): memory and the time
between progress steps follow the chunk.  A caster's sub-triangles do not depend on the other
casters and are splatted in caster order, so any cut, fixed or sized by time
(forward_images.ChunkSizer), gives the same sub-triangles and the same texture bit for bit."""

import numpy as np
import pytest

from addon.bake.estimators import forward_flux
from addon.bake.estimators import forward_images
from addon.bake.estimators.forward_images import ChunkSizer, caster_chunks
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
    assert np.array_equal(b, a)  # splatted in caster order: the same bits whatever the cut


def test_time_sized_chunks_follow_the_measured_rate():
    assert forward_images.FIRST_STEP_CASTERS >= 5
    sizer = ChunkSizer(seconds=1.0, first_work=10.0)
    work = np.full(1000, 2.0)
    runs = sizer.runs(work, max_work=1e9, max_casters=10 ** 9)
    assert next(runs) == (0, 5)  # the first: first_work of work
    sizer.took(0.5)  # 10 units in 0.5 s: 20 units a second
    assert next(runs) == (5, 15)
    sizer.took(2.0)  # 20 units in 2 s: 10 a second
    assert next(runs) == (15, 20)
    sizer.took(0.01)  # fast: at most twice the last run's work (10 units)
    assert next(runs) == (20, 30)
    short = ChunkSizer(seconds=1.0, first_work=1e9).runs(work, max_work=30.0, max_casters=7)
    assert next(short) == (0, min(7, forward_images.FIRST_STEP_CASTERS))  # ... and at most max_work and max_casters


def test_time_sized_bake_equals_one_chunk(monkeypatch):
    sc = glass_sphere_scene(resolution=48, segments=16, rings=8)
    settings = BakeSettings(resolution=48, samples=1)
    monkeypatch.setattr(forward_flux, "CASTER_CHUNK", 10 ** 9)
    monkeypatch.setattr(forward_flux, "CHUNK_WORK", 1e18)
    whole = bake(sc, settings)
    settings.step_seconds = 1e-4  # runs of a few casters, their ends set by the clock
    monkeypatch.setattr(forward_images, "FIRST_STEP_WORK", 50.0)
    monkeypatch.setattr(forward_images, "REACH_STEP", 100)
    monkeypatch.setattr(forward_images, "MESH_STEP", 100)
    messages = []
    from addon.bake.pipeline import bake_steps
    steps = bake_steps(sc, settings)
    while True:
        try:
            messages.append(next(steps)[1])
        except StopIteration as done:
            timed = done.value
            break
    passes = timed.report["estimators"]["forward-flux"]["passes"]
    assert max(p["chunks"] for p in passes) > 5
    assert any("cone tests 100/" in msg for msg in messages) and any("mesh points 100/" in msg for msg in messages)
    for pw, pt in zip(whole.report["estimators"]["forward-flux"]["passes"], passes):
        for key in ("emitters", "sub_triangles", "points_traced", "dropped", "partial", "border", "final_per_depth"):
            assert pt[key] == pw[key], key
    assert np.array_equal(timed.raw["floor"], whole.raw["floor"])
