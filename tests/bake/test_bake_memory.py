"""The memory budget (addon/bake/memory.py): a bake whose textures do not fit says so in one
line before it starts, and a MemoryError during a bake is one line naming the step."""

import os

import pytest

from addon.bake import memory, pipeline
from addon.bake.memory import BakeMemoryError, texel_bytes
from addon.bake.pipeline import BakeSettings, bake, bake_steps
from addon.bake.scene import SceneError

from fixtures.bake_scenes import glass_sphere_scene, mirror_scene


def test_a_bake_that_does_not_fit_stops_before_it_starts():
    sc, _ = mirror_scene(resolution=8)
    settings = BakeSettings(resolution=16384, memory_budget=1e9)
    need = texel_bytes([(16384, 16384)], settings.band_samples, 1)
    assert need > 1e9
    with pytest.raises(BakeMemoryError) as err:
        bake_steps(sc, settings)
    assert isinstance(err.value, SceneError)  # reported like every other bad input: one line
    assert str(err.value) == (f"the bake needs about {need / 1e9:.1f} GB for its textures (1 receiver(s), up to 16384 x "
                              "16384 texels), more than its memory budget of 1.0 GB; lower the resolution or raise "
                              "the memory budget")
    bake_steps(sc, BakeSettings(resolution=8, memory_budget=1e9)).close()  # small: fine


def test_a_scene_too_large_for_the_budget_stops_before_it_starts():
    sc = glass_sphere_scene(resolution=8, segments=64, rings=32)
    n = int(sc.n_triangles)
    textures = texel_bytes([(8, 8)], BakeSettings().band_samples, 1)
    scene_need = n * memory.BYTES_PER_TRIANGLE
    with pytest.raises(BakeMemoryError) as err:
        bake_steps(sc, BakeSettings(resolution=8, memory_budget=textures + 0.5 * scene_need))
    assert str(err.value).startswith(f"the bake needs about {(textures + scene_need) / 1e9:.1f} GB ({n:,} triangles and "
                                     "the textures), more than its memory budget of ")
    bake_steps(sc, BakeSettings(resolution=8, memory_budget=textures + 2.0 * scene_need)).close()  # fits


def test_the_default_budget_is_a_share_of_the_free_memory(monkeypatch):
    monkeypatch.setattr(memory, "available_memory", lambda: 4e9)
    assert memory.budget(BakeSettings()) == pytest.approx(memory.MEMORY_FRACTION * 4e9)
    assert memory.budget(BakeSettings(memory_budget=3e9)) == 3e9
    sc, _ = mirror_scene(resolution=8)
    with pytest.raises(BakeMemoryError, match="more than its memory budget of 2.0 GB"):
        bake_steps(sc, BakeSettings(resolution=16384))


def test_a_memory_error_during_the_bake_is_one_line_naming_the_step(monkeypatch):
    sc, _ = mirror_scene(resolution=8)
    real = pipeline.pad

    def pad(*a, **kw):
        raise MemoryError()

    monkeypatch.setattr(pipeline, "pad", pad)
    monkeypatch.setattr(pipeline, "_AREA_CACHE", {})  # the areas are computed (a step), not kept from an earlier test
    steps = bake_steps(sc, BakeSettings(resolution=8, samples=1))
    last = None
    with pytest.raises(BakeMemoryError) as err:
        for _, message in steps:
            last = message
    assert last.split(" (about ")[0] == "floor: texel areas, rows 8/8"  # the time left may follow
    assert str(err.value) == ("out of memory while floor: texel areas, rows 8/8; lower the resolution, the samples or "
                              "the image depth, or close other programs")
    monkeypatch.setattr(pipeline, "pad", real)
    assert bake(sc, BakeSettings(resolution=8, samples=1)).images["floor"].shape == (8, 8, 3)


@pytest.mark.bpy
def test_cli_memory_budget_is_one_line_rc2(tmp_path, capsys):
    pytest.importorskip("bpy")
    from addon.__main__ import main

    blend = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                         "sample_blends", "mirror_plane.blend")
    assert main(["bake", blend, "--out", str(tmp_path / "o"), "--resolution", "4096", "--memory-budget", "0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: the bake needs about ") and err[0].endswith(
        "more than its memory budget of 0.5 GB; lower the resolution or raise the memory budget")
    assert not (tmp_path / "o").exists()
