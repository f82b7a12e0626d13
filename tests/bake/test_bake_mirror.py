"""Mirror plane bake against the analytic image-source irradiance, texel by texel.

A texel's value is the mean of the irradiance at its covered supersamples, so the reference
is the same mean of the closed-form irradiance at the very same sample points (from
``rasterise`` with the bake's seed): like is compared with like, and the only differences
left are the solver's and the light's (the sun is a far point: error about 2 L / D).
"""

import numpy as np
import pytest

from addon.bake.pipeline import BakeSettings, bake
from addon.bake.raster import rasterise
from addon.bake.scene import ROLE_BOTH, Light
from addon.solver import fresnel_dielectric

from fixtures.bake_scenes import mirror_scene
from fixtures.checks import mirror_hit, point_reference, texel_mean

RES = 40
SETTINGS = BakeSettings(samples=4, seed=7, margin=0, one_bounce="points")  # exact paths at the samples


def _check(baked, ref, rtol=1e-3, min_cover=0.2):
    lit = ref > 0
    assert lit.sum() > min_cover * lit.size, "the caustic must cover a good part of the floor"
    rel = np.abs(baked[lit] - ref[lit]) / ref[lit]
    assert rel.max() <= rtol, rel.max()
    assert np.all(baked[~lit] == 0.0)
    return rel.max()


def test_point_light_mirror_matches_image_source_per_texel():
    sc, geo = mirror_scene(resolution=RES)
    res = bake(sc, SETTINGS)
    band = rasterise(sc, sc.receivers[0], SETTINGS.samples, SETTINGS.seed, SETTINGS.jitter)
    E, _, _ = point_reference(sc, geo, sc.lights[0], band)
    ref = texel_mean(band, E[:, None] * geo["tint"], RES)
    err = _check(res.raw["floor"], ref)
    assert err < 1e-9  # the solver is exact here; 1e-3 is the product requirement
    assert res.report["counts"]["texels_touched"] == int(np.count_nonzero(ref[:, :, 0]))
    # Padding does not change covered texels; the float32 image is the same numbers.
    np.testing.assert_allclose(res.images["floor"], ref, rtol=1e-6)


def test_spot_light_blend_follows_cycles_smoothstep():
    sc, geo = mirror_scene(resolution=RES)
    d = np.array([-0.05, -0.1, 1.0])
    sc.lights[0] = Light("Spot", "spot", (0.5, 1.0, 2.0), 25.0, position=(0.4, 0.3, 1.0), direction=d, spot_size=np.radians(70), spot_blend=0.4)
    res = bake(sc, SETTINGS)
    band = rasterise(sc, sc.receivers[0], SETTINGS.samples, SETTINGS.seed, SETTINGS.jitter)
    E, _, _ = point_reference(sc, geo, sc.lights[0], band)
    ref = texel_mean(band, E[:, None] * geo["tint"] * [0.5, 1.0, 2.0], RES)
    _check(res.raw["floor"], ref)
    # The blend zone is really exercised: some texels are partly faded.
    full = point_reference(sc, geo, Light("P", "point", (1, 1, 1), 25.0, position=(0.4, 0.3, 1.0)), band)[0]
    ratio = E[full > 0] / full[full > 0]
    assert np.mean((ratio > 0.05) & (ratio < 0.95)) > 0.1 and np.mean(ratio == 0) > 0.05


def test_sun_mirror_is_parallel_light():
    from addon.bake.scene import build_scene

    from fixtures.bake_scenes import floor, mirror_facing

    # A low sun from +x onto a mirror at x = -1 that faces +x and a little down.
    P, N, R, normal, sq = mirror_facing((0.866, 0.1, -0.5), centre=(-1.0, 0.0, 1.6))
    geo = dict(R=R, normal=normal, centre=np.array([-1.0, 0.0, 1.6]), half=0.75, tint=np.ones(3))
    d = np.array([-1.0, 0.15, -0.3])
    d /= np.linalg.norm(d)
    S = 3.0
    sc = build_scene([floor(resolution=RES), dict(name="mirror", tri_p=P, tri_n=N, role="reflect")], [Light("Sun", "sun", (1.0, 1.0, 1.0), S, direction=d)])
    res = bake(sc, SETTINGS)
    band = rasterise(sc, sc.receivers[0], SETTINGS.samples, SETTINGS.seed, SETTINGS.jitter)
    r = d - 2 * np.dot(d, normal) * normal  # reflected direction (towards the floor)
    assert r[2] < -0.5
    t, hit, local, inside = mirror_hit(geo, band.position, np.broadcast_to(-r, band.position.shape))
    E = np.where(inside & (t > 0), S * abs(r[2]), 0.0)
    # Precondition for a sharp comparison: no sample within 2e-5 m of the lit region's edge
    # (the far-point sun, D = 1e5 x 6.1 m, tilts rays by <= r_tri / D = 1.7e-6 rad, which moves
    # that edge by <= 2 m x 1.7e-6 = 3.4e-6 m).
    edge = np.min(np.abs(np.abs(local[:, :2]) - geo["half"]), axis=1)
    assert edge[t > 0].min() > 2e-5
    ref = texel_mean(band, E[:, None] * geo["tint"], RES)
    err = _check(res.raw["floor"], ref, min_cover=0.05)
    assert err < 1e-4  # 2 L / D with D = 1e5 x scene size


