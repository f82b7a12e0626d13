"""Progress that tells the truth (addon/bake/pipeline.py ``Progress``): the fraction follows the
stages' own counts (probes, forward images, texel rows, texel areas, padding) and reaches 1 only
at the end; the time left is estimated from the time taken so far."""

import pytest

from addon.bake import pipeline
from addon.bake.pipeline import BakeSettings, Progress, bake_steps, format_seconds

from fixtures.bake_scenes import glass_sphere_scene


def test_the_fraction_follows_the_stages_and_reaches_one_only_at_the_end():
    sc = glass_sphere_scene(resolution=32)
    steps = bake_steps(sc, BakeSettings(resolution=32, samples=1, band_samples=256))
    yielded = []
    while True:
        try:
            yielded.append(next(steps))
        except StopIteration:
            break
    fractions = [f for f, _ in yielded]
    messages = [m for _, m in yielded]
    assert all(f is not None for f in fractions) and fractions == sorted(fractions)
    assert fractions[-1] == pytest.approx(1.0) and messages[-1].startswith("floor: padded")
    assert all(f < 0.999 for f in fractions[:-1])
    probes = [f for f, m in yielded if m.startswith("planning: probe")]
    assert len(probes) >= 2 and max(probes) <= 0.05 + 1e-9  # one step per probe; planning is the first 5 %
    images = [f for f, m in yielded if "forward images" in m]
    assert len(images) >= 2 and images[0] < images[-1] <= 0.75  # the forward images: one step each
    rows = [f for f, m in yielded if ": rows " in m]
    areas = [f for f, m in yielded if "texel areas" in m]
    assert len(rows) >= 4 and len(areas) >= 4  # banded: 32 rows x 32 texels / 256 samples per band
    assert rows[-1] < areas[0] <= areas[-1] < 1.0  # the texel areas come after the rows and before the end


def test_time_left_is_estimated_from_the_time_taken(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(pipeline.time, "perf_counter", lambda: clock[0])
    p = Progress()
    p.set_weights(prepare=0.0, rows=1.0, areas=0.0, pad=0.0)
    assert p.tell("plan", 1.0, "planning") == (pytest.approx(0.05), "planning")  # no estimate at once
    clock[0] += 10.0
    f, message = p.tell("rows", 0.5, "floor: rows 16/32")
    assert f == pytest.approx(0.05 + 0.95 * 0.5)
    left = 10.0 * (1 - f) / f
    assert message == f"floor: rows 16/32 (about {format_seconds(left)} left)"
    assert format_seconds(42.4) == "42 s" and format_seconds(185) == "3 min 5 s" and format_seconds(7620) == "2 h 7 min"
    clock[0] += 1.0
    assert p.tell("rows", 0.25, "back")[0] == pytest.approx(f)  # never goes back
