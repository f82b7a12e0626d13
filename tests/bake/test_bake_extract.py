"""Scene extraction (addon/bake/extract.py) against hand-built meshes, transforms and materials."""

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.bake.extract import extract_scene, material_role  # noqa: E402
from addon.bake.scene import ROLE_BOTH, ROLE_NONE, ROLE_REFLECT, ROLE_REFRACT, SceneError  # noqa: E402


def _reset():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _mesh_object(name, verts, faces, uv=True, location=(0, 0, 0), rotation=(0, 0, 0), scale=(1, 1, 1)):
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], faces)
    if uv:
        layer = me.uv_layers.new(name="UVMap")
        co = np.array(verts, float)
        loops = np.empty(len(me.loops), dtype=np.int32)
        me.loops.foreach_get("vertex_index", loops)
        layer.uv.foreach_set("vector", (co[loops, :2] * 0.2 + 0.5).reshape(-1))
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    ob.location, ob.rotation_euler, ob.scale = location, rotation, scale
    return ob


def _material(name, node, **inputs):
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new(node)
    for k, v in inputs.items():
        bsdf.inputs[k].default_value = v
    nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat


def _point_light(energy=100.0, location=(0, 0, 3)):
    data = bpy.data.lights.new("Point", "POINT")
    data.energy = energy
    ob = bpy.data.objects.new("Point", data)
    bpy.context.scene.collection.objects.link(ob)
    ob.location = location
    return ob


def _world_matrix(ob):
    bpy.context.view_layer.update()
    return np.array(ob.matrix_world, float)


def test_positions_and_custom_normals_under_a_skewed_transform():
    _reset()
    verts = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0.5)]
    ob = _mesh_object("Patch", verts, [(0, 1, 2), (1, 3, 2)], location=(0.5, -1, 2), rotation=(0.3, -0.2, 0.7), scale=(2.0, 0.5, 1.5))
    me = ob.data
    custom = np.array([(0, 0, 1), (0.1, 0, 1), (0, 0.2, 1), (0.1, 0, 1), (0.3, 0.3, 1), (0, 0.2, 1)], float)
    me.normals_split_custom_set([tuple(c) for c in custom])
    _point_light()
    M = _world_matrix(ob)
    sc = extract_scene(resolution=32)
    assert sc.n_triangles == 2 and sc.objects == ["Patch"]
    V = np.c_[np.array(verts, float), np.ones(4)] @ M.T
    expected_p = V[:, :3][np.array([[0, 1, 2], [1, 3, 2]])]
    np.testing.assert_allclose(sc.tri_p, expected_p, atol=1e-12)
    # Normals: the mesh's own corner normals, by the inverse transpose, normalised.
    cn = np.empty(len(me.loops) * 3)
    me.corner_normals.foreach_get("vector", cn)
    n = cn.reshape(-1, 3) @ np.linalg.inv(M[:3, :3])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(sc.tri_n.reshape(-1, 3), n, atol=1e-12)
    # ... which are the custom normals we set (Blender stores them to ~1e-4).
    c = custom @ np.linalg.inv(M[:3, :3])
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    np.testing.assert_allclose(sc.tri_n.reshape(-1, 3), c, atol=2e-4)
    # Normals stay perpendicular to transformed tangents (what the inverse transpose is for):
    # a flat face's custom normal equal to its face normal stays the face normal.
    _reset()
    ob = _mesh_object("Flat", [(0, 0, 0), (1, 0, 0), (0, 1, 0.3)], [(0, 1, 2)], scale=(3.0, 0.5, 1.0), rotation=(0.4, 0, 0))
    _point_light()
    sc = extract_scene(resolution=8)
    ng = np.cross(sc.tri_p[0, 1] - sc.tri_p[0, 0], sc.tri_p[0, 2] - sc.tri_p[0, 0])
    ng /= np.linalg.norm(ng)
    np.testing.assert_allclose(sc.tri_n[0], np.tile(ng, (3, 1)), atol=1e-6)
    np.testing.assert_allclose(sc.receivers[0].uv[0], np.array([(0, 0), (1, 0), (0, 1)]) * 0.2 + 0.5, atol=1e-7)


