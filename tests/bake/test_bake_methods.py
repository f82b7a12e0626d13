"""Bake methods (BakeSettings.method): the photon tracer against the independent photon
reference and the analytic mirror, the Newton / SMS baselines in the bake, determinism.

Tolerances:
- photon (addon/solver/estimators/photon.py) vs tests/reference/photon.py: both are unbiased estimates of
  the same texel averages, so relMSE (rel_mse, tests/fixtures/checks.py) is the sum of
  their variances.  The reference's (3M photons into a loose cone, no stratification) is
  ~1/(photons per lit texel) ~ 1.5e-3 at 32² on the ring (4.7e-3 on the water, whose cone
  is wide); ours is ~10x smaller (stratified, tight cone: two seeds differ by 1.4e-4).
  Bounds: 5e-3 (ring), 8e-3 (water), ~3x / ~1.7x the expected.  Energy: each total is a sum
  over ~1e6 photons (relative noise ~1e-3); bound 1 %.
- mirror: the analytic image-source irradiance averaged over 16² centred points per texel
  (the averaging error at the caustic's edge is O(1/16) of the edge texels' values, the
  interior is exact); total flux to 0.3 %, relMSE 2e-3.
"""

import numpy as np
import pytest

from addon.bake.pipeline import BakeSettings, bake
from addon.bake.raster import rasterise
from addon.bake.scene import Light, build_scene
from addon.demo import wavy_water

from fixtures.bake_scenes import floor, mirror_scene, ring_scene
from reference.photon import KIND_REFLECT, KIND_REFRACT, trace_caustic
from fixtures.checks import kinds_of, rel_mse

PH = dict(samples=4, margin=0, method="photon", bounces=1)


