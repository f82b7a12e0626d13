"""bpy -> scene model (addon.bake.scene): only what the bake needs.  Touches bpy.

- Meshes from the evaluated depsgraph (modifiers applied, instances included), as loop
  triangles with world positions and **corner normals** (``mesh.corner_normals``: the
  normals Cycles interpolates, sharp edges and custom normals respected), normals
  transformed by the inverse transpose of the world matrix and normalised.
- Roles per triangle from its material (auto-detection below), overridable per object with
  the add-on's ``object.caustic_bake.role`` (when registered and not "auto") or else the custom
  property ``caustic_role`` in {"auto", "reflect", "refract", "both", "none"}:
    * Glass BSDF with roughness <= ROUGHNESS_MAX -> "both" (Fresnel-weighted R and T), its IOR
      and colour;
    * Refraction BSDF, or Principled with Transmission Weight >= 0.5 and roughness <=
      ROUGHNESS_MAX -> "refract" with its IOR and colour (base colour);
    * Principled with Metallic >= 0.5, or Glossy BSDF, roughness <= ROUGHNESS_MAX ->
      "reflect" with its colour;
    * anything else: occluder.
  Linked (textured) colour / IOR inputs fall back to the socket's own value (a warning).
- Receivers: ``object.caustic_bake.receiver`` or else ``caustic_receiver`` in {"auto", "yes",
  "no"}; auto = every non-caster mesh with a UV map; the texture size is
  ``object.caustic_bake.resolution`` (if > 0), else ``caustic_resolution``, else the bake's.
- What is baked is what the (viewport) depsgraph holds: objects hidden from renders are left
  out, and so are objects disabled in viewports (the render depsgraph is not reachable from
  Python outside a render).
- Lights in Cycles' units (verified against Cycles in tests/bake/test_bake_units.py):
  point / spot I = P / (4 pi) W/sr, sun S = strength W/m², area on-axis I = P / pi W/sr;
  times colour and 2^exposure.
"""

import math

import numpy as np

import bpy

from .scene import ROLE_BOTH, ROLE_NAMES, ROLE_NONE, ROLE_REFLECT, ROLE_REFRACT, Light, Receiver, Scene, SceneError

ROUGHNESS_MAX = 0.2
GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META", "CURVES"}


def _socket_value(node, name, default, warnings, what):
    sock = node.inputs.get(name)
    if sock is None:
        return default
    if sock.is_linked:
        warnings.append(f"{what}: input {name!r} is linked; using its unlinked value")
    val = sock.default_value
    try:
        return tuple(val)
    except TypeError:
        return float(val)


def _surface_node(mat):
    """The node feeding the active output's Surface (through reroutes), or None."""
    if mat is None or not getattr(mat, "node_tree", None):
        return None
    out = mat.node_tree.get_output_node("CYCLES") or mat.node_tree.get_output_node("ALL")
    if out is None:
        return None
    sock = out.inputs.get("Surface")
    node = None
    while sock is not None and sock.is_linked:
        node = sock.links[0].from_node
        if node.type == "REROUTE":
            sock = node.inputs[0]
            continue
        break
    return node


def material_role(mat, warnings=None):
    """(role, ior, tint (3,)) auto-detected from a material (see the module docstring)."""
    warnings = [] if warnings is None else warnings
    node = _surface_node(mat)
    if node is None:
        return ROLE_NONE, 1.5, (1.0, 1.0, 1.0)
    what = f"material {mat.name!r}"
    t = node.type
    rough = lambda: _socket_value(node, "Roughness", 0.0, warnings, what)  # noqa: E731
    col = lambda name: tuple(_socket_value(node, name, (1.0, 1.0, 1.0, 1.0), warnings, what)[:3])  # noqa: E731
    if t == "BSDF_GLASS" and rough() <= ROUGHNESS_MAX:
        return ROLE_BOTH, _socket_value(node, "IOR", 1.5, warnings, what), col("Color")
    if t == "BSDF_REFRACTION" and rough() <= ROUGHNESS_MAX:
        return ROLE_REFRACT, _socket_value(node, "IOR", 1.5, warnings, what), col("Color")
    if t == "BSDF_GLOSSY" and rough() <= ROUGHNESS_MAX:
        return ROLE_REFLECT, 1.5, col("Color")
    if t == "BSDF_PRINCIPLED" and rough() <= ROUGHNESS_MAX:
        if _socket_value(node, "Transmission Weight", 0.0, warnings, what) >= 0.5:
            return ROLE_REFRACT, _socket_value(node, "IOR", 1.5, warnings, what), col("Base Color")
        if _socket_value(node, "Metallic", 0.0, warnings, what) >= 0.5:
            return ROLE_REFLECT, 1.5, col("Base Color")
    return ROLE_NONE, 1.5, (1.0, 1.0, 1.0)


