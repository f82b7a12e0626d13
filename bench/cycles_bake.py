"""Cycles' own shadow caustics (MNEE) baked into the receivers' textures, in our units.

    cc = CyclesCaustics(model, resolution)   # the .blend ``model`` came from is open in bpy
    images, seconds, parts = cc.bake(samples=256, seed=1)
    open_blend(path)                         # the bpy scene is modified: reopen it afterwards

``images[receiver]`` is an (H, W, 3) float64 array of caustic irradiance in W/m² with the
layout of ``addon.bake.pipeline.BakeResult.raw`` (row 0 = v = 0, as Blender stores pixels; the
texel order is checked against our bakes in tests/bake/test_cycles_caustics.py), i.e. directly
comparable with our bakes and the chart's photon reference.

How it is measured
------------------
The open scene is set up for Cycles' Manifold Next Event Estimation ("Shadow Caustics"):
``light.cycles.is_caustics_light``, ``object.cycles.is_caustics_caster`` on every object our
scene model gives a refracting role (``refract`` or ``both``; MNEE walks refractive
interfaces only, so reflection-only scenes raise :class:`CyclesUnavailable`) and
``object.cycles.is_caustics_receiver`` on every receiver.  Each receiver's material is
replaced by a plain white Diffuse BSDF (roughness 0: Lambertian) with an active image node,
and Cycles bakes ``type='DIFFUSE'``, ``pass_filter={'DIRECT', 'INDIRECT'}`` (no COLOR),
``margin=0`` onto the receiver's UV map (the one our model uses, made active).

Units.  A diffuse light pass without colour is the reflected radiance divided by the
albedo: for a Lambertian surface L = albedo E / pi, so the pass holds E / pi and

    E [W/m²] = pi x baked value.

This is the relation tests/bake/test_bake_units.py pins down for renders; here it is checked on
the bake itself: pi x (Cycles' bake of the glass sphere's floor without the caustic, i.e. its
direct light, 1024 spp) / our ``direct=True`` bake = 1.0009 (median over lit texels, 5-95 %:
0.9998-1.0035); tests/bake/test_cycles_caustics.py asserts it on the (asymmetric) glass slab,
which also fixes the texel order (a flipped or transposed image fails it).  And through the
casters: inside the glass slab's caustic (chain TT, away from its border and from the hole
below) Cycles / our photon bake = 1.0002 (48², 1024 spp, 8M photons; per texel 5-95 %:
0.9987-1.0017).

Isolating the caustic.  Cycles' bake holds the direct light too, and MNEE cannot be baked
alone: its contribution is written as *indirect* light (the shadow path's bounce counter is
the number of MNEE vertices) but computed in the direct-light step, and bakes with only
DIRECT, only INDIRECT, or max_bounces 0 all have no caustic at all (checked on the slab,
casters on minus off: 0.0 each, against 1150 with both passes).  So every knob value costs two bakes with the same seed: casters on, then casters
off (``is_caustics_caster = False``), and

    caustic = pi x (bake_on - bake_off).

With the same seed and a fixed sample count the two bakes draw the same random numbers, so
the direct light (and the world, any diffuse interreflection) cancels texel by texel, not
just in expectation: outside the caustic the difference is exactly 0.  With the casters off
a refracting object simply blocks shadow rays, so what the subtraction leaves is MNEE's
light through the casters.  For that to be all it leaves, path tracing must not find
caustics of its own (it would in the off bake, where MNEE does not cull them):

- ``caustics_refractive`` must stay **on**: MNEE evaluates the caster's shader as after a
  diffuse bounce, and with refractive caustics off Cycles strips the refraction closure
  there, so MNEE finds nothing (checked: a zero caustic).
- ``caustics_reflective`` off, ``blur_glossy`` (Filter Glossy) 0: a blurred glass after a
  diffuse bounce gets next-event estimation, a path-traced (blurred) caustic in the off bake.
- lights invisible to glossy and transmission rays: a sun with an angle (water_pool's,
  0.5 degrees) can be hit by a floor -> water -> sun path; in the off bake that is a firefly
  caustic (measured: the subtraction went to -200 W/m² in places, a 0.12 energy ratio);
  with it hidden the difference is >= 0 everywhere.  The diffuse floor's own direct light
  (and its MIS companion, diffuse rays) is unaffected.
- the world removed: our bakes have no world light, and the world would also be a light in
  Cycles' light selection (see the sun bug below).
- no sample clamping (``sample_clamp_direct`` / ``_indirect`` 0; the default indirect clamp
  of 10 would apply to the MNEE light), adaptive sampling off (the two bakes must take the
  same samples), ``light_sampling_threshold`` 0, denoising off.
- ``diffuse_bounces`` 1.  MNEE counts as a diffuse bounce (with 0, or max_bounces 1, it is
  gone), so 1 is the least that keeps it, and it stops MNEE at later vertices of the path:
  the caustic reflected by the (white) receiver and sent back by the glass, light our chains
  do not have (0.9 % of the slab's caustic, and the only thing the subtraction left outside
  it: 0.01-0.02 W/m² per texel).  The other bounce limits are the scene's.

Time: wall seconds of every ``bpy.ops.object.bake`` call (scene sync, BVH, kernels, both
bakes of every receiver), measured around them.

What Cycles gets right and wrong here (measured at 48², 256-1024 spp, against our photon bake
of the same chains; glass_slab and glass_sphere chain TT, water_pool chain T):

- Direct light and the slab's TT caustic: exact (above).
- Receivers inside a refracting medium (a pool floor under an open water surface, chain T):
  Cycles' irradiance is E / eta², eta the medium's IOR.  Measured ratio Cycles / photon with
  the water_pool's point light: 0.825 (IOR 1.1; 1/eta² = 0.826), 0.570 (1.33; 0.565),
  0.451 (1.5; 0.444).  Cycles does not scale radiance by eta² across a refraction (a clear
  glass path has throughput 1 - F), so radiance, and the E / pi of a diffuse receiver, is
  kept in "air units"; seen back through the same interface the render is right.  Our bakes
  hold the physical flux / area.  :meth:`CyclesCaustics.bake` converts (``medium_ior``: the
  IOR of the open refracting surfaces when the scene has no closed ones, else 1) and reports
  the factor; for TT through a closed solid the factors cancel.
- A sun among several lights: Cycles' MNEE applies the light-selection probability twice
  for distant lights (``light_sample_update`` keeps a sun sample's pdf, selection included,
  then multiplies the selection pdf again), so a sun's caustic comes out 1 / P(select) too
  bright: water_pool (point + sun) baked together gave 10,469 (sum over the floor), the two
  lights baked one at a time 4,226 (point) + 3,112 (sun): the sun twice over, P = 1/2.  So when a scene has a sun and more than one
  light, every light is baked on its own (the others hidden from render) and the results
  added; the time is the sum.
- Missed light, inherent in MNEE's seeding (one straight receiver -> light ray; one solution
  per sample): the caustic ends where the straight ray leaves the caster's silhouette, not
  where the refracted beam ends (a texel-wide shift of the slab caustic's border; the part
  of the water_pool sun caustic entering the water beside the floor strip lit directly);
  folds with several paths per point get one; and the Newton walk fails in a disc of
  ~0.2 m radius around the light's nadir under the glass slab (seen in renders too, so not a
  bake artefact).  Its generalised geometry term is clamped at 2, which cuts the brightest
  focus: the glass sphere's focal texels are 28 W/m² against 91 (total energy 0.52).
  Totals, Cycles / photon of the same chains: glass_slab 0.916, water_pool 0.982 (converted;
  raw 0.555), glass_sphere 0.52.
- Meshes: MNEE rejects a caster without smooth normals.  glass_slab's box is flat-shaded, and
  smooth faces with all edges sharp are still flat to Cycles (the mesh's normal domain becomes
  FACE), so casters that are not plain smooth are split along their sharp edges and shaded
  smooth: each face keeps its own vertices and normals (the largest change of a corner
  normal is reported in ``notes``; 0 for the slab).
"""

