"""The plain-data scene model the bake runs on (numpy arrays, no bpy).

``extract.py`` builds it from a Blender depsgraph; tests and benchmarks build it by hand.
Everything is in world space, float64, metres.

Triangles (all of them: casters, receivers and plain occluders) live in one table so that
the visibility BVH is built once:

- ``tri_p``  (n,3,3)  vertex positions, ``tri_p[t, j]`` is corner j.
- ``tri_n``  (n,3,3)  corner normals (unit; Cycles' interpolated normals, sharp edges
  already split by Blender), transformed by the inverse transpose of the object matrix.
- ``tri_object`` (n,) index into ``objects``; ``tri_material`` (n,) index into ``materials``.
- ``tri_role`` (n,) ROLE_* of the triangle (from its material and the object override),
  ``tri_ior`` (n,) IOR of the medium behind the surface (normals point away from it),
  ``tri_tint`` (n,3) linear RGB colour of the specular lobe (metal colour, glass tint).

Receivers reference their triangles in the table and carry a UV per corner and the texture
size.  Lights carry their type and Cycles' units (see :class:`Light`).
"""

import math
from dataclasses import dataclass, field

import numpy as np

from ..solver.geometry.optics import ROLE_BOTH, ROLE_NONE, ROLE_REFLECT, ROLE_REFRACT
from ..solver.geometry.rows import group_rows
from .kept import keep_recent

# Surface roles (the solver's codes, addon.solver.geometry.optics): none = occluder only;
# reflect = mirror / metal (chain R, reflectance = tint); refract = one refracting interface
# such as water (chain T, 1 - F x tint); both = glass (R with dielectric Fresnel F, T with 1 - F).
ROLE_NAMES = {"none": ROLE_NONE, "reflect": ROLE_REFLECT, "refract": ROLE_REFRACT, "both": ROLE_BOTH}
ROLE_LABELS = {v: k for k, v in ROLE_NAMES.items()}
_WELD_KEPT = {}  # closedness per object (name, corners): its welding (each corner's first equal corner) and answer
WELD_KEPT_SIZE = 4  # objects kept (a 1M-triangle object keeps 28 MB of welding)


def _closed_surface(p, key):
    """Whether the triangles with corners ``p`` (3m, 3) form a closed surface (see
    :meth:`Scene.closed_objects`).  The answer depends only on which corners are equal after
    quantisation; the last answer for ``key`` (an animated object's previous frame) is reused
    when the same corners are equal now and no others (each corner equals the corner it was
    welded to, and those are pairwise distinct): the same welding, so the same answer."""
    lo, hi = point_bounds(p)
    size = float(np.max(hi - lo)) or 1.0
    q = np.round((p - lo) / (size * 1e-9)).astype(np.int64)
    kept = _WELD_KEPT.get(key)
    if kept is not None:
        rep, first, closed = kept
        if rep.size == q.shape[0] and np.array_equal(q, q[rep]):
            _ids, distinct = group_rows(np.ascontiguousarray(q[first]).view(np.uint64))
            if distinct.size == first.size:
                keep_recent(_WELD_KEPT, key, kept, WELD_KEPT_SIZE)
                return closed
    vid, first = group_rows(q.view(np.uint64))  # vertex ids: equal quantised positions
    tri = vid.reshape(-1, 3)
    a = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])
    b = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    eid, _ = group_rows(np.ascontiguousarray(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)).view(np.uint64))
    counts = np.bincount(eid)
    closed = bool(counts.size and np.all(counts == 2))
    keep_recent(_WELD_KEPT, key, (first[vid], first, closed), WELD_KEPT_SIZE)
    return closed


LIGHT_TYPES = ("point", "spot", "sun", "area")


class SceneError(ValueError):
    """A user error in the scene (no receivers, bad geometry, ...): a one-line reason."""


