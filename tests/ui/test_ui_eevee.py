"""EEVEE shows the bake: render a sample scene (64 x 64 pixels) before and after
``caustics.bake`` and check that the added light sits where the texture says, with the
brightness the node group promises (radiance = albedo x E / pi).  About 15 s."""

import os
import shutil

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy


REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")
PIXELS = 64



def _render(path):
    sc = bpy.context.scene
    sc.render.engine = "BLENDER_EEVEE"
    sc.render.resolution_x = sc.render.resolution_y = PIXELS
    sc.render.resolution_percentage = 100
    sc.eevee.taa_render_samples = 1
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.view_settings.exposure = 0.0
    sc.view_settings.gamma = 1.0
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path, check_existing=False)
    px = np.empty(PIXELS * PIXELS * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(PIXELS, PIXELS, 4)[:, :, :3].astype(np.float64)  # row 0 = bottom


def _texel_world_points(ob, res):
    """World position of each texel centre of ``ob`` (a planar, UV-unwrapped mesh): (res, res, 3),
    NaN where no face covers the texel."""
    me = ob.data
    me.calc_loop_triangles()
    M = np.array(ob.matrix_world)
    out = np.full((res, res, 3), np.nan)
    c = (np.arange(res) + 0.5) / res
    U, V = np.meshgrid(c, c)  # row j = v
    q = np.stack([U, V], axis=-1).reshape(-1, 2)
    flat = out.reshape(-1, 3)
    for lt in me.loop_triangles:
        uv = np.array([me.uv_layers.active.uv[i].vector for i in lt.loops])
        p = np.array([tuple(M @ np.append(me.vertices[v].co, 1.0))[:3] for v in lt.vertices])
        e1, e2 = uv[1] - uv[0], uv[2] - uv[0]
        det = e1[0] * e2[1] - e1[1] * e2[0]
        d = q - uv[0]
        b1 = (d[:, 0] * e2[1] - d[:, 1] * e2[0]) / det
        b2 = (e1[0] * d[:, 1] - e1[1] * d[:, 0]) / det
        inside = (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1)
        flat[inside] = p[0] + b1[inside, None] * (p[1] - p[0]) + b2[inside, None] * (p[2] - p[0])
    return out


def test_eevee_render_shows_the_baked_caustic_where_the_texture_says(tmp_path):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    path = str(tmp_path / "mirror_plane.blend")
    shutil.copy(os.path.join(SAMPLES, "mirror_plane.blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    sc = bpy.context.scene
    res = 48
    sc.caustic_bake.resolution = res
    sc.caustic_bake.samples = 1
    sc.caustic_bake.margin = 0
    before = _render(str(tmp_path / "before.exr"))
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    after = _render(str(tmp_path / "after.exr"))
    added = (after - before).mean(axis=2)  # rendered radiance the bake added, per pixel

    floor = bpy.data.objects["Floor"]
    img = bpy.data.images["CausticBake Floor"]
    tex = np.empty(res * res * 4, dtype=np.float32)
    img.pixels.foreach_get(tex)
    E = tex.reshape(res, res, 4)[:, :, :3].mean(axis=2)  # row 0 = v = 0
    group = floor.material_slots[0].material.node_tree.nodes["CausticBake Group 0"]
    albedo = np.array(group.inputs["Base Color"].default_value[:3]).mean()
    world = _texel_world_points(floor, res)
    bright, dark = [], []
    cam = sc.camera
    for j in range(res):
        for i in range(res):
            if np.isnan(world[j, i, 0]):
                continue
            ndc = world_to_camera_view(sc, cam, Vector(world[j, i]))
            x, y = int(ndc.x * PIXELS), int(ndc.y * PIXELS)
            if not (2 <= x < PIXELS - 2 and 2 <= y < PIXELS - 2 and ndc.z > 0):
                continue
            # Texels whose 3 x 3 neighbourhood is uniform enough for a pixel to sample them.
            nb = E[max(0, j - 1):j + 2, max(0, i - 1):i + 2]
            if E[j, i] > 0.5 * E.max() and nb.min() > 0.7 * E[j, i]:
                bright.append((added[y, x], albedo * E[j, i] / np.pi))
            elif nb.max() == 0.0:
                dark.append(added[y, x])
    assert len(bright) >= 5 and len(dark) >= 20, (len(bright), len(dark))
    bright = np.array(bright)
    dark = np.array(dark)
    print("bright: rendered / expected", np.median(bright[:, 0] / bright[:, 1]), "dark max", np.abs(dark).max(),
          "median bright", np.median(bright[:, 0]))
    # The caustic is where the texture is bright, and nowhere else ...
    assert np.median(bright[:, 0]) > 20 * max(np.abs(np.median(dark)), 1e-4)
    assert np.percentile(np.abs(dark), 90) < 0.05 * np.median(bright[:, 0])
    # ... with the radiance the node group promises: albedo x E / pi.
    assert np.median(bright[:, 0] / bright[:, 1]) == pytest.approx(1.0, rel=0.25)