import math
import time

import numpy as np

import bpy

from addon.bake.scene import ROLE_BOTH, ROLE_NONE, ROLE_REFLECT, ROLE_REFRACT

IMAGE_PREFIX = "CBcycles "
REFRACTING = (ROLE_REFRACT, ROLE_BOTH)


class CyclesUnavailable(Exception):
    """The scene has no caustic Cycles can render (reflection only); the reason is the message."""


def _split_sharp(me):
    """Give Cycles smooth-shaded triangles with the same normals: split ``me`` along its sharp
    edges and the edges of its flat faces, then shade every face smooth (see the module
    docstring).  Returns the largest change of a corner normal."""
    import bmesh

    before = np.empty(len(me.loops) * 3)
    me.corner_normals.foreach_get("vector", before)
    bm = bmesh.new()
    bm.from_mesh(me)
    edges = [e for e in bm.edges if not e.smooth or any(not f.smooth for f in e.link_faces)]
    bmesh.ops.split_edges(bm, edges=edges)
    for f in bm.faces:
        f.smooth = True
    for e in bm.edges:
        e.smooth = True
    bm.to_mesh(me)
    bm.free()
    me.update()
    after = np.empty(len(me.loops) * 3)
    me.corner_normals.foreach_get("vector", after)
    if after.shape != before.shape:
        return float("inf")
    return float(np.abs(after - before).max()) if before.size else 0.0


