"""Results that would otherwise be silently wrong: warnings for a zero-power light and for
overlapping UV islands, a point light inside a closed glass solid (its T chain starts inside;
too few bounces for its internal reflection is a warning), and a flat plane scaled to zero
thickness accepted as the valid geometry it is."""

import numpy as np
import pytest

from addon.bake.checks import lights_inside, uv_overlap
from addon.bake.pipeline import BakeSettings, bake
from addon.bake.scene import Light, build_scene

from fixtures.bake_scenes import floor, tilted_mirror, uv_sphere

FAST = dict(samples=1, margin=0)


def test_a_zero_power_light_is_a_warning():
    P, N = tilted_mirror()[:2]
    scene = build_scene([floor(resolution=8), dict(name="mirror", tri_p=P, tri_n=N, role="reflect")],
                        [Light("Key", "point", (1, 1, 1), 10.0, position=(0.3, 0.2, 3.0)),
                         Light("Off", "point", (1, 1, 1), 0.0, position=(0.0, 0.0, 3.0)),
                         Light("Black", "point", (0, 0, 0), 5.0, position=(0.0, 0.0, 3.0))])
    warnings = bake(scene, BakeSettings(resolution=8, bounces=1, **FAST)).report["warnings"]
    assert "light 'Off' has zero power: it adds no light" in warnings
    assert "light 'Black' has zero power: it adds no light" in warnings
    assert not any("'Key'" in w for w in warnings)


def test_overlapping_uv_islands_are_a_warning():
    rec = floor(resolution=8)
    # A second copy of the floor's triangles lying on the same UVs (a mirrored island, stacked).
    over = dict(rec, tri_p=rec["tri_p"] + [0.0, 0.0, -0.5])
    scene_ok = build_scene([rec], [Light("Key", "point", (1, 1, 1), 10.0, position=(0, 0, 2.0))])
    assert uv_overlap(scene_ok.receivers[0]) == 0.0
    tp = np.concatenate([rec["tri_p"], over["tri_p"][:1]])  # one of the two triangles twice: half the square
    uv = np.concatenate([rec["uv"], rec["uv"][:1]])
    scene = build_scene([dict(rec, tri_p=tp, uv=uv)], [Light("Key", "point", (1, 1, 1), 10.0, position=(0, 0, 2.0))])
    share = uv_overlap(scene.receivers[0])
    assert share == pytest.approx(0.5, abs=0.01)
    warnings = bake(scene, BakeSettings(resolution=8, **FAST)).report["warnings"]
    assert [w for w in warnings if "overlapping" in w] == [
        f"receiver 'floor': {100 * share:.1f} % of its UV map is covered by overlapping UV islands; light landing on "
        "either place is summed into the same texels"]
    assert not any("overlapping" in w for w in bake(scene_ok, BakeSettings(resolution=8, **FAST)).report["warnings"])


def _light_in_glass(role, I=100.0):
    P, N = uv_sphere(24, 12, radius=0.5, centre=(0.0, 0.0, 1.0))
    return build_scene([floor(half=1.6, resolution=16), dict(name="glass", tri_p=P, tri_n=N, role=role, ior=1.5)],
                       [Light("Bulb", "point", (1, 1, 1), I, position=(0.0, 0.0, 1.0))])


def _centre_expected(I, h=1.0, half=1.6, res=16, texels=2, n=64):
    """Mean over the centre texels of E = 0.96 I h / (r² + h²)^1.5: every ray from the centre of
    the sphere leaves it at normal incidence (transmittance 1 - 0.04), without bending."""
    t = 2 * half / res
    x = (np.arange(n * texels) + 0.5) / (n * texels) * texels * t - texels * t / 2
    X, Y = np.meshgrid(x, x)
    return float(np.mean(0.96 * I * h / (X * X + Y * Y + h * h) ** 1.5))


def test_a_light_inside_a_closed_glass_solid_bakes_its_t_chain_from_inside():
    scene = _light_in_glass("refract")
    assert lights_inside(scene, [1]) == {0: [1]} and lights_inside(scene, [0]) == {}
    res = bake(scene, BakeSettings(resolution=16, bounces=1, direct=False, **FAST))
    assert res.report["plan"]["summary"] == ["floor: T 100.0 %"]
    centre = res.images["floor"][7:9, 7:9, 0].mean()
    assert centre == pytest.approx(_centre_expected(100.0), rel=0.03)
    assert not any("inside" in w for w in res.report["warnings"])  # nothing is missing


def test_too_few_bounces_for_a_light_inside_glass_is_a_warning():
    scene = _light_in_glass("both")
    one = bake(scene, BakeSettings(resolution=16, bounces=1, direct=False, **FAST))
    assert ("light 'Bulb' is inside the closed refracting object 'glass': light reflected inside before it leaves "
            "(chain RT) needs 2 bounces; set Max Bounces (--bounces) to 2 or Auto") in one.report["warnings"]
    auto = bake(scene, BakeSettings(resolution=16, direct=False, **FAST))
    assert not any("inside" in w for w in auto.report["warnings"])
    assert "RT" in auto.report["plan"]["summary"][0]
    c1, ca = one.images["floor"][7:9, 7:9, 0].mean(), auto.images["floor"][7:9, 7:9, 0].mean()
    assert ca > c1 * 1.02  # the internal reflections add light
    assert ca == pytest.approx(_centre_expected(100.0) * 1.04, rel=0.03)


@pytest.mark.bpy
def test_a_plane_scaled_to_zero_thickness_is_valid_and_a_collapsed_one_is_not():
    bpy = pytest.importorskip("bpy")
    from addon.bake.extract import extract_scene
    from addon.bake.scene import SceneError

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_plane_add(size=2, location=(0, 0, 0))
    floor_ob = bpy.context.object
    floor_ob.name = "Floor"
    floor_ob.scale = (2.0, 1.5, 0.0)  # flat in z anyway: zero thickness changes nothing
    bpy.ops.mesh.primitive_plane_add(size=1, location=(0, 0, 1.5))
    mirror = bpy.context.object
    mirror.name = "Mirror"
    mirror["caustic_role"] = "reflect"
    mirror.scale = (1.0, 1.0, 0.0)
    mirror.rotation_euler = (0.3, 0.0, 0.0)
    light = bpy.data.objects.new("Point", bpy.data.lights.new("Point", "POINT"))
    bpy.context.scene.collection.objects.link(light)
    light.location = (0.2, 0.0, 3.0)
    scene = extract_scene(resolution=8)
    scene.validate()
    rec = scene.receivers[0]
    assert rec.name == "Floor"
    np.testing.assert_allclose(scene.tri_n[rec.tri_index], np.broadcast_to([0.0, 0.0, 1.0], (2, 3, 3)), atol=1e-12)
    m = scene.tri_object == scene.objects.index("Mirror")
    want = np.array([0.0, -np.sin(0.3), np.cos(0.3)])
    np.testing.assert_allclose(scene.tri_n[m], np.broadcast_to(want, (2, 3, 3)), atol=1e-12)
    assert np.ptp(scene.tri_p[rec.tri_index][:, :, 0]) == pytest.approx(4.0)
    mirror.scale = (0.0, 1.0, 1.0)  # an in-plane axis collapsed: no area left
    with pytest.raises(SceneError, match="'Mirror' has a degenerate \\(zero-scale\\) transform"):
        extract_scene(resolution=8)
