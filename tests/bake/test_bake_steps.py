"""The resumable bake (pipeline.bake_steps) that the Blender operator drives from a timer."""

import numpy as np
import pytest

from addon.bake.pipeline import BakeCancelled, BakeSettings, bake, bake_steps
from addon.bake.scene import SceneError

from fixtures.bake_scenes import mirror_scene

SETTINGS = dict(samples=4, seed=3, margin=2, batch_tuples=4096, band_samples=1024, one_bounce="points")  # banded tuple steps


def _drain(steps):
    yielded = []
    while True:
        try:
            yielded.append(next(steps))
        except StopIteration as done:
            return yielded, done.value


def test_steps_give_bit_identical_results_and_monotone_progress():
    sc, _ = mirror_scene(resolution=32)
    ref = bake(sc, BakeSettings(**SETTINGS))
    yielded, result = _drain(bake_steps(sc, BakeSettings(**SETTINGS)))
    assert set(result.images) == set(ref.images) == {"floor"}
    np.testing.assert_array_equal(result.images["floor"], ref.images["floor"])
    np.testing.assert_array_equal(result.raw["floor"], ref.raw["floor"])
    assert result.report["counts"] == ref.report["counts"]
    assert ref.report["counts"]["paths_visible"] > 0
    # Bounded chunks: several bands (32 rows x 4 samples x 32 texels / 1024 samples per band).
    fractions = [f for f, _ in yielded if f is not None]
    assert len(fractions) >= 4
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    assert all(isinstance(m, str) and m for _, m in yielded)


def test_progress_false_cancels_and_close_abandons():
    sc, _ = mirror_scene(resolution=32)
    calls = []

    def progress(fraction, message):
        calls.append((fraction, message))
        return len(calls) < 3

    with pytest.raises(BakeCancelled):
        bake(sc, BakeSettings(**SETTINGS), progress)
    assert len(calls) == 3
    steps = bake_steps(sc, BakeSettings(**SETTINGS))
    next(steps)
    steps.close()
    with pytest.raises(StopIteration):
        next(steps)


def test_bad_settings_and_scenes_fail_before_the_first_step():
    sc, _ = mirror_scene(resolution=8)
    with pytest.raises(SceneError, match="bounces"):
        bake_steps(sc, BakeSettings(bounces=3))
    sc.receivers = []
    with pytest.raises(SceneError, match="no receivers"):
        bake_steps(sc, BakeSettings())
