"""Generate the sample scenes in sample_blends/ (run with the bpy module or Blender).

    .venv/bin/python sample_blends/make_samples.py            # all of them
    .venv/bin/python sample_blends/make_samples.py mirror_plane water_pool

Scenes (metres, Z up; every floor is a 4 m receiver plane with a UV map, materials pick the
caster roles, see addon/bake/extract.py):

- mirror_plane.blend: a tilted square mirror (Principled, metallic 1, roughness 0) above the
  floor and a point light between them: chain R, the analytic image-source caustic.
- metal_ring.blend: a metal ring (tube, smooth walls, sharp rims) on the floor under a low
  sun: chain R, the coffee-cup cardioid.
- glass_sphere.blend: a smooth glass sphere (Glass BSDF, IOR 1.5) above the floor, point
  light: chains TT (the focus) and R.
- water_pool.blend: a water surface (grid with a Displace modifier, then a Subdivision
  Surface modifier: smooth, 73,728 triangles; Principled transmission, IOR 1.33) over a pool
  floor, lit by a point light and a sun: chain T (animated: frames 1..48 move the waves).
- glass_slab.blend: a flat glass slab (box, Glass BSDF) above the floor: chains TT and R.

Each scene has a camera, Cycles set up for a quick preview render, and the settings EEVEE
needs to show the bake through glass and water (raytraced refraction on the glass and water
materials, scene raytracing, a screen-tracing thickness that reaches the floor).
"""

import math
import os
import sys

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))


def _reset():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = 64
    sc.cycles.use_denoising = False
    sc.render.resolution_x = 480
    sc.render.resolution_y = 360
    sc.view_settings.view_transform = "AgX"
    # EEVEE: raytracing (mirrors and glass would show dark without it) with a screen-tracing
    # thickness that lets refracted rays reach the floor behind water and glass (Blender's
    # 0.2 lets them pass behind it; apply.eevee_settings_for_casters does the same for a user's scene)
    sc.eevee.use_raytracing = True
    sc.eevee.ray_tracing_options.screen_trace_thickness = 6.0
    sc.eevee.taa_render_samples = 32
    world = bpy.data.worlds.new("World")
    world.color = (0.02, 0.02, 0.025)
    if world.node_tree is None:
        world.use_nodes = True
    bg = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    bg.inputs["Color"].default_value = (0.02, 0.02, 0.025, 1.0)
    sc.world = world
    return sc


def _material(name, kind, color=(0.8, 0.8, 0.8), ior=1.5, roughness=0.0):
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if kind == "glass":
        bsdf = nt.nodes.new("ShaderNodeBsdfGlass")
        bsdf.inputs["Color"].default_value = (*color, 1.0)
        bsdf.inputs["IOR"].default_value = ior
        bsdf.inputs["Roughness"].default_value = roughness
    else:
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        bsdf.inputs["Roughness"].default_value = roughness if kind != "diffuse" else 1.0
        if kind == "metal":
            bsdf.inputs["Metallic"].default_value = 1.0
        elif kind == "water":
            bsdf.inputs["Transmission Weight"].default_value = 1.0
            bsdf.inputs["IOR"].default_value = ior
    bsdf.location = (-300, 0)
    nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    if kind in ("glass", "water"):
        mat.use_raytrace_refraction = True  # EEVEE draws refraction opaque without it
    return mat


def _floor(size=4.0, name="Floor"):
    bpy.ops.mesh.primitive_plane_add(size=size, location=(0, 0, 0))
    ob = bpy.context.object
    ob.name = name
    ob.data.materials.append(_material("Floor", "diffuse", (0.8, 0.8, 0.8)))
    return ob


def _camera(location, target, lens=35.0):
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    bpy.context.collection.objects.link(cam)
    cam.location = location
    d = [t - l for t, l in zip(target, location)]
    cam.rotation_euler = (math.atan2(math.hypot(d[0], d[1]), -d[2]), 0.0, math.atan2(d[1], d[0]) - math.pi / 2)
    cam.data.lens = lens
    bpy.context.scene.camera = cam
    return cam


def _light(kind, name, energy, location=(0, 0, 0), rotation=(0, 0, 0), **props):
    data = bpy.data.lights.new(name, kind)
    data.energy = energy
    for k, v in props.items():
        setattr(data, k, v)
    ob = bpy.data.objects.new(name, data)
    bpy.context.collection.objects.link(ob)
    ob.location = location
    ob.rotation_euler = rotation
    return ob


def mirror_plane():
    _reset()
    _floor()
    bpy.ops.mesh.primitive_plane_add(size=1.5, location=(0, 0, 2.0), rotation=(math.radians(180 + 20), 0, 0))
    mirror = bpy.context.object
    mirror.name = "Mirror"
    mirror.data.materials.append(_material("Mirror", "metal", (0.95, 0.95, 0.95)))
    _light("POINT", "Point", 150.0, (0.4, 0.3, 1.0), shadow_soft_size=0.0)
    _camera((4.0, -4.0, 3.5), (0.0, 0.0, 0.5))


