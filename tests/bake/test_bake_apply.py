"""Images + CausticBake node group on receiver materials (addon/bake/apply.py), and the exact undo."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.bake.apply import GROUP_NAME, apply_bake, clear_bake  # noqa: E402
from fixtures.checks import snapshot  # noqa: E402


def _plane(name, z, mat=None):
    bpy.ops.mesh.primitive_plane_add(size=2, location=(0, 0, z))
    ob = bpy.context.object
    ob.name = name
    if mat is not None:
        ob.data.materials.append(mat)
    return ob


def _principled(name, color=(0.5, 0.4, 0.3, 1.0), linked=False):
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = color
    if linked:
        rgb = nt.nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = (0.2, 0.7, 0.1, 1.0)
        nt.links.new(rgb.outputs[0], bsdf.inputs["Base Color"])
    return mat


def make_context():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    shared = _principled("Shared", (0.9, 0.8, 0.7, 1.0))
    solo = _principled("Solo", linked=True)
    floor = _plane("Floor", 0.0, shared)
    ramp = _plane("Ramp", 1.0, shared)  # another receiver with the same material
    box = _plane("Box", 2.0, shared)  # not a receiver, same material
    box["caustic_receiver"] = "no"
    solo_ob = _plane("SoloOb", 3.0, solo)
    bare = _plane("Bare", 4.0)  # no material at all
    return dict(floor=floor, ramp=ramp, box=box, solo=solo_ob, bare=bare, shared=shared, solo_mat=solo)


def _images(names, rng):
    return {n: rng.uniform(0, 5, (8, 12, 3)).astype(np.float32) for n in names}, {n: "UVMap" for n in names}


def test_apply_wires_the_node_group_and_clear_restores_exactly(tmp_path):
    s = make_context()
    before = snapshot()
    rng = np.random.default_rng(0)
    names = ["Floor", "Ramp", "SoloOb", "Bare"]
    images, uvs = _images(names, rng)
    done = apply_bake(images, uvs, directory=str(tmp_path))
    assert set(done) == set(names)
    group = bpy.data.node_groups[GROUP_NAME]
    # Each receiver has its own image holding exactly the baked numbers (row 0 = bottom).
    for n in names:
        img = bpy.data.images[done[n]]
        assert img.colorspace_settings.name == "Non-Color" and tuple(img.size) == (12, 8)
        px = np.empty(12 * 8 * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
        np.testing.assert_array_equal(px.reshape(8, 12, 4)[:, :, :3], images[n])
    # Shared material: the two receivers get their own copies, the non-receiver keeps the original.
    f_mat, r_mat = s["floor"].material_slots[0].material, s["ramp"].material_slots[0].material
    assert f_mat is not s["shared"] and r_mat is not s["shared"] and f_mat is not r_mat
    assert s["box"].material_slots[0].material is s["shared"] and "caustic_bake_state" not in s["shared"]
    assert s["solo"].material_slots[0].material is s["solo_mat"]  # used by one receiver only: in place
    for ob in (s["floor"], s["ramp"], s["solo"], s["bare"]):
        mat = ob.material_slots[0].material
        nt = mat.node_tree
        out = nt.get_output_node("CYCLES")
        gnode = out.inputs["Surface"].links[0].from_node
        assert gnode.type == "GROUP" and gnode.node_tree is group
        assert gnode.inputs["Shader"].links[0].from_node.type == "BSDF_PRINCIPLED"
        tex = gnode.inputs["Irradiance"].links[0].from_node
        assert tex.type == "TEX_IMAGE" and tex.image.name == done[ob.name]
        assert tex.inputs["Vector"].links[0].from_node.uv_map == "UVMap"
        if ob is s["solo"]:
            assert gnode.inputs["Base Color"].links[0].from_node.type == "RGB"
        elif ob is s["bare"]:
            assert np.allclose(gnode.inputs["Base Color"].default_value[:3], 0.8)
        else:
            assert np.allclose(gnode.inputs["Base Color"].default_value[:3], (0.9, 0.8, 0.7))
    # The group computes Shader + Emission(Base Color x Irradiance / pi).
    scale = next(n for n in group.nodes if n.type == "VECT_MATH" and n.operation == "SCALE")
    assert scale.inputs["Scale"].default_value == pytest.approx(1 / np.pi)
    assert next(n for n in group.nodes if n.type == "EMISSION").inputs["Strength"].default_value == 1.0
    # Re-applying replaces, clearing restores everything.
    apply_bake(images, uvs, directory=str(tmp_path))
    assert sum(1 for m in bpy.data.materials if "CausticBake" in m.name) == 3
    clear_bake()
    assert snapshot() == before


def test_clear_only_named_objects_and_packing():
    s = make_context()
    before = snapshot()
    rng = np.random.default_rng(1)
    images, uvs = _images(["Floor", "SoloOb"], rng)
    apply_bake(images, uvs, pack=True)  # unsaved .blend: packed
    assert all(bpy.data.images[f"CausticBake {n}"].packed_file is not None for n in images)
    clear_bake(["SoloOb"])
    assert "caustic_bake_state" not in s["solo_mat"] and "CausticBake SoloOb" not in bpy.data.images
    assert s["floor"].material_slots[0].material is not s["shared"]
    clear_bake()
    assert snapshot() == before