@dataclass
class Light:
    """A light in Cycles' units.

    - point / spot: ``intensity`` I = P / (4 pi) W/sr (times ``color``); ``radius`` > 0 is a
      sphere light, sampled when the bake asks for light samples.
    - spot: ``direction`` the cone axis (the light's -Z), ``spot_size`` the full cone angle
      (rad), ``spot_blend`` Blender's blend (Cycles: smoothstep((cos a - cos(size/2)) /
      ((1 - cos(size/2)) blend))).
    - sun: ``direction`` the direction the light travels (the light's -Z), ``intensity`` the
      irradiance S on a surface facing the sun, W/m²; ``angle`` its angular diameter (rad).
    - area: ``position`` the centre, ``direction`` the emitting side's normal (-Z),
      ``axis_u`` / ``axis_v`` unit axes, ``size_u`` / ``size_v`` the full edge lengths (or
      the diameters for ``ellipse``), ``intensity`` the on-axis intensity P / pi W/sr of a
      Lambertian single-sided emitter.
    """

    name: str
    type: str
    color: np.ndarray  # (3,) linear RGB multiplier
    intensity: float
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    radius: float = 0.0
    spot_size: float = math.pi
    spot_blend: float = 0.0
    angle: float = 0.0
    axis_u: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    axis_v: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    size_u: float = 0.0
    size_v: float = 0.0
    ellipse: bool = False

    def __post_init__(self):
        self.color = np.asarray(self.color, dtype=np.float64).reshape(3)
        self.position = np.asarray(self.position, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3)
        nd = np.linalg.norm(d)
        self.direction = d / nd if nd > 0 else d
        self.axis_u = np.asarray(self.axis_u, dtype=np.float64).reshape(3)
        self.axis_v = np.asarray(self.axis_v, dtype=np.float64).reshape(3)
        self.intensity = float(self.intensity)

    def as_dict(self):
        out = {"name": self.name, "type": self.type, "color": self.color.tolist(), "intensity": self.intensity}
        if self.type != "sun":
            out["position"] = self.position.tolist()
        if self.type in ("spot", "sun", "area"):
            out["direction"] = self.direction.tolist()
        if self.type in ("point", "spot"):
            out["radius"] = self.radius
        if self.type == "spot":
            out.update(spot_size=self.spot_size, spot_blend=self.spot_blend)
        if self.type == "sun":
            out["angle"] = self.angle
        if self.type == "area":
            out.update(size_u=self.size_u, size_v=self.size_v, ellipse=self.ellipse)
        return out


def point_bounds(p):
    """(lo (3,), hi (3,)) of points ``p`` (n, 3), column by column: numpy's min / max over axis 0
    of an (n, 3) array walks it in rows of 3 and costs ~10x more."""
    return (np.array([p[:, k].min() for k in range(3)]), np.array([p[:, k].max() for k in range(3)]))


@dataclass
class Receiver:
    """A receiver object: its triangles in the scene table and a UV per corner.

    ``uv`` (m,2... ) is (m,3,2): UV of corner j of triangle ``tri_index[i]``; ``resolution``
    (width, height) in texels; ``uv_map`` the UV layer's name (for the material nodes).
    """

    name: str
    object_index: int
    tri_index: np.ndarray  # (m,) int64 into Scene.tri_*
    uv: np.ndarray  # (m,3,2) float64
    resolution: tuple = (256, 256)
    uv_map: str = "UVMap"

    def __post_init__(self):
        self.tri_index = np.ascontiguousarray(self.tri_index, dtype=np.int64)
        self.uv = np.ascontiguousarray(self.uv, dtype=np.float64)
        if isinstance(self.resolution, (int, np.integer)):
            self.resolution = (int(self.resolution), int(self.resolution))
        self.resolution = (int(self.resolution[0]), int(self.resolution[1]))