#: custom property -> attribute of the object's ``caustic_bake`` property group (addon.ui).
_GROUP_ATTR = {"caustic_role": "role", "caustic_receiver": "receiver", "caustic_resolution": "resolution"}


def _prop(ob, key, allowed, default):
    """An object's role setting: its ``caustic_bake`` property group (the add-on's UI) when that
    says something other than "auto" (or a resolution > 0), else the custom property ``key``."""
    group = getattr(ob, "caustic_bake", None)
    if group is not None:
        val = getattr(group, _GROUP_ATTR[key], None)
        if val is not None and val != "auto" and val != 0:
            return val
    val = ob.get(key, default)
    if allowed is None:
        return val
    if isinstance(val, str):
        val = val.lower()
    if val not in allowed:
        raise SceneError(f"object {ob.name!r}: custom property {key}={val!r} is not one of {sorted(allowed)}")
    return val


def _mesh_arrays(ob_eval, need_uv=True, need_material=True):
    """(positions (v,3), loop triangles' vertex ids (t,3), their loop ids (t,3) or None, material
    index (t,) or None, normals (k,3), each triangle corner's row of them (t,3), uv layers
    {name: (l,2)}, active uv name) of an evaluated object.  Smooth meshes (normals on the
    point domain) give their vertex normals, others their corner normals; the loop ids, UV
    layers (``need_uv``) and material indices (``need_material``) are read only when asked for
    or needed (a caster's UVs are never used; one material needs no index)."""
    me = ob_eval.to_mesh()
    try:
        me.calc_loop_triangles()
        nv, nt, nl = len(me.vertices), len(me.loop_triangles), len(me.loops)
        co = np.empty(nv * 3)
        me.vertices.foreach_get("co", co)
        tri32 = np.empty(nt * 3, dtype=np.int32)
        me.loop_triangles.foreach_get("vertices", tri32)
        tv = tri32.astype(np.int64).reshape(-1, 3)
        by_point = me.normals_domain == "POINT"
        tl = None
        if need_uv or not by_point:
            me.loop_triangles.foreach_get("loops", tri32)
            tl = tri32.astype(np.int64).reshape(-1, 3)
        tm = None
        if need_material:
            m32 = np.empty(nt, dtype=np.int32)
            me.loop_triangles.foreach_get("material_index", m32)
            tm = m32.astype(np.int64)
        if by_point:
            normals = np.empty(nv * 3)
            me.vertex_normals.foreach_get("vector", normals)
            n_index = tv
        else:
            normals = np.empty(nl * 3)
            me.corner_normals.foreach_get("vector", normals)
            n_index = tl
        uvs = {}
        active = None
        if need_uv:
            for layer in me.uv_layers:
                uv = np.empty(nl * 2)
                layer.uv.foreach_get("vector", uv)
                uvs[layer.name] = uv.reshape(-1, 2)
                if layer.active_render:
                    active = layer.name
            if active is None and me.uv_layers.active is not None:
                active = me.uv_layers.active.name
        return co.reshape(-1, 3), tv, tl, tm, normals.reshape(-1, 3), n_index, uvs, active
    finally:
        ob_eval.to_mesh_clear()


def _light_model(ob, matrix, warnings):
    L = ob.data
    M = np.array(matrix, dtype=np.float64)
    pos = M[:3, 3]
    direction = -M[:3, 2]
    color = np.array(L.color[:3], dtype=np.float64) * (2.0 ** float(getattr(L, "exposure", 0.0)))
    if getattr(L, "use_temperature", False):
        warnings.append(f"light {ob.name!r}: colour temperature is not modelled; using its colour only")
    if getattr(L, "use_nodes", False) and L.node_tree is not None:
        warnings.append(f"light {ob.name!r}: light nodes are not modelled; using its colour and power")
    energy = float(L.energy)
    if not getattr(L, "normalize", True) and L.type != "AREA":
        warnings.append(f"light {ob.name!r}: un-normalised light power is not modelled; treated as normalised")
    if L.type in ("POINT", "SPOT"):
        kw = dict(radius=float(L.shadow_soft_size))
        if L.type == "SPOT":
            kw.update(direction=direction, spot_size=float(L.spot_size), spot_blend=float(L.spot_blend))
        return Light(ob.name, L.type.lower(), color, energy / (4.0 * math.pi), position=pos, **kw)
    if L.type == "SUN":
        return Light(ob.name, "sun", color, energy, direction=direction, angle=float(L.angle))
    if L.type == "AREA":
        if getattr(L, "spread", math.pi) < math.pi - 1e-6:
            warnings.append(f"light {ob.name!r}: area light spread below 180 degrees is not modelled")
        if not getattr(L, "normalize", True):
            warnings.append(f"light {ob.name!r}: un-normalised area light power is not modelled")
        ax_u = M[:3, 0]
        ax_v = M[:3, 1]
        su = float(L.size) * np.linalg.norm(ax_u)
        sv = float(L.size_y if L.shape in ("RECTANGLE", "ELLIPSE") else L.size) * np.linalg.norm(ax_v)
        return Light(ob.name, "area", color, energy / math.pi, position=pos, direction=direction,
                     axis_u=ax_u / max(np.linalg.norm(ax_u), 1e-300), axis_v=ax_v / max(np.linalg.norm(ax_v), 1e-300),
                     size_u=su, size_v=sv, ellipse=L.shape in ("DISK", "ELLIPSE"))
    warnings.append(f"light {ob.name!r}: type {L.type} is not supported; skipped")
    return None


