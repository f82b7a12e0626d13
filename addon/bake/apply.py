"""Baked textures -> Blender images and material nodes, and the exact undo.  Touches bpy.

``apply_bake`` gives every receiver object an Image ("CausticBake <object>", float, Non-Color,
loaded from the EXR :func:`write_textures` wrote, e.g. ``//caustics/<blend>/<receiver>.exr``
with the path stored relative to the .blend, or packed into the .blend) and inserts into each of its materials, between the surface shader and the Material Output,
the node group "CausticBake":

    Surface out = Shader + Emission(colour = Base Color x Irradiance / pi, strength 1)

with Irradiance from an Image Texture node on the receiver's UV map and Base Color linked
from (or copied from) the surface BSDF's base colour.  A diffuse surface of albedo rho under
irradiance E reflects radiance rho E / pi, so Cycles and EEVEE both show the caustic the way
they would show direct light.  (Receivers under a refractive surface: Cycles' own MNEE
caustics give about E / n² there because it skips the n² radiance scaling; this bakes the
physical irradiance.)

A frame range (:func:`write_sequence_frame` per finished frame into a staging folder,
:func:`publish_sequence_frames` when the range ends, then :func:`apply_sequence`)
gives every receiver an Image with source ``SEQUENCE`` over the EXR sequence named by
:func:`addon.bake.names.texture_filename` (``<receiver>.<frame>.exr``, the CLI's names), and
its Image Texture node's image user maps the scene frame to the file of that frame
(``frame_start`` = first frame, ``frame_offset`` = first frame - 1, ``frame_duration`` = the
frames baked, auto refresh on), so that timeline playback and Cycles and EEVEE renders show each
frame's caustic; after the last frame the last one shows (before the first, Blender's image user
asks for the frame before it, which was not baked).  A sequence is never packed (Blender cannot
pack image sequences).

What changed is recorded on the data itself (a JSON custom property on each material and
object touched, and a tag on images), so ``clear_bake`` removes all of it and restores the
materials exactly: the added nodes go, the original surface links come back, material copies
made for receivers that share a material with other objects are removed and the slots
restored, and the images and node group (found by its tag, not its name) are deleted.  With
``delete_files`` it also deletes the sequence files the images list (``caustic_bake_files``)
that Caustic Bake wrote (the folder's manifest, :data:`FILES_MANIFEST`); a user's file is
never deleted or overwritten.  Files are written all or nothing before anything in Blender
changes (:mod:`addon.bake.output`), so a failed write leaves the previous bake as it was.

EEVEE cannot compute caustics, and it draws refracting materials opaque and mirrors dark
unless raytracing is on: :func:`eevee_settings_for_casters` turns on the refracting casters'
raytraced refraction and the scene's raytracing where they were off (recorded, restored by
``clear_bake``), so the caustic baked under water or glass shows in EEVEE too
(tests/ui/test_ui_eevee.py).
"""

import json
import math
import os

import bpy
import numpy as np

from . import output
from .names import texture_filename
from .output import FILES_MANIFEST  # noqa: F401  (the folder's list of the files Caustic Bake wrote)

GROUP_NAME = "CausticBake"
NODE_PREFIX = "CausticBake"
STATE_KEY = "caustic_bake_state"
SLOT_KEY = "caustic_bake_slots"
TAG_KEY = "caustic_bake"
FILES_KEY = "caustic_bake_files"  # on a sequence image: JSON [absolute folder, [file names]]
EEVEE_KEY = "caustic_bake_eevee"  # on a material / scene: JSON of the EEVEE settings the bake changed (to restore)
BASE_COLOR_INPUTS = {"BSDF_PRINCIPLED": "Base Color", "BSDF_DIFFUSE": "Color", "BSDF_SHEEN": "Color", "BSDF_TOON": "Color"}


def node_groups():
    """The add-on's own node groups: those tagged with :data:`TAG_KEY` (a user's group that is
    merely named "CausticBake" is not one of them)."""
    return [g for g in bpy.data.node_groups if g.get(TAG_KEY)]