@dataclass
class Scene:
    tri_p: np.ndarray
    tri_n: np.ndarray
    tri_object: np.ndarray
    tri_role: np.ndarray
    tri_ior: np.ndarray
    tri_tint: np.ndarray
    tri_material: np.ndarray
    objects: list  # object names, indexed by tri_object
    materials: list = field(default_factory=list)  # material names, indexed by tri_material
    receivers: list = field(default_factory=list)
    lights: list = field(default_factory=list)
    frame: int = 1
    warnings: list = field(default_factory=list)

    @property
    def n_triangles(self):
        return self.tri_p.shape[0]

    def casters(self, roles=(ROLE_REFLECT, ROLE_REFRACT, ROLE_BOTH)):
        """Indices of the triangles whose role is in ``roles``."""
        return np.flatnonzero(np.isin(self.tri_role, roles))

    def closed_objects(self, objects=None):
        """Object indices (of ``objects``, default all) whose triangles form a closed surface
        (every edge shared by exactly two triangles, vertices matched by position to 1e-9 of the
        object's size): a solid such as a glass sphere or slab."""
        out = set()
        for oi in np.unique(self.tri_object) if objects is None else np.unique(np.asarray(list(objects), dtype=np.int64)):
            p = self.tri_p[self.tri_object == oi].reshape(-1, 3)
            if p.size and _closed_surface(p, (self.objects[oi] if oi < len(self.objects) else "", p.shape[0])):
                out.add(int(oi))
        return out

    def extent(self):
        """Diagonal of the bounding box of all triangles (1 for an empty scene)."""
        if self.n_triangles == 0:
            return 1.0
        lo, hi = point_bounds(self.tri_p.reshape(-1, 3))
        d = float(np.linalg.norm(hi - lo))
        return d if d > 0 else 1.0

    def validate(self):
        """Raise SceneError with a one-line reason for input the bake cannot use."""
        n = self.n_triangles
        for name, arr, tail in (("tri_p", self.tri_p, (3, 3)), ("tri_n", self.tri_n, (3, 3)), ("tri_tint", self.tri_tint, (3,))):
            if arr.shape != (n,) + tail:
                raise SceneError(f"scene table {name} has shape {arr.shape}, expected {(n,) + tail}")
        for name in ("tri_object", "tri_role", "tri_ior", "tri_material"):
            if getattr(self, name).shape != (n,):
                raise SceneError(f"scene table {name} has shape {getattr(self, name).shape}, expected ({n},)")
        if not self.receivers:
            raise SceneError("the scene has no receivers (meshes with a UV map that are not casters)")
        if not self.lights:
            raise SceneError("the scene has no lights")
        bad = ~np.all(np.isfinite(self.tri_p.reshape(n, 9)), axis=1) | ~np.all(np.isfinite(self.tri_n.reshape(n, 9)), axis=1)
        if bad.any():
            t = int(np.flatnonzero(bad)[0])
            raise SceneError(f"object {self.objects[self.tri_object[t]]!r} has NaN or infinite vertex positions or normals")
        if not np.all(np.isfinite(self.tri_ior)) or np.any(self.tri_ior[self.tri_role >= ROLE_REFRACT] <= 0):
            raise SceneError("a refracting material has an invalid IOR")
        area = triangle_areas(self.tri_p)
        for rec in self.receivers:
            if rec.tri_index.size == 0:
                raise SceneError(f"receiver {rec.name!r} has no faces")
            if rec.uv.shape != (rec.tri_index.size, 3, 2):
                raise SceneError(f"receiver {rec.name!r} has no UV map")
            if not np.all(np.isfinite(rec.uv)):
                raise SceneError(f"receiver {rec.name!r} has NaN UV coordinates")
            if min(rec.resolution) < 1 or max(rec.resolution) > 16384:
                raise SceneError(f"receiver {rec.name!r} has an invalid texture size {rec.resolution}")
            a = area[rec.tri_index]
            if not np.any(a > 0):
                raise SceneError(f"receiver {rec.name!r} has zero area")
            uva = uv_areas(rec.uv)
            if not np.any(uva > 0):
                raise SceneError(f"receiver {rec.name!r} has a UV map of zero area")
        cast = self.casters()
        if cast.size and not np.any(area[cast] > 0):
            names = sorted({self.objects[i] for i in self.tri_object[cast]})
            raise SceneError(f"caster {names[0]!r} has zero area")
        for light in self.lights:
            vals = [light.intensity, *light.color, *light.position, *light.direction]
            if not all(math.isfinite(float(v)) for v in vals):
                raise SceneError(f"light {light.name!r} has NaN or infinite values")
            if light.type not in LIGHT_TYPES:
                raise SceneError(f"light {light.name!r} has an unsupported type {light.type!r}")
            if light.type in ("spot", "sun", "area") and not np.linalg.norm(light.direction) > 0:
                raise SceneError(f"light {light.name!r} has no direction")


