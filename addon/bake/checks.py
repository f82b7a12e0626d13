"""Checks of a scene model that give warnings where a bake would otherwise be silently wrong
(no bpy, plain numpy):

- :func:`zero_power_lights`: lights whose power or colour is zero add nothing;
- :func:`uv_overlap`: the share of a receiver's UV area covered by more than one of its
  triangles (overlapping UV islands: light landing on either place goes into the same
  texels, which then hold the sum);
- :func:`lights_inside`: which point-like lights (point, spot, area centre) lie inside which
  closed objects (ray parity against the object's triangles).

:func:`scene_warnings` gives the warnings of the first two, one line each.
"""

import hashlib

import numpy as np

from .kept import keep_recent

UV_OVERLAP_GRID = 256  # sample points per side of the UV square for the overlap measure
UV_OVERLAP_WARN = 0.002  # warn above this share of the covered UV area
_MAX_PAIRS = 1 << 24
_OVERLAP_KEPT = {}  # uv_overlap per hash of the UVs and grid, most recent last (an animation's receiver keeps its UVs)
OVERLAP_KEPT_SIZE = 8


def zero_power_lights(scene):
    """Names of the lights that emit nothing (zero power, or a black colour)."""
    return [light.name for light in scene.lights
            if not float(light.intensity) > 0 or not np.any(np.asarray(light.color, dtype=np.float64) > 0)]


def uv_overlap(receiver, grid=UV_OVERLAP_GRID):
    """Share of ``receiver``'s covered UV area (measured on a ``grid`` x ``grid`` lattice of
    points in the unit square) that lies strictly inside two or more of its UV triangles
    (a function of the UVs alone: kept for the next frame's bake of the same UVs)."""
    uv = np.ascontiguousarray(receiver.uv, dtype=np.float64)
    key = hashlib.sha1(uv.tobytes() + np.int64(grid).tobytes()).hexdigest()
    share = _OVERLAP_KEPT.get(key)
    return keep_recent(_OVERLAP_KEPT, key, _uv_overlap(uv, grid) if share is None else share, OVERLAP_KEPT_SIZE)


def _uv_overlap(uv, grid):
    n = uv.shape[0]
    if n == 0:
        return 0.0
    lo = np.clip(np.floor(uv.min(axis=1) * grid - 0.5), 0, grid - 1).astype(np.int64)
    hi = np.clip(np.ceil(uv.max(axis=1) * grid - 0.5), -1, grid - 1).astype(np.int64)
    nx = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    pairs = int(np.sum(nx * ny))
    if pairs > _MAX_PAIRS and grid > 16:
        return _uv_overlap(uv, grid // 2)
    counts = np.zeros(grid * grid, dtype=np.int32)
    covered = np.zeros(grid * grid, dtype=bool)
    per = nx * ny
    tri = np.repeat(np.arange(n), per)
    k = np.arange(pairs) - np.repeat(np.cumsum(per) - per, per)
    ix = lo[tri, 0] + k % np.maximum(nx[tri], 1)
    iy = lo[tri, 1] + k // np.maximum(nx[tri], 1)
    px = (ix + 0.5) / grid
    py = (iy + 0.5) / grid
    a, b, c = uv[tri, 0], uv[tri, 1], uv[tri, 2]
    e1, e2 = b - a, c - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 0
    det = np.where(ok, det, 1.0)
    dx, dy = px - a[:, 0], py - a[:, 1]
    s = (dx * e2[:, 1] - dy * e2[:, 0]) / det
    t = (e1[:, 0] * dy - e1[:, 1] * dx) / det
    eps = 1e-9
    inside = ok & (s > eps) & (t > eps) & (s + t < 1 - eps)
    on = ok & (s >= -eps) & (t >= -eps) & (s + t <= 1 + eps)
    cell = iy * grid + ix
    np.add.at(counts, cell[inside], 1)
    covered[cell[on]] = True
    n_cov = int(covered.sum())
    return float(np.count_nonzero(counts >= 2)) / n_cov if n_cov else 0.0


def lights_inside(scene, objects):
    """{light index: [object index, ...]}: the point-like lights inside each closed object of
    ``objects`` (a ray from the light crosses the object's surface an odd number of times)."""
    out = {}
    direction = np.array([0.5773502691896258, 0.5773502691896257, 0.5773502691896259])
    direction = direction + np.array([1e-3, -2e-3, 3e-3])
    direction /= np.linalg.norm(direction)
    for li, light in enumerate(scene.lights):
        if light.type == "sun":
            continue
        o = np.asarray(light.position, dtype=np.float64)
        for oi in objects:
            p = scene.tri_p[scene.tri_object == oi]
            e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
            h = np.cross(direction, e2)
            a = np.einsum("ij,ij->i", e1, h)
            ok = np.abs(a) > 1e-300
            f = 1.0 / np.where(ok, a, 1.0)
            s = o - p[:, 0]
            u = f * np.einsum("ij,ij->i", s, h)
            q = np.cross(s, e1)
            v = f * (q @ direction)
            t = f * np.einsum("ij,ij->i", e2, q)
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
            if int(np.count_nonzero(hit)) % 2 == 1:
                out.setdefault(li, []).append(int(oi))
    return out


def scene_warnings(scene, receivers):
    """One-line warnings: lights that emit nothing, receivers with overlapping UV islands."""
    warnings = [f"light {name!r} has zero power: it adds no light" for name in zero_power_lights(scene)]
    for rec in receivers:
        share = uv_overlap(rec)
        if share > UV_OVERLAP_WARN:
            warnings.append(f"receiver {rec.name!r}: {100 * share:.1f} % of its UV map is covered by overlapping UV "
                            f"islands; light landing on either place is summed into the same texels")
    return warnings