def ensure_node_group():
    """The shared "CausticBake" shader node group (created once; found by its tag, not its name)."""
    for group in node_groups():
        if group.bl_idname == "ShaderNodeTree":
            return group
    group = bpy.data.node_groups.new(GROUP_NAME, "ShaderNodeTree")
    group[TAG_KEY] = True
    iface = group.interface
    iface.new_socket("Shader", in_out="INPUT", socket_type="NodeSocketShader")
    base = iface.new_socket("Base Color", in_out="INPUT", socket_type="NodeSocketColor")
    base.default_value = (0.8, 0.8, 0.8, 1.0)
    irr = iface.new_socket("Irradiance", in_out="INPUT", socket_type="NodeSocketColor")
    irr.default_value = (0.0, 0.0, 0.0, 1.0)
    iface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    nodes, links = group.nodes, group.links
    gin = nodes.new("NodeGroupInput")
    gin.location = (-600, 0)
    gout = nodes.new("NodeGroupOutput")
    gout.location = (400, 0)
    mul = nodes.new("ShaderNodeVectorMath")
    mul.operation = "MULTIPLY"
    mul.location = (-350, -150)
    scale = nodes.new("ShaderNodeVectorMath")
    scale.operation = "SCALE"
    scale.inputs["Scale"].default_value = 1.0 / math.pi
    scale.location = (-150, -150)
    emit = nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    emit.location = (50, -150)
    add = nodes.new("ShaderNodeAddShader")
    add.location = (220, 0)
    links.new(gin.outputs["Base Color"], mul.inputs[0])
    links.new(gin.outputs["Irradiance"], mul.inputs[1])
    links.new(mul.outputs["Vector"], scale.inputs[0])
    links.new(scale.outputs["Vector"], emit.inputs["Color"])
    links.new(gin.outputs["Shader"], add.inputs[0])
    links.new(emit.outputs["Emission"], add.inputs[1])
    links.new(add.outputs["Shader"], gout.inputs["Shader"])
    return group


def _socket_by_id(sockets, identifier):
    for s in sockets:
        if s.identifier == identifier:
            return s
    return None


def _material_users(mat):
    return [o for o in bpy.data.objects if any(s.material == mat for s in o.material_slots)]


def foreign_files(object_names, directory, frames=None):
    """The files :func:`apply_bake` (or with ``frames``, :func:`write_sequence_frame` for those
    frames) would write over in ``directory`` that Caustic Bake did not write there itself (a
    user's own files, never overwritten); [] when ``directory`` is None."""
    if directory is None:
        return []
    names = list(object_names)
    fnames = [texture_filename(n, f, receivers=names) for n in names for f in (frames or [None])]
    return output.foreign_files(bpy.path.abspath(directory), fnames)


def write_textures(images, directory, frame=None):
    """Write ``images`` ({receiver: (H, W, 3) irradiance}) into ``directory`` (absolute, or
    relative to the .blend with //) under :func:`~addon.bake.names.texture_filename`'s names
    (of ``frame`` in a sequence), all or nothing (:func:`addon.bake.output.write_textures`:
    :class:`~addon.bake.output.OutputError` leaves the folder as it was), recorded as written
    by Caustic Bake.  A file there that Caustic Bake did not write is never overwritten
    (FileExistsError, before anything is written).  Returns {receiver name: absolute path}."""
    abs_dir = bpy.path.abspath(directory)
    clash = foreign_files(images, directory, None if frame is None else [frame])
    if clash:
        raise FileExistsError(f"{clash[0]} exists and was not written by Caustic Bake; choose another output folder")
    names = {n: texture_filename(n, frame, receivers=images) for n in images}
    paths = output.write_textures(abs_dir, {names[n]: img for n, img in images.items()})
    return {n: paths[names[n]] for n in images}


SEQUENCE_STAGING = ".caustic-bake-staging"  # a frame range's finished frames, until they replace the earlier ones


def write_sequence_frame(images, directory, frame):
    """Write one frame of a sequence: per receiver ``images[name]`` ((H, W, 3) irradiance) to
    ``directory``/``SEQUENCE_STAGING``/:func:`~addon.bake.names.texture_filename` (name,
    frame), all or nothing (:func:`write_textures`): the earlier bake's frames in
    ``directory`` stay as they are until :func:`publish_sequence_frames`.  Returns {receiver
    name: absolute path of the staged file}."""
    return write_textures(images, _staging(directory), frame)


def _staging(directory):
    return directory.rstrip("/\\") + "/" + SEQUENCE_STAGING


