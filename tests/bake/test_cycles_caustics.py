"""Cycles' own shadow caustics (MNEE, bench/cycles_bake.py) against our photon bake.

The chart's "cycles" method is only meaningful if its numbers are in our units and texel
layout; these tests pin both down on the sample scenes, at 32² and a few seconds of Cycles:

- glass_slab (chain TT; the light is off-centre, so a flipped or transposed image fails):
  pi x Cycles' bake without the caustic equals our direct-light bake texel by texel (units of
  the DIFFUSE pass), the subtraction leaves nothing negative and nothing outside the slab's
  caustic, and inside the caustic, away from its border and from the disc around the light's
  nadir where Cycles' Newton walk fails, Cycles' caustic equals our photon bake's.
  Measured at 48², 1024 spp, 8M photons: interior ratio 1.0002 (per texel 5-95 %:
  0.9987-1.0017); the whole floor 0.916 (the nadir hole and the border shift).  Here (32²,
  64 spp, 2M photons): interior 1.0003, direct-light median 1.0003.
- water_pool (chain T into water, a point light and a sun): Cycles' raw caustic is the
  physical one / 1.33² (Cycles keeps radiance in "air units" across a refraction), and
  baked one light at a time (Cycles' MNEE over-weights a sun among several lights) and
  converted it matches our photon bake's energy.  Measured at 48², 256 spp: 0.982 (the rest
  is light MNEE cannot seed: see bench/cycles_bake.py).
"""

import math
import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from addon.bake.pipeline import BakeSettings, bake  # noqa: E402
from addon.bake.extract import extract_scene, open_blend  # noqa: E402
from cycles_bake import CyclesCaustics  # noqa: E402

RES = 32


def _open(name):
    open_blend(os.path.join(ROOT, "sample_blends", name + ".blend"))
    return extract_scene(resolution=RES)


def _texel_centres(half=2.0):
    x = (np.arange(RES) + 0.5) / RES * 2 * half - half
    return np.meshgrid(x, x)  # X[j, i], Y[j, i]: row j is v (y), column i is u (x)


def _interior(lit):
    inner = lit.copy()
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            inner &= np.roll(np.roll(lit, dj, 0), di, 1)
    return inner


def test_glass_slab_units_layout_and_caustic_match_photons():
    model = _open("glass_slab")
    light = model.lights[0]
    direct = bake(model, BakeSettings(resolution=RES, samples=16, margin=0, caustics=False, direct=True)).raw["Floor"]
    photon = bake(model, BakeSettings(resolution=RES, bounces=2, margin=0, method="photon", photons=2_000_000, seed=4,
                                       chains=("TT",))).raw["Floor"]
    cc = CyclesCaustics(model, RES)
    images, seconds, parts = cc.bake(64, seed=2)
    cyc = images["Floor"]
    assert cc.casters == ["GlassSlab"] and cc.ior == 1.0 and not cc.per_light
    assert any("split along sharp edges" in n and "by 0.0e+00" in n for n in cc.notes)

    # Units and layout: the bake with the casters off is the direct light (the slab's shadow black).
    off = math.pi * parts["off"][0]["Floor"]
    lit = _interior(direct.sum(-1) > 0.05 * direct.sum(-1).max())  # not at the shadow's edge
    ratio = off[lit] / direct[lit]
    assert abs(np.median(ratio) - 1.0) <= 0.005, np.median(ratio)
    assert np.percentile(np.abs(ratio - 1.0), 95) <= 0.02
    assert abs(off[lit].sum() / direct[lit].sum() - 1.0) <= 0.005

    # The subtraction is clean: nothing negative, nothing where neither the slab's shadow nor
    # the photon caustic is (the direct light cancelled exactly).
    assert cyc.min() >= -1e-6 * cyc.max()
    shadow = direct.sum(-1) < 1e-9
    near = _interior(~(shadow | (photon.sum(-1) > 0)))  # well away from both
    assert near.sum() > 0.5 * near.size
    assert cyc[near].sum() <= 1e-3 * cyc.sum()

    # The caustic itself, inside (photon-lit texels whose 8 neighbours are lit too) and more
    # than 0.35 m from the light's nadir.
    X, Y = _texel_centres()
    r = np.hypot(X - light.position[0], Y - light.position[1])
    inner = _interior(photon.sum(-1) > 0) & (r > 0.35)
    assert inner.sum() > 100
    assert abs(cyc[inner].sum() / photon[inner].sum() - 1.0) <= 0.03
    per_texel = cyc[inner][:, 0] / photon[inner][:, 0]
    assert np.all(np.abs(np.percentile(per_texel, [5, 95]) - 1.0) <= 0.08), np.percentile(per_texel, [5, 95])
    # ... and Cycles' hole under the light: well under the photon caustic there.
    hole = (r < 0.12) & (photon.sum(-1) > 0)
    assert hole.any() and cyc[hole].sum() < 0.5 * photon[hole].sum()
    assert seconds > 0


def test_water_pool_medium_units_and_sun_weight():
    model = _open("water_pool")
    photon = bake(model, BakeSettings(resolution=RES, margin=0, method="photon", photons=2_000_000, seed=4)).raw["PoolFloor"]
    cc = CyclesCaustics(model, RES)
    assert cc.casters == ["Water"] and cc.per_light and abs(cc.ior - 1.33) < 1e-6
    images, seconds, parts = cc.bake(32, seed=2)
    cyc = images["PoolFloor"]
    assert len(parts["on"]) == 2  # one light at a time
    ratio = cyc.sum() / photon.sum()
    assert abs(ratio - 0.98) <= 0.03, ratio  # measured 0.9825 (48², 256 spp)
    raw = sum(math.pi * (on["PoolFloor"] - off["PoolFloor"]).sum() for on, off in zip(parts["on"], parts["off"]))
    assert abs(raw / photon.sum() * 1.33 ** 2 - ratio) <= 1e-6 * ratio  # the conversion is exactly eta²