def triangle_areas(tri_p):
    e1 = tri_p[:, 1] - tri_p[:, 0]
    e2 = tri_p[:, 2] - tri_p[:, 0]
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def uv_areas(uv):
    e1 = uv[:, 1] - uv[:, 0]
    e2 = uv[:, 2] - uv[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def build_scene(objects, lights, receivers=(), frame=1):
    """Assemble a Scene from per-object dicts (used by extract.py and by tests).

    ``objects``: list of dicts with ``name``, ``tri_p`` (m,3,3), ``tri_n`` (m,3,3) and optional
    ``role`` (name or code, default "none"), ``ior`` (1.5), ``tint`` ((1,1,1)),
    ``tri_material`` (m,) and ``materials`` (names), ``uv`` (m,3,2) + ``receiver`` True +
    ``resolution`` + ``uv_map`` for receivers, or per-triangle ``tri_role`` / ``tri_ior`` /
    ``tri_tint`` arrays overriding the scalars.
    """
    tri_p, tri_n, tri_obj, tri_role, tri_ior, tri_tint, tri_mat = [], [], [], [], [], [], []
    names, materials, recs = [], [], []
    offset = 0
    for oi, ob in enumerate(objects):
        p = np.asarray(ob["tri_p"], dtype=np.float64).reshape(-1, 3, 3)
        m = p.shape[0]
        nrm = np.asarray(ob.get("tri_n", None) if ob.get("tri_n", None) is not None else _flat_normals(p), dtype=np.float64).reshape(m, 3, 3)
        role = ob.get("role", "none")
        role = ROLE_NAMES[role] if isinstance(role, str) else int(role)
        tri_p.append(p)
        tri_n.append(nrm)
        tri_obj.append(np.full(m, oi, dtype=np.int64))
        tri_role.append(np.asarray(ob.get("tri_role", np.full(m, role)), dtype=np.int64).reshape(m))
        tri_ior.append(np.asarray(ob.get("tri_ior", np.full(m, float(ob.get("ior", 1.5)))), dtype=np.float64).reshape(m))
        tint = np.asarray(ob.get("tint", (1.0, 1.0, 1.0)), dtype=np.float64)
        tri_tint.append(np.asarray(ob.get("tri_tint", np.broadcast_to(tint, (m, 3))), dtype=np.float64).reshape(m, 3))
        mats = list(ob.get("materials", [ob.get("material", "")]))
        local_mat = np.asarray(ob.get("tri_material", np.zeros(m, dtype=np.int64)), dtype=np.int64).reshape(m)
        tri_mat.append(local_mat + len(materials))
        materials.extend(mats)
        names.append(ob["name"])
        if ob.get("receiver", False):
            recs.append(Receiver(ob["name"], oi, np.arange(offset, offset + m), np.asarray(ob["uv"], dtype=np.float64).reshape(m, 3, 2),
                                 ob.get("resolution", (256, 256)), ob.get("uv_map", "UVMap")))
        offset += m
    cat = lambda xs, shape, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(shape, dtype=dt)  # noqa: E731
    scene = Scene(
        tri_p=cat(tri_p, (0, 3, 3), np.float64), tri_n=cat(tri_n, (0, 3, 3), np.float64),
        tri_object=cat(tri_obj, (0,), np.int64), tri_role=cat(tri_role, (0,), np.int64),
        tri_ior=cat(tri_ior, (0,), np.float64), tri_tint=cat(tri_tint, (0, 3), np.float64),
        tri_material=cat(tri_mat, (0,), np.int64), objects=names, materials=materials,
        receivers=recs + list(receivers), lights=list(lights), frame=frame)
    return scene


def _flat_normals(p):
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    return np.repeat(n[:, None, :], 3, axis=1)