def test_glass_reflection_has_dielectric_fresnel():
    sc, geo = mirror_scene(resolution=RES)
    sc.tri_role[sc.tri_object == 1] = ROLE_BOTH
    sc.tri_ior[:] = 1.5
    res = bake(sc, SETTINGS)
    band = rasterise(sc, sc.receivers[0], SETTINGS.samples, SETTINGS.seed, SETTINGS.jitter)
    E, _, w_in = point_reference(sc, geo, sc.lights[0], band)
    cos_i = np.abs(w_in @ geo["normal"])
    F = np.array([fresnel_dielectric(c, 1.0, 1.5) for c in cos_i])
    ref = texel_mean(band, (E * F)[:, None] * geo["tint"], RES)
    _check(res.raw["floor"], ref)
    # A real Fresnel: about 4 % near normal incidence, so far below the mirror's value.
    assert 0.03 < res.raw["floor"][ref > 0].mean() / texel_mean(band, E[:, None] * geo["tint"], RES)[ref > 0].mean() < 0.08


def test_occluder_between_mirror_and_floor_casts_a_shadow():
    from addon.bake.scene import build_scene

    from fixtures.bake_scenes import floor, tilted_mirror

    P, N, R, normal, sq = tilted_mirror()
    blocker = np.array([[[-2, -2, 0.5], [0.0, -2, 0.5], [0.0, 2, 0.5]], [[-2, -2, 0.5], [0.0, 2, 0.5], [-2, 2, 0.5]]], float)
    light = Light("Point", "point", (1, 1, 1), 10.0, position=(0.4, 0.3, 1.0))
    sc = build_scene([floor(resolution=RES), dict(name="mirror", tri_p=P, tri_n=N, role="reflect"), dict(name="blocker", tri_p=blocker)], [light])
    res = bake(sc, SETTINGS)
    img = res.raw["floor"][:, :, 0]
    x = (np.arange(RES) + 0.5) / RES * 4 - 2
    # Under the blocker (x < 0) the floor gets nothing; beside it the caustic is there.
    assert np.all(img[:, x < -0.4] == 0.0)
    assert np.count_nonzero(img[:, x > 0.05]) > 0.2 * img[:, x > 0.05].size


def _dense_average(sc, geo, light, n=32):
    """The analytic texel average: the image-source irradiance at n x n centred samples
    (partly lit texels: error ~ 1 / n of their edge share)."""
    band = rasterise(sc, sc.receivers[0], n * n, 0, False)
    E, _, _ = point_reference(sc, geo, light, band)
    cnt = np.bincount(band.texel, minlength=RES * RES)
    lit = np.bincount(band.texel, weights=(E > 0).astype(float), minlength=RES * RES)
    return texel_mean(band, E[:, None] * geo["tint"], RES), (lit == cnt).reshape(RES, RES) & (cnt > 0).reshape(RES, RES)


def test_flux_estimator_matches_image_source_texel_average():
    """one_bounce="flux": each forward-traced sub-triangle of the mirror spreads its flux
    (I Ω) over its image with a density linear between its corners (quadratic-element
    Jacobians).  Against the analytic texel average: fully lit texels within 4e-3 (measured
    3.2e-3: the corner densities of the quadratic element err at second order on the image
    source's projective map; the points estimator is exact here), the texels on the lit
    region's edge within 3 % in sum (the reference's own quantisation there), energy within
    0.5 % (measured 1.0004)."""
    sc, geo = mirror_scene(resolution=RES)
    res = bake(sc, BakeSettings(samples=1, seed=7, margin=0, one_bounce="flux"))
    ref, full = _dense_average(sc, geo, sc.lights[0])
    got = res.raw["floor"]
    lit = ref[:, :, 0] > 0
    assert full.sum() > 0.2 * full.size
    np.testing.assert_allclose(got[full], ref[full], rtol=4e-3)
    edge = lit & ~full
    # measured 2.2 %: mostly the reference's, whose lit fraction of a texel the image's edge
    # crosses is counted in 1/32 steps (an edge along a row of samples: up to 7 % per texel)
    assert np.abs(got[edge] - ref[edge]).sum() <= 0.03 * ref[edge].sum()
    assert abs(got.sum() / ref.sum() - 1) <= 5e-3
    assert np.all(got[~lit & ~np.pad(lit, 1)[1:-1, 2:] & ~np.pad(lit, 1)[1:-1, :-2] & ~np.pad(lit, 1)[2:, 1:-1]
                      & ~np.pad(lit, 1)[:-2, 1:-1]] == 0.0)
    rep = res.report["estimators"]["forward-flux"]["passes"][0]
    assert rep["chain"] == "R" and rep["sub_triangles"] > 0