def _world_normals(normals, A, P, n_index, name):
    """World corner normals (n, 3, 3) of triangles ``P`` (world positions) whose local corner
    normals are ``normals[n_index]``, under the linear part ``A`` of the object's transform:
    the inverse transpose, or where ``A`` is singular (a flat plane scaled to zero thickness)
    its cofactor matrix, which maps a face's normal to the world face's normal wherever the
    world triangle has area.  Corners whose normal collapses take their world face normal.
    An object none of whose triangles keeps any area is a SceneError."""
    face = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    face_len = np.linalg.norm(face, axis=1)
    try:
        nmat = np.linalg.inv(A).T
    except np.linalg.LinAlgError:
        nmat = np.column_stack([np.cross(A[:, 1], A[:, 2]), np.cross(A[:, 2], A[:, 0]), np.cross(A[:, 0], A[:, 1])])
        size = float(np.abs(P).max()) if P.size else 0.0
        if not np.any(face_len > 1e-24 * max(size * size, 1e-300)):
            raise SceneError(f"object {name!r} has a degenerate (zero-scale) transform") from None
    ncorner = normals @ nmat.T
    ln = np.linalg.norm(ncorner, axis=1, keepdims=True)
    ncorner = np.divide(ncorner, ln, out=np.zeros_like(ncorner), where=ln > 0)
    N = ncorner[n_index]
    collapsed = np.linalg.norm(N, axis=2) < 0.5
    if collapsed.any():
        unit = np.divide(face, face_len[:, None], out=np.zeros_like(face), where=face_len[:, None] > 0)
        N = np.where(collapsed[:, :, None], unit[:, None, :], N)
    return N


def _slot_roles(slot_mats, role_cache):
    """The (role, ior, tint, warnings) of each slot's material, each material read once per
    extraction (``role_cache``, by name); its warnings are reported where it is first used."""
    out = []
    for mat in slot_mats:
        key = mat.name if mat is not None else ""
        if key not in role_cache:
            said = []
            role_cache[key] = material_role(mat, said) + (said,)
        out.append(role_cache[key])
    return out


