"""Light samples (addon/bake/lights.py) and the direct light they give."""

import math

import numpy as np
import pytest

from addon.bake.pipeline import BakeSettings, bake
from addon.bake.lights import emission_factor, sample_light, spot_factor
from addon.bake.raster import rasterise
from addon.bake.scene import Light, build_scene

from fixtures.bake_scenes import floor


def test_spot_factor_is_cycles_smoothstep():
    half = math.radians(30)
    blend = 0.4
    c0 = math.cos(half)
    smooth = 1.0 / ((1 - c0) * blend)
    assert spot_factor(c0, c0, smooth) == 0.0 and spot_factor(c0 - 1e-6, c0, smooth) == 0.0
    assert spot_factor(c0 + (1 - c0) * blend, c0, smooth) == 1.0 and spot_factor(1.0, c0, smooth) == 1.0
    assert spot_factor(c0 + 0.5 * (1 - c0) * blend, c0, smooth) == pytest.approx(0.5, abs=1e-12)
    assert spot_factor(c0 + 0.25 * (1 - c0) * blend, c0, smooth) == pytest.approx(0.25**2 * (3 - 0.5), abs=1e-12)
    assert spot_factor(c0 + 1e-9, c0, math.inf) == 1.0  # blend 0: a hard edge


def test_sphere_light_samples_add_up_to_the_point_light_far_away():
    light = Light("P", "point", (1.0, 0.5, 0.25), 10.0, position=(0, 0, 0), radius=0.3)
    ls = sample_light(light, 400, seed=1)
    assert ls.size == 400
    np.testing.assert_allclose(np.linalg.norm(ls.position, axis=1), 0.3, rtol=1e-12)
    rng = np.random.default_rng(0)
    for w in rng.normal(size=(20, 3)):
        w /= np.linalg.norm(w)
        f = emission_factor(ls, np.arange(400), np.tile(w, (400, 1)))
        total = (ls.rgb * f[:, None]).sum(0)
        np.testing.assert_allclose(total, 10.0 * np.array([1.0, 0.5, 0.25]), rtol=0.02)
    one = sample_light(light, 1)
    assert one.size == 1 and np.allclose(one.rgb, 10.0 * np.array([1.0, 0.5, 0.25])) and not one.lobe.any()


def test_sun_disc_and_area_samples():
    d = np.array([0.2, -0.1, -1.0])
    sun = sample_light(Light("S", "sun", (1, 1, 1), 3.0, direction=d, angle=math.radians(2.0)), 64, seed=2)
    np.testing.assert_allclose(sun.rgb.sum(0), 3.0)
    ang = np.arccos(np.clip(sun.direction @ (d / np.linalg.norm(d)), -1, 1))
    assert ang.max() <= math.radians(1.0) + 1e-12 and ang.max() > math.radians(0.8)
    area = sample_light(Light("A", "area", (1, 1, 1), 5.0, position=(1, 2, 3), direction=(0, 0, -1), size_u=0.4, size_v=0.2), 50)
    np.testing.assert_allclose(area.rgb.sum(0), 5.0)
    local = area.position - [1, 2, 3]
    assert np.all(np.abs(local[:, 0]) <= 0.2) and np.all(np.abs(local[:, 1]) <= 0.1) and np.allclose(local[:, 2], 0)
    assert np.allclose(area.lobe, [0, 0, -1])


def test_sphere_light_near_the_floor_gives_the_point_light_irradiance():
    """A uniformly bright sphere wholly above a plane lights it exactly like a point light at
    its centre (E = I cos / d²): the sampled sphere (1024 samples) must agree within 1.5 %."""
    intensity, centre = 5.0, np.array([0.2, -0.1, 0.6])
    point = Light("P", "point", (1, 1, 1), intensity, position=centre)
    sphere = Light("P", "point", (1, 1, 1), intensity, position=centre, radius=0.3)
    sc = build_scene([floor(half=1.0, resolution=16)], [sphere])
    res = bake(sc, BakeSettings(samples=1, caustics=False, direct=True, light_samples=1024, margin=0, jitter=False))
    band = rasterise(sc, sc.receivers[0], 1)
    d = band.position - centre
    E = intensity * np.abs(d[:, 2]) / np.linalg.norm(d, axis=1) ** 3
    ref = np.zeros(256)
    ref[band.texel] = E
    got = res.raw["floor"][:, :, 0].reshape(-1)
    np.testing.assert_allclose(got, ref, rtol=0.015)
    assert abs(got.sum() / ref.sum() - 1) < 2e-3
    # And with one light sample the radius is ignored: exactly the point light.
    sc.lights = [point]
    res1 = bake(sc, BakeSettings(samples=1, caustics=False, direct=True, margin=0, jitter=False))
    np.testing.assert_allclose(res1.raw["floor"][:, :, 0].reshape(-1), ref, rtol=1e-12)