def test_smooth_and_sharp_corner_normals():
    _reset()
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, radius=1.0, location=(0, 0, 0))
    sphere = bpy.context.object
    bpy.ops.object.shade_smooth()
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(4, 0, 0))
    cube = bpy.context.object
    cube.data.shade_smooth()
    cube.data.set_sharp_from_angle(angle=math.radians(30))
    _point_light()
    sc = extract_scene(resolution=8)
    s = sc.tri_object == sc.objects.index(sphere.name)
    # Smooth sphere: every corner carries its vertex's normal (Blender's angle-weighted vertex
    # normal, close to radial), shared by all the corners at that vertex.
    P, N = sc.tri_p[s].reshape(-1, 3), sc.tri_n[s].reshape(-1, 3)
    me = sphere.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    vn = np.empty(len(me.vertices) * 3)
    me.vertex_normals.foreach_get("vector", vn)
    co, vn = co.reshape(-1, 3), vn.reshape(-1, 3)
    vid = np.argmin(np.linalg.norm(P[:, None, :] - co[None], axis=2), axis=1)
    np.testing.assert_allclose(P, co[vid], atol=1e-12)
    np.testing.assert_allclose(N, vn[vid] / np.linalg.norm(vn[vid], axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(N, P / np.linalg.norm(P, axis=1, keepdims=True), atol=0.03)
    # Cube with sharp 90-degree edges: every corner normal is its face's normal (split normals).
    c = sc.tri_object == sc.objects.index(cube.name)
    P, N = sc.tri_p[c], sc.tri_n[c]
    ng = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    np.testing.assert_allclose(N, np.repeat(ng[:, None], 3, axis=1), atol=1e-6)
    assert sc.n_triangles == 16 * 2 + 16 * 6 * 2 + 12 and sc.tri_p.shape == (sc.n_triangles, 3, 3)


def test_modifiers_are_applied():
    _reset()
    ob = _mesh_object("Strip", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    arr = ob.modifiers.new("Array", "ARRAY")
    arr.count = 3
    arr.use_relative_offset = False
    arr.use_constant_offset = True
    arr.constant_offset_displace = (2.0, 0.0, 0.0)
    _point_light()
    sc = extract_scene(resolution=8)
    assert sc.n_triangles == 3
    np.testing.assert_allclose(np.sort(sc.tri_p[:, 0, 0]), [0.0, 2.0, 4.0], atol=1e-12)


def test_roles_from_materials_and_overrides():
    _reset()
    mats = {
        "glass": _material("Glass", "ShaderNodeBsdfGlass", IOR=1.45, Color=(0.9, 1.0, 0.8, 1.0)),
        "rough_glass": _material("RoughGlass", "ShaderNodeBsdfGlass", Roughness=0.5),
        "metal": _material("Gold", "ShaderNodeBsdfPrincipled", Metallic=1.0, Roughness=0.05, **{"Base Color": (1.0, 0.8, 0.3, 1.0)}),
        "rough_metal": _material("Brushed", "ShaderNodeBsdfPrincipled", Metallic=1.0, Roughness=0.6),
        "water": _material("Water", "ShaderNodeBsdfPrincipled", Roughness=0.0, IOR=1.33, **{"Transmission Weight": 1.0}),
        "glossy": _material("Chrome", "ShaderNodeBsdfAnisotropic", Roughness=0.0, Color=(0.7, 0.7, 0.7, 1.0)),
        "diffuse": _material("Paint", "ShaderNodeBsdfDiffuse"),
    }
    r = {k: material_role(m) for k, m in mats.items()}
    assert r["glass"][0] == ROLE_BOTH and r["glass"][1] == pytest.approx(1.45) and np.allclose(r["glass"][2], (0.9, 1.0, 0.8))
    assert r["rough_glass"][0] == ROLE_NONE and r["rough_metal"][0] == ROLE_NONE and r["diffuse"][0] == ROLE_NONE
    assert r["metal"][0] == ROLE_REFLECT and np.allclose(r["metal"][2], (1.0, 0.8, 0.3))
    assert r["water"][0] == ROLE_REFRACT and r["water"][1] == pytest.approx(1.33)
    assert r["glossy"][0] == ROLE_REFLECT and np.allclose(r["glossy"][2], 0.7)
    # Per-triangle materials, object overrides, receivers.
    two = _mesh_object("TwoMats", [(0, 0, 1), (1, 0, 1), (0, 1, 1), (1, 1, 1)], [(0, 1, 2), (1, 3, 2)], uv=False)
    two.data.materials.append(mats["glass"])
    two.data.materials.append(mats["metal"])
    two.data.polygons[1].material_index = 1
    forced = _mesh_object("Forced", [(0, 0, 2), (1, 0, 2), (0, 1, 2)], [(0, 1, 2)], uv=False)
    forced.data.materials.append(mats["glass"])
    forced["caustic_role"] = "none"
    floor = _mesh_object("Floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)], [(0, 1, 2, 3)])
    floor.data.materials.append(mats["diffuse"])
    wall = _mesh_object("Wall", [(-2, 2, 0), (2, 2, 0), (2, 2, 2)], [(0, 1, 2)])
    wall["caustic_receiver"] = "no"
    floor["caustic_resolution"] = 64
    _point_light()
    sc = extract_scene(resolution=16)
    t2 = sc.tri_object == sc.objects.index("TwoMats")
    assert sc.tri_role[t2].tolist() == [ROLE_BOTH, ROLE_REFLECT]
    assert sc.tri_ior[t2][0] == pytest.approx(1.45) and np.allclose(sc.tri_tint[t2][1], (1.0, 0.8, 0.3))
    assert np.all(sc.tri_role[sc.tri_object == sc.objects.index("Forced")] == ROLE_NONE)
    assert [r.name for r in sc.receivers] == ["Floor"] and sc.receivers[0].resolution == (64, 64)
    assert sc.receivers[0].tri_index.size == 2 and sc.receivers[0].uv_map == "UVMap"
    # A forced receiver without UVs, and a bad override value, are user errors.
    two["caustic_receiver"] = "yes"
    two["caustic_role"] = "none"
    with pytest.raises(SceneError, match="TwoMats.*no UV map"):
        extract_scene()
    two["caustic_receiver"] = "maybe"
    with pytest.raises(SceneError, match="caustic_receiver"):
        extract_scene()


def test_lights_in_cycles_units():
    _reset()
    _mesh_object("Floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0)], [(0, 1, 2)])
    specs = [("POINT", 100.0, dict(shadow_soft_size=0.25, color=(1.0, 0.5, 0.25))),
             ("SPOT", 200.0, dict(spot_size=math.radians(50), spot_blend=0.3)),
             ("SUN", 4.0, dict(angle=math.radians(1.0))),
             ("AREA", 60.0, dict(shape="RECTANGLE", size=0.5, size_y=0.2))]
    for kind, energy, props in specs:
        data = bpy.data.lights.new(kind, kind)
        data.energy = energy
        for k, v in props.items():
            setattr(data, k, v)
        ob = bpy.data.objects.new(kind, data)
        bpy.context.scene.collection.objects.link(ob)
        ob.location = (0.1, 0.2, 2.0)
        ob.rotation_euler = (0.3, 0.0, 0.5)
        if kind == "AREA":
            ob.scale = (2.0, 1.0, 1.0)
    data.exposure = 1.0  # the area light: x 2
    bpy.context.view_layer.update()
    sc = extract_scene()
    L = {light.type: light for light in sc.lights}
    down = np.array(bpy.data.objects["SPOT"].matrix_world)[:3, 2] * -1
    assert L["point"].intensity == pytest.approx(100.0 / (4 * math.pi)) and L["point"].radius == pytest.approx(0.25)
    np.testing.assert_allclose(L["point"].color, (1.0, 0.5, 0.25))
    np.testing.assert_allclose(L["point"].position, (0.1, 0.2, 2.0), atol=1e-6)
    assert L["spot"].intensity == pytest.approx(200.0 / (4 * math.pi))
    assert L["spot"].spot_size == pytest.approx(math.radians(50)) and L["spot"].spot_blend == pytest.approx(0.3)
    np.testing.assert_allclose(L["spot"].direction, down / np.linalg.norm(down), atol=1e-6)
    assert L["sun"].intensity == pytest.approx(4.0) and L["sun"].angle == pytest.approx(math.radians(1.0))
    np.testing.assert_allclose(L["sun"].direction, down / np.linalg.norm(down), atol=1e-6)
    assert L["area"].intensity == pytest.approx(60.0 / math.pi)
    np.testing.assert_allclose(L["area"].color, (2.0, 2.0, 2.0))
    assert L["area"].size_u == pytest.approx(1.0) and L["area"].size_v == pytest.approx(0.2)


def test_hidden_objects_and_bad_input():
    _reset()
    _mesh_object("Floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0)], [(0, 1, 2)])
    with pytest.raises(SceneError, match="no lights"):
        extract_scene().validate()
    light = _point_light()
    light.hide_render = True
    with pytest.raises(SceneError, match="no lights"):
        extract_scene().validate()
    light.hide_render = False
    extract_scene().validate()
    bpy.data.objects["Floor"].hide_render = True
    with pytest.raises(SceneError, match="no meshes"):
        extract_scene()
    _reset()
    _point_light()
    _mesh_object("Point", [(0, 0, 0), (0, 0, 0), (0, 0, 0)], [(0, 1, 2)])
    with pytest.raises(SceneError, match="zero area"):
        extract_scene().validate()
    _reset()
    _point_light()
    ob = _mesh_object("Bad", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    ob.data.vertices[1].co = (float("nan"), 0.0, 0.0)
    with pytest.raises(SceneError, match="NaN"):
        extract_scene().validate()