def extract_scene(depsgraph=None, resolution=256, frame=None):
    """The :class:`~addon.bake.scene.Scene` of the current (or given) depsgraph.

    ``resolution``: texture size (texels per side) of receivers without a
    ``caustic_resolution`` property.  Objects hidden from renders are skipped.
    """
    if frame is not None:
        bpy.context.scene.frame_set(int(frame))
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    warnings = []
    tri_p, tri_n, tri_obj, tri_role, tri_ior, tri_tint, tri_mat = [], [], [], [], [], [], []
    names, materials, receivers, lights = [], [], [], []
    mat_index = {}
    role_cache = {}
    offset = 0
    for inst in depsgraph.object_instances:
        ob = inst.object
        orig = ob.original
        if orig.hide_render or not inst.show_self:
            continue
        if ob.type == "LIGHT":
            light = _light_model(orig, inst.matrix_world, warnings)
            if light is not None:
                if inst.is_instance:
                    light.name = f"{orig.name} [instance {len(lights)}]"
                lights.append(light)
            continue
        if ob.type not in GEOMETRY_TYPES:
            continue
        slots = list(orig.material_slots) if not inst.is_instance else list(ob.material_slots)
        slot_mats = [s.material for s in slots] or [None]
        override = _prop(orig, "caustic_role", set(ROLE_NAMES) | {"auto"}, "auto")
        want = _prop(orig, "caustic_receiver", {"auto", "yes", "no"}, "auto")
        roles = _slot_roles(slot_mats, role_cache)
        # UVs only where the object can be a receiver (a caster by its override or every slot cannot)
        surely_caster = override != "none" if override != "auto" else all(r[0] != ROLE_NONE for r in roles)
        need_uv = want == "yes" or (want == "auto" and not surely_caster)
        co, tv, tl, tm, normals, n_index, uvs, active_uv = _mesh_arrays(ob, need_uv, len(slot_mats) > 1)
        if tv.shape[0] == 0:
            continue
        # Materials: per slot, roles auto-detected, then the object override.
        local_role = np.zeros(len(slot_mats), dtype=np.int64)
        local_ior = np.full(len(slot_mats), 1.5)
        local_tint = np.ones((len(slot_mats), 3))
        local_mat = np.zeros(len(slot_mats), dtype=np.int64)
        for k, (mat, (role, ior, tint, said)) in enumerate(zip(slot_mats, roles)):
            key = mat.name if mat is not None else ""
            local_role[k], local_ior[k], local_tint[k] = role, ior, tint
            if key not in mat_index:
                mat_index[key] = len(materials)
                materials.append(key)
                warnings.extend(said)
            local_mat[k] = mat_index[key]
        M = np.array(inst.matrix_world, dtype=np.float64)
        A = M[:3, :3]
        world = co @ A.T + M[:3, 3]
        P = world[tv]
        N = _world_normals(normals, A, P, n_index, orig.name)
        m = P.shape[0]
        oi = len(names)
        name = orig.name if not inst.is_instance else f"{orig.name} [instance {oi}]"
        names.append(name)
        mi = np.clip(tm, 0, len(slot_mats) - 1) if tm is not None else np.zeros(m, dtype=np.int64)
        role = local_role[mi]
        if override != "auto":
            role = np.full(m, ROLE_NAMES[override], dtype=np.int64)
        tri_p.append(P)
        tri_n.append(N)
        tri_obj.append(np.full(m, oi, dtype=np.int64))
        tri_role.append(role)
        tri_ior.append(local_ior[mi])
        tri_tint.append(local_tint[mi])
        tri_mat.append(local_mat[mi])
        is_caster = bool(np.any(role != ROLE_NONE))
        if want == "yes" or (want == "auto" and not is_caster and uvs):
            if inst.is_instance:
                if want == "yes":
                    warnings.append(f"{name}: an instance cannot be a receiver (no image of its own); skipped")
            elif not uvs:
                raise SceneError(f"receiver {orig.name!r} has no UV map")
            else:
                res = int(_prop(orig, "caustic_resolution", None, resolution))
                uv = uvs[active_uv][tl]
                receivers.append(Receiver(orig.name, oi, np.arange(offset, offset + m), uv, (res, res), active_uv))
        offset += m
    if not tri_p:
        raise SceneError("the scene has no meshes")
    cat = np.concatenate
    scene = Scene(tri_p=cat(tri_p), tri_n=cat(tri_n), tri_object=cat(tri_obj), tri_role=cat(tri_role), tri_ior=cat(tri_ior),
                  tri_tint=cat(tri_tint), tri_material=cat(tri_mat), objects=names, materials=materials,
                  receivers=receivers, lights=lights, frame=int(bpy.context.scene.frame_current), warnings=warnings)
    return scene


def readiness(bl_scene):
    """(receivers, lights): how many objects of ``bl_scene`` would be receivers and lights,
    by the rules of :func:`extract_scene` but without evaluating meshes (cheap enough for a
    panel's poll).  Objects hidden from renders are left out; instances are not counted."""
    n_rec = n_light = 0
    roles = {}
    for ob in bl_scene.objects:
        if ob.hide_render:
            continue
        if ob.type == "LIGHT":
            n_light += 1
            continue
        if ob.type != "MESH":
            continue
        try:
            want = _prop(ob, "caustic_receiver", {"auto", "yes", "no"}, "auto")
            override = _prop(ob, "caustic_role", set(ROLE_NAMES) | {"auto"}, "auto")
        except SceneError:
            continue
        if want == "no":
            continue
        if want == "auto":
            if not ob.data.uv_layers:
                continue
            if override != "auto":
                caster = override != "none"
            else:
                caster = False
                for slot in ob.material_slots:
                    mat = slot.material
                    key = mat.name if mat is not None else ""
                    if key not in roles:
                        roles[key] = material_role(mat)[0]
                    caster = caster or roles[key] != ROLE_NONE
            if caster:
                continue
        n_rec += 1
    return n_rec, n_light


def open_blend(path):
    """Open a .blend file (the whole session switches to it)."""
    bpy.ops.wm.open_mainfile(filepath=str(path))