def medium_ior(model):
    """The IOR of the medium the receivers lie in, as Cycles' units need it: the IOR of the
    scene's open refracting surfaces (water) when it has no closed refracting solids, else 1
    (light through a solid leaves it again).  Raises CyclesUnavailable for a mix of both, or
    open surfaces of different IORs (the factor would differ per chain / texel)."""
    refr = np.isin(model.tri_role, REFRACTING)
    if not refr.any():
        return 1.0
    closed = model.closed_objects()
    objs = set(np.unique(model.tri_object[refr]).tolist())
    open_objs = objs - closed
    if not open_objs:
        return 1.0
    if objs & closed:
        raise CyclesUnavailable("open and closed refracting objects: the receivers' medium is ambiguous")
    iors = np.unique(np.round(model.tri_ior[refr & np.isin(model.tri_object, list(open_objs))], 6))
    if iors.size != 1:
        raise CyclesUnavailable(f"open refracting surfaces of different IORs {iors.tolist()}")
    return float(iors[0])


class CyclesCaustics:
    """The open bpy scene (the one ``model`` was extracted from), set up to bake Cycles' MNEE
    caustics onto ``model``'s receivers at ``resolution`` texels per side.  Modifies the bpy
    scene (materials, flags, settings, caster meshes): reopen the .blend afterwards."""

    def __init__(self, model, resolution):
        sc = bpy.context.scene
        self.scene = sc
        self.res = int(resolution)
        roles = {}
        for oi, role in zip(model.tri_object.tolist(), model.tri_role.tolist()):
            if role != ROLE_NONE:
                roles.setdefault(model.objects[oi], set()).add(role)
        self.casters = sorted(n for n, r in roles.items() if r - {ROLE_REFLECT})
        if not self.casters:
            raise CyclesUnavailable("Cycles MNEE cannot render reflection caustics")
        self.ior = medium_ior(model)
        self.receivers = [r.name for r in model.receivers]
        self.notes = []
        c = sc.cycles
        sc.render.engine = "CYCLES"
        c.device = "CPU"
        c.use_adaptive_sampling = False
        c.use_denoising = False
        c.use_animated_seed = False
        c.sample_clamp_direct = 0.0
        c.sample_clamp_indirect = 0.0
        c.light_sampling_threshold = 0.0
        c.blur_glossy = 0.0
        c.diffuse_bounces = 1
        c.caustics_refractive = True
        c.caustics_reflective = False
        sc.world = None
        light_names = {lt.name for lt in model.lights}
        self.lights = [ob.name for ob in sc.objects if ob.type == "LIGHT" and ob.name in light_names]
        for name in self.lights:
            ob = bpy.data.objects[name]
            ob.data.cycles.is_caustics_light = True
            ob.visible_glossy = False
            ob.visible_transmission = False
        has_sun = any(bpy.data.objects[n].data.type == "SUN" for n in self.lights)
        self.per_light = has_sun and len(self.lights) > 1
        if self.per_light:
            self.notes.append("one light at a time (Cycles' MNEE over-weights a sun among several lights)")
        for name in self.casters:
            ob = bpy.data.objects[name]
            if ob.type == "MESH" and ob.data.normals_domain != "POINT":
                d = _split_sharp(ob.data)
                self.notes.append(f"{name}: split along sharp edges and shaded smooth for MNEE (normals changed by {d:.1e})")
            ob.cycles.is_caustics_caster = True
        if self.ior != 1.0:
            self.notes.append(f"x {self.ior:g}² (receivers under an open refracting surface of IOR {self.ior:g})")
        self.images = {}
        for rec in model.receivers:
            ob = bpy.data.objects[rec.name]
            ob.cycles.is_caustics_receiver = True
            layer = ob.data.uv_layers.get(rec.uv_map)
            if layer is not None:
                ob.data.uv_layers.active = layer  # the map Cycles bakes into
            mat = bpy.data.materials.new(IMAGE_PREFIX + rec.name)
            nt = mat.node_tree
            for nd in list(nt.nodes):
                nt.nodes.remove(nd)
            out = nt.nodes.new("ShaderNodeOutputMaterial")
            dif = nt.nodes.new("ShaderNodeBsdfDiffuse")
            dif.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
            dif.inputs["Roughness"].default_value = 0.0
            nt.links.new(dif.outputs[0], out.inputs["Surface"])
            img = bpy.data.images.new(IMAGE_PREFIX + rec.name, self.res, self.res, alpha=False, float_buffer=True)
            img.colorspace_settings.name = "Non-Color"
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image = img
            nt.nodes.active = tex
            ob.data.materials.clear()
            ob.data.materials.append(mat)
            self.images[rec.name] = img

    def _bake_receivers(self):
        sc = self.scene
        out = {}
        for name in self.receivers:
            ob = bpy.data.objects[name]
            for o in sc.objects:
                o.select_set(False)
            ob.select_set(True)
            bpy.context.view_layer.objects.active = ob
            bpy.ops.object.bake(type="DIFFUSE", pass_filter={"DIRECT", "INDIRECT"}, margin=0, use_clear=True,
                                target="IMAGE_TEXTURES")
            px = np.empty(self.res * self.res * 4, dtype=np.float32)
            self.images[name].pixels.foreach_get(px)
            out[name] = px.reshape(self.res, self.res, 4)[..., :3].astype(np.float64)
        return out

    def _bake_pair(self, samples, seed):
        """(on, off): the raw bakes with the casters on and off, same seed."""
        self.scene.cycles.samples = int(samples)
        self.scene.cycles.seed = int(seed)
        pair = []
        for on in (True, False):
            for name in self.casters:
                bpy.data.objects[name].cycles.is_caustics_caster = on
            pair.append(self._bake_receivers())
        for name in self.casters:
            bpy.data.objects[name].cycles.is_caustics_caster = True
        return pair

    def bake(self, samples, seed=1):
        """``(images, seconds, parts)``: images {receiver: (H, W, 3) caustic irradiance W/m², our
        units}; seconds: wall time of all the Cycles bakes; parts: {"on": [...], "off": [...],
        "factor": pi x ior²} with the raw bakes (one dict per light when baked per light)."""
        factor = math.pi * self.ior ** 2
        images = {name: np.zeros((self.res, self.res, 3)) for name in self.receivers}
        parts = dict(on=[], off=[], factor=factor)
        groups = [[n] for n in self.lights] if self.per_light else [self.lights]
        seconds = 0.0
        try:
            for group in groups:
                for name in self.lights:
                    bpy.data.objects[name].hide_render = name not in group
                t0 = time.perf_counter()
                on, off = self._bake_pair(samples, seed)
                seconds += time.perf_counter() - t0
                for name in self.receivers:
                    images[name] += factor * (on[name] - off[name])
                parts["on"].append(on)
                parts["off"].append(off)
        finally:
            for name in self.lights:
                bpy.data.objects[name].hide_render = False
        return images, seconds, parts