def metal_ring():
    _reset()
    _floor()
    seg, r_in, r_out, h = 96, 1.0, 1.06, 0.5
    verts, faces = [], []
    for k in range(seg):
        a = 2 * math.pi * k / seg
        c, s = math.cos(a), math.sin(a)
        verts += [(r_in * c, r_in * s, 0.0), (r_in * c, r_in * s, h), (r_out * c, r_out * s, h), (r_out * c, r_out * s, 0.0)]
    for k in range(seg):
        a, b = 4 * k, 4 * ((k + 1) % seg)
        faces += [(a, b, b + 1, a + 1),  # inner wall (faces the axis)
                  (a + 1, b + 1, b + 2, a + 2),  # top rim
                  (a + 2, b + 2, b + 3, a + 3),  # outer wall
                  (a + 3, b + 3, b, a)]  # bottom rim
    me = bpy.data.meshes.new("Ring")
    me.from_pydata(verts, [], faces)
    me.validate()
    me.shade_smooth()
    me.set_sharp_from_angle(angle=math.radians(30))
    ring = bpy.data.objects.new("Ring", me)
    bpy.context.collection.objects.link(ring)
    me.materials.append(_material("Gold", "metal", (1.0, 0.78, 0.34)))
    # Low sun from +x: the cardioid opens towards it.
    _light("SUN", "Sun", 2.0, rotation=(math.radians(90 - 25), 0.0, math.radians(90)), angle=math.radians(0.5))
    _camera((0.0, -3.2, 3.6), (0.0, 0.0, 0.0))


def glass_sphere():
    _reset()
    _floor()
    bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24, radius=0.5, location=(0, 0, 1.0))
    sphere = bpy.context.object
    sphere.name = "GlassSphere"
    bpy.ops.object.shade_smooth()
    sphere.data.materials.append(_material("Glass", "glass", (1.0, 1.0, 1.0), ior=1.5))
    _light("POINT", "Point", 300.0, (0.0, 0.0, 3.0), shadow_soft_size=0.0)
    _camera((3.0, -3.0, 2.6), (0.0, 0.0, 0.4))


def water_pool():
    _reset()
    floor = _floor(name="PoolFloor")
    floor.data.materials[0] = _material("Tiles", "diffuse", (0.55, 0.75, 0.85))
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=48, y_subdivisions=48, size=4.0, location=(0, 0, 1.0))
    water = bpy.context.object
    water.name = "Water"
    bpy.ops.object.shade_smooth()
    # Rolling waves: a Displace modifier with a Clouds texture in the frame of an empty that
    # drifts over frames 1..48 (so --frames bakes an animation).
    tex = bpy.data.textures.new("Waves", "CLOUDS")
    tex.noise_scale = 0.45
    tex.noise_depth = 1
    driver = bpy.data.objects.new("WaveDriver", None)
    bpy.context.collection.objects.link(driver)
    driver.location = (0.0, 0.0, 0.0)
    driver.keyframe_insert("location", frame=1)
    driver.location = (0.6, 0.35, 0.0)
    driver.keyframe_insert("location", frame=48)
    disp = water.modifiers.new("Waves", "DISPLACE")
    disp.texture = tex
    disp.texture_coords = "OBJECT"
    disp.texture_coords_object = driver
    disp.strength = 0.12
    disp.mid_level = 0.5
    # Smooth water: the 48 x 48 grid's interpolated normals would show the mesh as a grid of
    # blocks in the caustic (true to the model); Catmull-Clark after the waves gives a smooth
    # surface of 73,728 triangles (about a texel each at 512²)
    subd = water.modifiers.new("Smooth", "SUBSURF")
    subd.levels = subd.render_levels = 2
    water.data.materials.append(_material("Water", "water", (1.0, 1.0, 1.0), ior=1.33))
    _light("POINT", "Point", 150.0, (0.3, -0.2, 3.0), shadow_soft_size=0.0)
    _light("SUN", "Sun", 1.0, rotation=(math.radians(20), 0.0, math.radians(30)), angle=math.radians(0.5))
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 48
    _camera((3.5, -3.5, 4.0), (0.0, 0.0, 0.3))


def glass_slab():
    _reset()
    _floor()
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 1.0))
    slab = bpy.context.object
    slab.name = "GlassSlab"
    slab.scale = (1.2, 1.2, 0.12)
    slab.data.materials.append(_material("Glass", "glass", (1.0, 1.0, 1.0), ior=1.5))
    _light("POINT", "Point", 300.0, (0.5, 0.2, 3.0), shadow_soft_size=0.0)
    _camera((3.0, -3.0, 2.6), (0.0, 0.0, 0.4))


SCENES = {"mirror_plane": mirror_plane, "metal_ring": metal_ring, "glass_sphere": glass_sphere, "water_pool": water_pool, "glass_slab": glass_slab}


def main(names):
    for name in names or list(SCENES):
        SCENES[name]()
        path = os.path.join(HERE, name + ".blend")
        bpy.ops.wm.save_as_mainfile(filepath=path, compress=True)
        if os.path.exists(path + "1"):
            os.remove(path + "1")  # Blender's backup of the previous version
        print(f"wrote {path} ({os.path.getsize(path) / 1024:.0f} KiB)")


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    main(argv)
