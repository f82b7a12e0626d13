"""The up-front estimate (addon/bake/estimate.py) and the confirmation of a very large bake:
the estimate counts the scene's texels, supersamples and one-bounce first casters as the
pipeline and the planner do; the CLI asks (or stops with one line) before a bake estimated
over CONFIRM_SECONDS unless --yes, writing nothing; the operator shows a confirmation dialog
first and starts nothing until it is answered."""

import os

import numpy as np
import pytest

from addon.bake import estimate
from addon.bake.estimate import estimate_bake, needs_confirmation
from addon.bake.memory import BYTES_PER_TRIANGLE, texel_bytes
from addon.bake.pipeline import AREA_SAMPLES, BakeSettings
from addon.bake.plan import CHAIN_ROLES
from addon.bake.raster import grid_side

from fixtures.bake_scenes import glass_sphere_scene, wavy_sheet

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")


def test_the_estimate_counts_texels_supersamples_and_first_casters():
    sheet = wavy_sheet(1, 64, n=40)  # 3,200 water triangles over a floor: T is the only one-bounce chain
    e = estimate_bake(sheet, BakeSettings(resolution=256, samples=9))
    texels = 256 * 256
    assert e.texels == texels and e.casters == 3200
    supersamples = texels * (grid_side(9) ** 2 + grid_side(max(9, AREA_SAMPLES)) ** 2)
    assert e.seconds - e.forward_seconds == pytest.approx(supersamples * estimate.SUPERSAMPLE_SECONDS)
    assert e.forward_seconds == pytest.approx(3200 * estimate.CASTER_SECONDS + texels * estimate.TEXEL_SECONDS)
    assert e.memory == texel_bytes([(256, 256)], BakeSettings().band_samples, 1) + sheet.n_triangles * BYTES_PER_TRIANGLE
    # a closed glass sphere: its single refraction ends inside (the planner leaves T out), R remains
    sphere = glass_sphere_scene(resolution=64, segments=16, rings=8)
    casters = int(np.isin(sphere.tri_role, CHAIN_ROLES["R"]).sum())
    assert casters > 0
    assert estimate_bake(sphere, BakeSettings(resolution=64)).casters == casters
    assert estimate_bake(sphere, BakeSettings(resolution=64, chains=("T",))).casters == 0
    # the per-frame estimate of a range
    ten = e.times(10)
    assert ten.seconds == pytest.approx(10 * e.seconds) and ten.memory == e.memory


def test_only_very_large_bakes_ask():
    sphere = glass_sphere_scene(resolution=64, segments=16, rings=8)
    small = estimate_bake(sphere, BakeSettings(resolution=1024))
    huge = estimate_bake(sphere, BakeSettings(resolution=16384))
    assert not needs_confirmation(small) and needs_confirmation(huge)
    assert huge.texels == 16384 ** 2 and huge.seconds > 256 * small.seconds * 0.9
    assert huge.line().startswith("at least about ") and " min" in huge.line() and "GB of memory" in huge.line()


@pytest.mark.bpy
def test_cli_asks_before_a_very_large_bake(tmp_path, capsys, monkeypatch):
    pytest.importorskip("bpy")
    from addon.__main__ import main

    blend = os.path.join(SAMPLES, "mirror_plane.blend")
    monkeypatch.setattr(estimate, "CONFIRM_SECONDS", 0.0)  # every bake is "very large"
    out = tmp_path / "out"
    assert main(["bake", blend, "--out", str(out), "--resolution", "16", "--samples", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: the bake needs at least about ") and err[0].endswith("pass --yes to bake it")
    assert "256 texels" in err[0]
    assert not out.exists() or not os.listdir(out)  # nothing written
    assert main(["bake", blend, "--out", str(out), "--resolution", "16", "--samples", "1", "--yes"]) == 0
    assert (out / "Floor.exr").exists()
    # a frame range asks once, for all its frames
    seq = tmp_path / "seq"
    assert main(["bake", os.path.join(SAMPLES, "water_pool.blend"), "--out", str(seq), "--resolution", "8", "--samples",
                 "1", "--frames", "1:3"]) == 2
    assert "pass --yes" in capsys.readouterr().err and not (seq.exists() and any(n.endswith(".exr") for n in os.listdir(seq)))
