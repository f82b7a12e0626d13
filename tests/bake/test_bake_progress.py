"""Progress that tells the truth (addon/bake/pipeline.py ``Progress``): one step per probe,
forward image and band of rows or texel areas; the fraction is the time done over the time done
and left (each stage extrapolated from its own count of work), never goes back and reaches 1
only at the end, and the message gives the time left."""

import re

import pytest

from addon.bake import pipeline
from addon.bake.pipeline import BakeSettings, Progress, bake_steps, format_seconds

from fixtures.bake_scenes import glass_sphere_scene


def test_the_fraction_follows_the_stages_and_reaches_one_only_at_the_end():
    sc = glass_sphere_scene(resolution=16)
    steps = bake_steps(sc, BakeSettings(resolution=16, samples=1, band_samples=64))
    yielded = []
    while True:
        try:
            yielded.append(next(steps))
        except StopIteration:
            break
    fractions = [f for f, _ in yielded]
    messages = [m for _, m in yielded]
    assert all(f is not None for f in fractions) and fractions == sorted(fractions)
    assert fractions[0] < 0.2 and fractions[-1] == 1.0 and messages[-1].startswith("floor: padded")
    assert all(f < 1.0 for f in fractions[:-1])  # 100 % only at the end
    assert len([m for m in messages if m.startswith("planning: probe")]) >= 2  # one step per probe
    images = [f for f, m in yielded if "forward images" in m]
    chunks = [re.search(r", casters (\d+)/(\d+)", m) for m in messages if "forward images" in m]
    chunks = [c.groups() for c in chunks if c]
    assert len(images) >= 2 and images[0] < 0.9  # a step before each forward image (far from done) ...
    assert chunks and chunks[-1][0] == chunks[-1][1]  # ... and after each chunk, the last with every caster done
    rows = [f for f, m in yielded if ": rows " in m]
    areas = [f for f, m in yielded if "texel areas" in m]
    assert len(rows) >= 4 and len(areas) >= 4  # banded: 16 rows x 16 texels / 64 samples per band
    assert rows[-1] <= areas[0] <= areas[-1] < 1.0  # the texel areas come after the rows and before the end


def test_the_fraction_is_time_done_over_time_done_and_left(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(pipeline.time, "perf_counter", lambda: clock[0])
    p = Progress()
    p.set_guesses(prepare=0.0, rows=10.0, areas=0.0, pad=0.0)
    p.set_guesses(pad=1.0)
    assert p.tell("plan", 0.0, "planning") == (0.0, "planning")
    clock[0] += 1.0
    f, message = p.tell("rows", 0.0, "floor: rows 0/32")
    assert p.speed() == 1.0 and p.left == pytest.approx(11.0)  # the guesses, planning done
    assert f == pytest.approx(1.0 / 12.0) and message == "floor: rows 0/32"  # no estimate before 3 s
    clock[0] += 5.0  # a quarter of the rows in 5 s where 2.5 s were guessed: 15 s left, and padding 2 s
    f, message = p.tell("rows", 0.25, "floor: rows 8/32")
    assert p.speed() == pytest.approx(2.0)
    assert f == pytest.approx(6.0 / 23.0) and message == "floor: rows 8/32 (about 17 s left)"
    p.set_guesses(pad=100.0)  # more work found: the fraction stays, it never goes back
    assert p.tell("rows", 0.25, "floor: rows 8/32")[0] == pytest.approx(f) and p.left == pytest.approx(215.0)
    p.set_guesses(pad=0.0)
    clock[0] += 15.0
    f, message = p.tell("rows", 1.0, "floor: rows 32/32")
    assert f == pytest.approx(0.999) and message == "floor: rows 32/32 (about 0 s left)"
    assert p.tell("pad", 1.0, "floor: padded") == (1.0, "floor: padded")
    assert format_seconds(42.4) == "42 s" and format_seconds(185) == "3 min 5 s" and format_seconds(7620) == "2 h 7 min"
