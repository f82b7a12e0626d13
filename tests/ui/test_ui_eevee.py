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


def _floor_texel_under_pixels(sc, floor_name, water_name, res, pixels, eta):
    """Per render pixel (row 0 = bottom) whose camera ray meets the water first: the texel
    (row, column) of the floor its refracted ray lands on (Snell's law at the water's
    surface, IOR ``eta``), else (-1, -1)."""
    import math

    from mathutils import Vector
    from mathutils.geometry import barycentric_transform, intersect_point_tri

    dg = bpy.context.evaluated_depsgraph_get()
    cam = sc.camera
    tr, br, bl, tl = [cam.matrix_world @ v for v in cam.data.view_frame(scene=sc)]
    origin = cam.matrix_world.translation
    floor = bpy.data.objects[floor_name]
    me = floor.evaluated_get(dg).to_mesh()
    me.calc_loop_triangles()
    uvl = me.uv_layers.active.uv
    tris = {}
    for lt in me.loop_triangles:
        tris.setdefault(lt.polygon_index, []).append(([me.vertices[v].co.copy() for v in lt.vertices],
                                                      [Vector((*uvl[k].vector, 0.0)) for k in lt.loops]))
    inv = floor.matrix_world.inverted()
    out = np.full((pixels, pixels, 2), -1, dtype=int)
    for y in range(pixels):
        for x in range(pixels):
            fx, fy = (x + 0.5) / pixels, (y + 0.5) / pixels
            d = (bl.lerp(br, fx).lerp(tl.lerp(tr, fx), fy) - origin).normalized()
            hit, loc, nrm, _i, ob, _m = sc.ray_cast(dg, origin, d)
            if not hit or ob.name != water_name:
                continue
            n = nrm.normalized()
            c = -n.dot(d)
            if c < 0:
                n, c = -n, -c
            k = 1.0 - (1.0 - c * c) / eta ** 2
            t = (d / eta + n * (c / eta - math.sqrt(k))).normalized()
            hit, loc2, _n, poly, ob, _m = sc.ray_cast(dg, loc + 1e-4 * t, t)
            if not hit or ob.name != floor_name:
                continue
            p = inv @ loc2
            for (a, b, cc), (ua, ub, uc) in tris.get(poly, []):
                if intersect_point_tri(p, a, b, cc) is not None:
                    uv = barycentric_transform(p, a, b, cc, ua, ub, uc)
                    out[y, x] = (min(res - 1, max(0, int(uv.y * res))), min(res - 1, max(0, int(uv.x * res))))
                    break
    floor.evaluated_get(dg).to_mesh_clear()
    return out


@pytest.mark.slow
def test_eevee_sees_the_caustic_under_the_water(tmp_path):
    """water_pool with EEVEE's defaults (the sample ships EEVEE-ready): EEVEE draws water
    opaque unless raytraced refraction is on.  After the
    operator's bake (which turns on the water's raytraced refraction, the scene's raytracing
    and a screen-tracing thickness that reaches the floor), the floor seen through the water
    carries the caustic: the render's added radiance there, on 4 x 4 pixel blocks, has the
    pattern of albedo x E / pi at the floor points the refracted camera rays reach (correlation)
    and its level (x the water's transmission, ~0.9); without the settings it was ~0.14 of it.
    Clear puts every setting back."""
    path = str(tmp_path / "water_pool.blend")
    shutil.copy(os.path.join(SAMPLES, "water_pool.blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    sc = bpy.context.scene
    water = bpy.data.materials["Water"]
    # the sample ships EEVEE-ready; a user's scene has EEVEE's defaults
    water.use_raytrace_refraction = False
    sc.eevee.use_raytracing = False
    sc.eevee.ray_tracing_options.screen_trace_thickness = 0.2
    settings0 = (water.use_raytrace_refraction, sc.eevee.use_raytracing, sc.eevee.ray_tracing_options.screen_trace_thickness)
    res = 128
    sc.caustic_bake.resolution = res
    before = _render(str(tmp_path / "before.exr"))
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    assert water.use_raytrace_refraction and sc.eevee.use_raytracing
    assert "EEVEE: turned on Water, scene raytracing, screen tracing thickness" in sc.caustic_bake.last_plan  # the panel's lines
    after = _render(str(tmp_path / "after.exr"))
    added = (after - before).mean(axis=2)
    img = bpy.data.images["CausticBake PoolFloor"]
    tex = np.empty(res * res * 4, dtype=np.float32)
    img.pixels.foreach_get(tex)
    E = tex.reshape(res, res, 4)[:, :, :3].mean(axis=2)
    group = next(n for n in bpy.data.objects["PoolFloor"].material_slots[0].material.node_tree.nodes
                 if n.name.startswith("CausticBake Group"))
    albedo = np.array(group.inputs["Base Color"].default_value[:3]).mean()
    texel = _floor_texel_under_pixels(sc, "PoolFloor", "Water", res, PIXELS, 1.33)
    under = texel[:, :, 0] >= 0
    expect = np.where(under, albedo * E[texel[:, :, 0], texel[:, :, 1]] / np.pi, 0.0)
    k = 4
    blocks = lambda a: a.reshape(PIXELS // k, k, PIXELS // k, k).sum(axis=(1, 3))  # noqa: E731
    full = blocks(under.astype(float)) == k * k
    assert full.sum() >= 30, full.sum()
    got = blocks(np.where(under, added, 0.0))[full] / k ** 2
    want = blocks(expect)[full] / k ** 2
    ratio = got.mean() / want.mean()
    corr = np.corrcoef(got, want)[0, 1]
    print(f"under the water: rendered / expected {ratio:.3f}, correlation {corr:.3f} over {full.sum()} blocks")
    assert 0.6 <= ratio <= 1.2
    assert corr >= 0.3
    assert bpy.ops.caustics.clear() == {"FINISHED"}
    assert (water.use_raytrace_refraction, sc.eevee.use_raytracing) == settings0[:2]
    assert sc.eevee.ray_tracing_options.screen_trace_thickness == settings0[2]
    assert water.get("caustic_bake_eevee") is None and sc.get("caustic_bake_eevee") is None