def _water_scene(res_=32, half=2.0):
    wp, wn = wavy_water(cells=12, size=2.0, amplitude=0.08)
    swap = lambda a: a[..., [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # noqa: E731
    wp, wn = swap(wp), swap(wn)
    wp[..., 2] += 1.0
    light = Light("Point", "point", (1.0, 1.0, 1.0), 20.0, position=(0.3, -0.2, 3.0))
    return build_scene([floor(half=half, resolution=res_), dict(name="water", tri_p=wp, tri_n=wn, role="refract", ior=1.33)], [light])


@pytest.mark.slow
def test_photon_ring_matches_photon_reference():
    res_, half = 32, 1.6
    sc = ring_scene(resolution=res_, half=half)
    light = sc.lights[0]
    out = bake(sc, BakeSettings(seed=1, photons=3_000_000, **PH))
    ref = trace_caustic(light.position, light.intensity, sc.tri_p, sc.tri_n, kinds_of(sc, KIND_REFLECT), sc.tri_ior,
                        (-half, -half), (2 * half, 2 * half), (res_, res_), 3_000_000, seed=5,
                        target_centre=(0.0, 0.0, 0.25), target_radius=1.2)
    tint = (1.0, 0.9, 0.6)
    for c in range(3):
        b = out.raw["floor"][:, :, c]
        assert rel_mse(b, ref * tint[c]) <= 5e-3
        assert abs(b.sum() / (ref.sum() * tint[c]) - 1) <= 0.01
    rep = out.report
    assert rep["estimator"] == "photon" and rep["chains"][0]["status"] == "baked"
    assert rep["counts"]["photons"] >= 3_000_000 and rep["counts"]["photons_deposited"] > 500_000


def test_photon_water_matches_photon_reference():
    res_, half = 32, 2.0
    sc = _water_scene(res_, half)
    light = sc.lights[0]
    out = bake(sc, BakeSettings(seed=2, photons=2_000_000, **PH))
    ref = trace_caustic(light.position, light.intensity, sc.tri_p, sc.tri_n, kinds_of(sc, KIND_REFRACT), sc.tri_ior,
                        (-half, -half), (2 * half, 2 * half), (res_, res_), 2_000_000, seed=9,
                        target_centre=(0.0, 0.0, 1.0), target_radius=2.0 * np.sqrt(2) + 0.1)
    b = out.raw["floor"][:, :, 0]
    # The reference is the noisy side here: its cone is wide (most photons miss the water) and
    # two of its seeds differ by relMSE 9.4e-3 (variance ~4.7e-3 each); ours: 7e-5.
    assert rel_mse(b, ref) <= 8e-3
    assert abs(b.sum() / ref.sum() - 1) <= 0.01
    # Against the deterministic bake (16 supersamples per texel): the same texel averages.
    sp = bake(sc, BakeSettings(samples=16, seed=1, margin=0)).raw["floor"][:, :, 0]
    assert rel_mse(b, sp) <= 2e-4
    assert abs(b.sum() / sp.sum() - 1) <= 2e-3


def test_photon_mirror_conserves_flux_against_image_source():
    res_ = 32
    sc, geo = mirror_scene(resolution=res_)
    out = bake(sc, BakeSettings(seed=4, photons=4_000_000, **PH))
    # Analytic texel averages: the image-source irradiance at 16 x 16 centred points per texel.
    from fixtures.checks import point_reference, texel_mean

    band = rasterise(sc, sc.receivers[0], 256, 0, False)
    E, _, _ = point_reference(sc, geo, sc.lights[0], band)
    ref = texel_mean(band, E[:, None] * geo["tint"], res_)
    b = out.raw["floor"]
    texel_area = (4.0 / res_) ** 2
    for c in range(3):
        assert abs(b[:, :, c].sum() * texel_area / (ref[:, :, c].sum() * texel_area) - 1) <= 3e-3
        assert rel_mse(b[:, :, c], ref[:, :, c]) <= 2e-3
    # No light outside the reflected beam's footprint (one texel of slack at its edge).
    lit = ref[:, :, 0] > 0
    grown = lit.copy()
    grown[1:] |= lit[:-1]
    grown[:-1] |= lit[1:]
    grown[:, 1:] |= grown[:, :-1].copy()
    grown[:, :-1] |= grown[:, 1:].copy()
    assert np.all(b[~grown] == 0.0)


def test_photon_is_deterministic_for_any_thread_count():
    from addon.solver.runtime.jit import get_num_threads, set_num_threads

    sc = ring_scene(resolution=16)
    base = dict(seed=7, photons=300_000, **PH)
    before = get_num_threads()
    try:
        a = bake(sc, BakeSettings(**base)).raw["floor"]
        b = bake(sc, BakeSettings(**base, threads=1)).raw["floor"]
        c = bake(sc, BakeSettings(**base, threads=2, batch_tuples=3000)).raw["floor"]  # the tuple batch plays no part
    finally:
        set_num_threads(before)
    d = bake(sc, BakeSettings(**{**base, "seed": 8})).raw["floor"]
    assert a.tobytes() == b.tobytes() == c.tobytes()
    assert a.tobytes() != d.tobytes() and abs(d.sum() / a.sum() - 1) < 0.02


def test_baselines_bake_the_ring_and_never_add_energy():
    sc = ring_scene(resolution=24)
    s = dict(samples=4, seed=3, margin=0, bounces=1)
    # every path at the same samples as the baselines (which can only miss some of them)
    ref = bake(sc, BakeSettings(**s, one_bounce="points"))
    e_ref = ref.raw["floor"].sum()
    assert (ref.report["estimator"], ref.report["solver"]) == ("path-points", "spoly")
    for method, kw in (("newton", {}), ("sms", {"sms_seeds": 4})):
        out = bake(sc, BakeSettings(method=method, **s, **kw))
        assert (out.report["estimator"], out.report["solver"]) == ("path-points", method)
        assert out.report["chains"][0]["status"] == "baked"
        e = out.raw["floor"].sum()
        assert 0.2 * e_ref < e <= e_ref * (1 + 1e-9), (method, e / e_ref)
        # they miss paths, they never invent them: no texel brighter than the full solution
        assert np.all(out.raw["floor"] <= ref.raw["floor"] * (1 + 1e-6) + 1e-9)


def test_methods_skip_chains_they_cannot_solve():
    sc = _water_scene(16)
    out = bake(sc, BakeSettings(samples=1, method="newton", chains=("T",), bounces=1))
    assert out.report["chains"][0]["status"] == "baked"
    sc2 = ring_scene(resolution=8)
    out = bake(sc2, BakeSettings(samples=1, method="curve", bounces=1))
    st = out.report["chains"][0]["status"]
    assert st.startswith("skipped:") and ("curve solver does not solve R" in st or "not available" in st)
    assert any("chain R skipped" in w for w in out.report["warnings"])
    assert np.all(out.raw["floor"] == 0.0)


def test_unknown_method_is_a_clear_value_error():
    sc = ring_scene(resolution=8)
    with pytest.raises(ValueError, match="unknown bake method 'photons'.*spoly, newton, sms, curve, photon"):
        bake(sc, BakeSettings(method="photons"))
    with pytest.raises(ValueError, match="sms_seeds"):
        bake(sc, BakeSettings(method="sms", sms_seeds=0))
    with pytest.raises(ValueError, match="photons must be"):
        bake(sc, BakeSettings(method="photon", photons=0))


@pytest.mark.bpy
def test_cli_method_flag_writes_the_method_into_report(tmp_path, capsys):
    pytest.importorskip("bpy")
    import json
    import os

    from addon.__main__ import main

    blend = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "sample_blends", "mirror_plane.blend")
    out = tmp_path / "ph"
    assert main(["bake", blend, "--out", str(out), "--resolution", "16", "--method", "photon", "--photons", "20000"]) == 0
    rep = json.load(open(out / "report.json"))
    assert rep["estimator"] == "photon" and rep["settings"]["photons"] == 20000 and rep["counts"]["photons_deposited"] > 0
    assert "[photon (" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["bake", blend, "--out", str(out), "--method", "bogus"])