def publish_sequence_frames(receivers, directory, frames):
    """Move the staged frames ``frames`` of ``receivers`` (:func:`write_sequence_frame`) into
    ``directory`` (:func:`addon.bake.output.move_files`: recorded as written by Caustic Bake
    first, then each file renamed over the earlier one) and remove the staging folder.  Returns {frame:
    {receiver name: absolute path}}.  Raises :class:`~addon.bake.output.OutputError`."""
    names = {(f, n): texture_filename(n, f, receivers=receivers) for f in frames for n in receivers}
    paths = output.move_files(bpy.path.abspath(_staging(directory)), bpy.path.abspath(directory), list(names.values()))
    discard_staged_frames(directory)
    done = {}
    for (f, n), name in names.items():
        done.setdefault(f, {})[n] = paths[name]
    return done


def discard_staged_frames(directory):
    """Remove the staging folder of a frame range (:func:`write_sequence_frame`), if any."""
    import shutil

    shutil.rmtree(bpy.path.abspath(_staging(directory)), ignore_errors=True)


def _relative_path(directory, path):
    """``path`` as Blender should store it: relative to the .blend (//...) when ``directory`` is."""
    if directory is not None and directory.startswith("//"):
        return directory.rstrip("/\\") + "/" + os.path.basename(path)
    return path


def make_image(name, pixels_rgb, directory=None, pack=False, source=None):
    """An Image from (H, W, 3) irradiance (row 0 = bottom): loaded from ``source`` (an EXR of
    these pixels already written, e.g. by :func:`write_textures` or the CLI; its path stored
    relative to the .blend when ``directory`` starts with //) and packed if asked; without a
    source, a packed image holding the pixels."""
    import numpy as np

    H, W = pixels_rgb.shape[:2]
    old = bpy.data.images.get(name)
    if old is not None and old.get(TAG_KEY):
        bpy.data.images.remove(old)
    if source is not None and os.path.isfile(source):
        img = bpy.data.images.load(os.path.abspath(source), check_existing=False)
        img.name = name
        img.filepath = _relative_path(directory, source)
        if pack:
            img.pack()
    else:
        img = bpy.data.images.new(name, W, H, float_buffer=True, alpha=False)
        rgba = np.ones((H, W, 4), dtype=np.float32)
        rgba[:, :, :3] = pixels_rgb
        img.pixels.foreach_set(rgba.reshape(-1))
        img.pack()
    img.colorspace_settings.name = "Non-Color"
    img[TAG_KEY] = True
    return img


def _insert_nodes(mat, image, uv_map, group, frames=None):
    """Insert the CausticBake nodes into ``mat``; return its state record.  ``frames`` (a
    sequence image's contiguous frames): the texture node's image user maps scene frame f to
    the file of frame f."""
    nt = mat.node_tree
    outputs = []
    for target in ("CYCLES", "EEVEE", "ALL"):
        out = nt.get_output_node(target)
        if out is not None and out not in outputs:
            outputs.append(out)
    if not outputs:
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        out.name = NODE_PREFIX + " Output"
        outputs = [out]
    added, removed = [], []
    if outputs[0].name.startswith(NODE_PREFIX):
        added.append(outputs[0].name)
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.name = tex.label = NODE_PREFIX + " Irradiance"
    tex.image = image
    tex.interpolation = "Linear"
    tex.extension = "EXTEND"
    if frames:
        iu = tex.image_user
        iu.frame_duration = len(frames)
        iu.frame_start = frames[0]
        iu.frame_offset = frames[0] - 1
        iu.use_cyclic = False
        iu.use_auto_refresh = True
    uvn = nt.nodes.new("ShaderNodeUVMap")
    uvn.name = uvn.label = NODE_PREFIX + " UV"
    uvn.uv_map = uv_map
    nt.links.new(uvn.outputs["UV"], tex.inputs["Vector"])
    added += [tex.name, uvn.name]
    x0, y0 = outputs[0].location
    tex.location = (x0 - 300, y0 - 320)
    uvn.location = (x0 - 500, y0 - 320)
    for k, out in enumerate(outputs):
        surf = out.inputs["Surface"]
        gnode = nt.nodes.new("ShaderNodeGroup")
        gnode.node_tree = group
        gnode.name = gnode.label = f"{NODE_PREFIX} Group {k}"
        gnode.location = (out.location[0], out.location[1] + 160)
        added.append(gnode.name)
        src = None
        if surf.is_linked:
            link = surf.links[0]
            src = link.from_socket
            removed.append([link.from_node.name, link.from_socket.identifier, out.name, surf.identifier])
            nt.links.remove(link)
            nt.links.new(src, gnode.inputs["Shader"])
        nt.links.new(gnode.outputs["Shader"], surf)
        nt.links.new(tex.outputs["Color"], gnode.inputs["Irradiance"])
        bsdf = src.node if src is not None else None
        while bsdf is not None and bsdf.type == "REROUTE" and bsdf.inputs[0].is_linked:
            bsdf = bsdf.inputs[0].links[0].from_node
        name = BASE_COLOR_INPUTS.get(bsdf.type) if bsdf is not None else None
        base_in = bsdf.inputs.get(name) if name else None
        if base_in is not None and base_in.is_linked:
            nt.links.new(base_in.links[0].from_socket, gnode.inputs["Base Color"])
        elif base_in is not None:
            gnode.inputs["Base Color"].default_value = tuple(base_in.default_value)
        else:
            gnode.inputs["Base Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    return {"nodes": added, "links": removed}


def apply_bake(images, uv_maps, directory=None, pack=False, files=None):
    """Show baked irradiance on receivers.

    ``images``: {object name: (H, W, 3) irradiance array (row 0 = bottom)};
    ``uv_maps``: {object name: UV layer name}; ``files``: {object name: path of an EXR of that
    same array already on disk (the CLI's output)}: loaded as is instead of writing a second
    copy.  Without ``files`` the textures are written into ``directory`` first
    (:func:`write_textures`, all or nothing), or packed when ``directory`` is None: a failed
    write raises before anything in Blender changed.  Re-applying replaces an earlier bake.
    Returns {object name: image name}.
    """
    if files is None and directory is not None:
        files = write_textures(images, directory)
    clear_bake([name for name in images])
    group = ensure_node_group()
    done = {}
    for obj_name, pixels in images.items():
        ob = bpy.data.objects.get(obj_name)
        if ob is None or ob.type != "MESH":
            continue
        img = make_image(f"{NODE_PREFIX} {obj_name}", pixels, directory, pack, source=(files or {}).get(obj_name))
        _hook_object(ob, img, uv_maps.get(obj_name, ""), group)
        done[obj_name] = img.name
    return done


def apply_sequence(object_names, uv_maps, directory, frames):
    """Show a baked frame range on receivers: per object an Image with source ``SEQUENCE``
    over the files of ``frames`` in ``directory`` (:func:`publish_sequence_frames`; a
    contiguous, increasing list), its texture node's image user set to play them at their
    frames.  Re-applying replaces an earlier bake.  Returns {object name: image name}."""
    frames = [int(f) for f in frames]
    if not frames or frames != list(range(frames[0], frames[0] + len(frames))):
        raise ValueError(f"a sequence needs contiguous increasing frames, got {frames}")
    clear_bake(list(object_names))
    group = ensure_node_group()
    abs_dir = bpy.path.abspath(directory)
    done = {}
    for obj_name in object_names:
        ob = bpy.data.objects.get(obj_name)
        if ob is None or ob.type != "MESH":
            continue
        names = [texture_filename(obj_name, f, receivers=object_names) for f in frames]
        name = f"{NODE_PREFIX} {obj_name}"
        old = bpy.data.images.get(name)
        if old is not None and old.get(TAG_KEY):
            bpy.data.images.remove(old)
        img = bpy.data.images.load(os.path.join(abs_dir, names[0]), check_existing=False)
        img.name = name
        img.source = "SEQUENCE"
        img.filepath = _relative_path(directory, os.path.join(abs_dir, names[0]))
        img.colorspace_settings.name = "Non-Color"
        img[TAG_KEY] = True
        img[FILES_KEY] = json.dumps([abs_dir, names])
        _hook_object(ob, img, uv_maps.get(obj_name, ""), group, frames)
        done[obj_name] = img.name
    return done


def _hook_object(ob, img, uv_map, group, frames=None):
    """Insert the CausticBake nodes showing ``img`` into every material of ``ob`` (a material
    other objects share is copied for ``ob`` first; an object without materials gets one)."""
    obj_name = ob.name
    slot_state = []
    if len(ob.material_slots) == 0:
        mat = bpy.data.materials.new(f"{NODE_PREFIX} {obj_name}")
        mat[TAG_KEY] = True
        ob.data.materials.append(mat)
        slot_state.append({"added_slot": True, "material": mat.name})
    for k, slot in enumerate(ob.material_slots):
        mat = slot.material
        if mat is None or (mat.get(STATE_KEY) is None and mat.get(TAG_KEY) is None and _material_users(mat) != [ob]):
            # Empty slot, or a material other objects use too: this object gets its own copy.
            if mat is None:
                new = bpy.data.materials.new(f"{NODE_PREFIX} {obj_name} {k}")
            else:
                new = mat.copy()
                new.name = f"{mat.name} ({NODE_PREFIX} {obj_name})"
            new[TAG_KEY] = True
            orig_link = slot.link
            slot.link = "OBJECT"
            obj_mat = slot.material
            slot_state.append({"slot": k, "link": orig_link, "object_material": obj_mat.name if obj_mat else None})
            slot.material = new
            mat = new
        if mat.get(STATE_KEY) is not None:
            continue  # a material used by several slots of this object: done once
        if getattr(mat, "node_tree", None) is None:
            continue
        state = _insert_nodes(mat, img, uv_map, group, frames)
        state["object"] = obj_name
        state["image"] = img.name
        mat[STATE_KEY] = json.dumps(state)
    if slot_state:
        ob[SLOT_KEY] = json.dumps(slot_state)


def _restore_material(mat):
    state = json.loads(mat[STATE_KEY])
    nt = mat.node_tree
    for name in state["nodes"]:
        node = nt.nodes.get(name)
        if node is not None:
            nt.nodes.remove(node)
    for from_node, from_id, to_node, to_id in state["links"]:
        a = nt.nodes.get(from_node)
        b = nt.nodes.get(to_node)
        if a is None or b is None:
            continue
        sa = _socket_by_id(a.outputs, from_id)
        sb = _socket_by_id(b.inputs, to_id)
        if sa is not None and sb is not None:
            nt.links.new(sa, sb)
    del mat[STATE_KEY]


def clear_bake(object_names=None, delete_files=False, keep_files=()):
    """Remove what :func:`apply_bake` and :func:`apply_sequence` added (for the named objects,
    or everywhere).  ``delete_files``: also delete the files of the sequence images removed
    that Caustic Bake wrote, except the absolute paths in ``keep_files``."""
    wanted = None if object_names is None else set(object_names)
    keep = {os.path.normpath(p) for p in keep_files}
    for mat in list(bpy.data.materials):
        raw = mat.get(STATE_KEY)
        if raw is None:
            continue
        if wanted is not None and json.loads(raw).get("object") not in wanted:
            continue
        _restore_material(mat)
    for ob in bpy.data.objects:
        raw = ob.get(SLOT_KEY)
        if raw is None or (wanted is not None and ob.name not in wanted):
            continue
        for st in reversed(json.loads(raw)):
            if st.get("added_slot"):
                idx = next((k for k, sl in enumerate(ob.material_slots) if sl.material and sl.material.name == st["material"]), -1)
                if idx >= 0:
                    # Through the operator: popping the mesh's list leaves the object's slot behind.
                    with bpy.context.temp_override(object=ob):
                        ob.active_material_index = idx
                        bpy.ops.object.material_slot_remove()
                continue
            slot = ob.material_slots[st["slot"]]
            slot.link = "OBJECT"
            slot.material = bpy.data.materials.get(st["object_material"]) if st["object_material"] else None
            slot.link = st["link"]
        del ob[SLOT_KEY]
    for mat in list(bpy.data.materials):
        if mat.get(TAG_KEY) and mat.users == 0:
            bpy.data.materials.remove(mat)
    for img in list(bpy.data.images):
        if img.get(TAG_KEY):
            name = img.name[len(NODE_PREFIX) + 1:] if img.name.startswith(NODE_PREFIX + " ") else None
            if wanted is None or name in wanted or img.users == 0:
                if delete_files and img.get(FILES_KEY):
                    _delete_sequence_files(img[FILES_KEY], keep)
                bpy.data.images.remove(img)
    for group in node_groups():
        if group.users == 0:
            bpy.data.node_groups.remove(group)
    if wanted is None:  # the casters' EEVEE settings belong to the whole bake
        _restore_eevee_settings()


def _delete_sequence_files(record, keep):
    """Delete the files of a sequence image's record ([folder, [names]]) that the folder's
    manifest says Caustic Bake wrote, except those in ``keep``; forget them in the manifest."""
    try:
        abs_dir, names = json.loads(record)
    except (TypeError, ValueError):
        return
    written = output.written_here(abs_dir)
    gone = []
    for fname in names:
        path = os.path.join(abs_dir, fname)
        if fname in written and os.path.normpath(path) not in keep:
            try:
                os.remove(path)
            except FileNotFoundError:
                pass
            gone.append(fname)
    if gone and os.path.isdir(abs_dir):
        output.record_written(abs_dir, forget=gone)


def eevee_settings_for_casters(scene_model):
    """Let EEVEE show the bake through and on the casters.  EEVEE draws a refracting material
    opaque unless its raytraced refraction is on (Material > Settings > Raytraced
    Transmission, ``use_raytrace_refraction``), which needs the scene's raytracing (Render >
    Raytracing, ``eevee.use_raytracing``; without it mirrors and glass also show dark), and its
    screen-space rays find what lies behind the water only when the depth buffer's objects are
    taken as thick enough (Raytracing > Screen Tracing > Thickness, ``screen_trace_thickness``;
    Blender's default 0.2 lets the refracted rays pass behind the pool floor): raised to the
    scene's size (``scene_model.extent()``).  Turns these on where they are off: the refracting
    casters' materials (role refract or both in ``scene_model``) and, when the scene has
    casters, the scene.  The previous values are recorded on each material and the scene
    (:data:`EEVEE_KEY`), so :func:`clear_bake` restores them exactly (Undo does too); Cycles
    ignores all three.  Returns the names of what changed (materials, then scene settings)."""
    from .scene import ROLE_NAMES

    changed = []
    refracting = scene_model.tri_role >= ROLE_NAMES["refract"]
    names = sorted({scene_model.materials[k] for k in np.unique(scene_model.tri_material[refracting])} - {""})
    for name in names:
        mat = bpy.data.materials.get(name)
        if mat is None or mat.use_raytrace_refraction or mat.get(EEVEE_KEY) is not None:
            continue
        mat[EEVEE_KEY] = json.dumps({"use_raytrace_refraction": False})
        mat.use_raytrace_refraction = True
        changed.append(name)
    scene = bpy.context.scene
    if not np.any(scene_model.tri_role > 0) or scene.get(EEVEE_KEY) is not None:
        return changed
    eevee, trace = scene.eevee, scene.eevee.ray_tracing_options
    old = {"use_raytracing": bool(eevee.use_raytracing), "screen_trace_thickness": float(trace.screen_trace_thickness)}
    thickness = max(old["screen_trace_thickness"], float(scene_model.extent())) if refracting.any() else None
    on_scene = []
    if not old["use_raytracing"]:
        eevee.use_raytracing = True
        on_scene.append("scene raytracing")
    if thickness is not None and thickness > old["screen_trace_thickness"]:
        trace.screen_trace_thickness = thickness
        on_scene.append("screen tracing thickness {:.3g}".format(thickness))
    if on_scene:
        scene[EEVEE_KEY] = json.dumps(old)
    return changed + on_scene


def _restore_eevee_settings():
    """Put back the EEVEE settings :func:`eevee_settings_for_casters` changed."""
    for mat in bpy.data.materials:
        raw = mat.get(EEVEE_KEY)
        if raw is not None:
            mat.use_raytrace_refraction = bool(json.loads(raw)["use_raytrace_refraction"])
            del mat[EEVEE_KEY]
    for scene in bpy.data.scenes:
        raw = scene.get(EEVEE_KEY)
        if raw is not None:
            old = json.loads(raw)
            scene.eevee.use_raytracing = bool(old["use_raytracing"])
            scene.eevee.ray_tracing_options.screen_trace_thickness = float(old["screen_trace_thickness"])
            del scene[EEVEE_KEY]


def receivers_uv_maps(scene_model):
    """{receiver object name: UV map name} from an extracted scene model."""
    return {r.name: r.uv_map for r in scene_model.receivers}
