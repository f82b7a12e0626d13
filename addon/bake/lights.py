"""Lights as point (or parallel) samples with an emission profile, in Cycles' units.

A light becomes ``n`` samples; each is a point x0 (or, for the sun, a direction) with an RGB
weight and a directional factor f(w) for the emitted direction w:

- point: I = P / (4 pi) W/sr in every direction.  With a radius and ``n`` > 1: a sphere
  light, ``n`` stratified points on the sphere, each a Lambertian emitter along its outward
  normal with weight 4 I / n (the mean of max(0, cos) over the sphere is 1/4, so the samples
  add up to I in every direction from afar, and to the exact sphere light near it).
- spot: as point, times Cycles' cone falloff
  smoothstep((cos a - cos(size / 2)) / ((1 - cos(size / 2)) blend)), a the angle to the axis.
- sun: parallel light of irradiance S W/m² along ``direction``; with an angle and ``n`` > 1,
  ``n`` directions stratified over the disc of the sun, S / n each.
- area: Lambertian single-sided emitter with on-axis intensity P / pi: ``n`` stratified
  points on the rectangle / ellipse, each with intensity (P / pi) / n times max(0, cos) to
  the light's normal.  (``spread`` other than 180 degrees is not modelled.)
"""

import math
from dataclasses import dataclass

import numpy as np

from .cull import vertex_cap

PROFILE_ISOTROPIC = 0
PROFILE_LAMBERT = 1  # max(0, axis . w)


@dataclass
class LightSamples:
    """Samples of one light (struct of arrays, m samples)."""

    light: str
    kind: str  # "point" (x0 is a point) or "sun" (direction is the travel direction)
    position: np.ndarray  # (m,3)
    direction: np.ndarray  # (m,3) sun: travel direction of the light
    rgb: np.ndarray  # (m,3) W/sr (point kinds) or W/m² (sun), colour included
    lobe: np.ndarray  # (m,3) Lambertian lobe axis (zero vector: isotropic)
    spot_axis: np.ndarray  # (3,) unit, or zeros when not a spot
    spot_cos: float  # cos(size / 2)
    spot_smooth: float  # 1 / ((1 - cos(size / 2)) blend); inf for a hard edge

    @property
    def size(self):
        return self.position.shape[0]


def _stratified_square(n, rng):
    """n points in [0,1)^2 stratified on a near-square grid, jittered."""
    sx = max(1, int(math.floor(math.sqrt(n))))
    sy = int(math.ceil(n / sx))
    idx = np.arange(n)
    a = idx % sx
    b = idx // sx
    j = rng.random((n, 2))
    return np.column_stack([(a + j[:, 0]) / sx, (b + j[:, 1]) / sy])


def _frame(w):
    w = w / np.linalg.norm(w)
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    return u, v, w


def spot_factor(cos_a, spot_cos, spot_smooth):
    """Cycles' spot falloff for cos of the angle to the axis (numpy, vectorised)."""
    cos_a = np.asarray(cos_a, dtype=np.float64)
    if not np.isfinite(spot_smooth):
        return (cos_a > spot_cos).astype(np.float64)
    f = np.clip((cos_a - spot_cos) * spot_smooth, 0.0, 1.0)
    return f * f * (3.0 - 2.0 * f)


def sample_light(light, n=1, seed=0):
    """The samples of one :class:`~addon.bake.scene.Light` (n = 1: the light as a point / parallel light)."""
    n = max(1, int(n))
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib_hash(light.name)])
    rgb = light.color * light.intensity
    spot_axis = np.zeros(3)
    spot_cos, spot_smooth = -2.0, math.inf
    if light.type == "spot":
        spot_axis = light.direction.copy()
        spot_cos = math.cos(0.5 * min(light.spot_size, math.pi))
        blend = float(light.spot_blend)
        spot_smooth = 1.0 / ((1.0 - spot_cos) * blend) if blend > 0 and spot_cos < 1 else math.inf
    if light.type in ("point", "spot"):
        if light.radius > 0 and n > 1:
            uv = _stratified_square(n, rng)
            z = 1.0 - 2.0 * uv[:, 0]
            r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
            phi = 2.0 * math.pi * uv[:, 1]
            normals = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
            pos = light.position + light.radius * normals
            w = np.broadcast_to(4.0 * rgb / n, (n, 3)).copy()
            return LightSamples(light.name, "point", pos, np.zeros((n, 3)), w, normals, spot_axis, spot_cos, spot_smooth)
        return LightSamples(light.name, "point", light.position[None].copy(), np.zeros((1, 3)), rgb[None].copy(),
                            np.zeros((1, 3)), spot_axis, spot_cos, spot_smooth)
    if light.type == "sun":
        d = light.direction / np.linalg.norm(light.direction)
        if light.angle > 0 and n > 1:
            half = 0.5 * light.angle
            uv = _stratified_square(n, rng)
            cos_t = 1.0 - uv[:, 0] * (1.0 - math.cos(half))
            sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
            phi = 2.0 * math.pi * uv[:, 1]
            u, v, w = _frame(d)
            dirs = (sin_t * np.cos(phi))[:, None] * u + (sin_t * np.sin(phi))[:, None] * v + cos_t[:, None] * w
            wts = np.broadcast_to(rgb / n, (n, 3)).copy()
            return LightSamples(light.name, "sun", np.zeros((n, 3)), dirs, wts, np.zeros((n, 3)), spot_axis, spot_cos, spot_smooth)
        return LightSamples(light.name, "sun", np.zeros((1, 3)), d[None].copy(), rgb[None].copy(), np.zeros((1, 3)), spot_axis, spot_cos, spot_smooth)
    if light.type == "area":
        axis = light.direction / np.linalg.norm(light.direction)
        if n > 1 and (light.size_u > 0 or light.size_v > 0):
            uv = _stratified_square(n, rng)
            if light.ellipse:
                r = np.sqrt(uv[:, 0])
                phi = 2.0 * math.pi * uv[:, 1]
                a = 0.5 * r * np.cos(phi)
                b = 0.5 * r * np.sin(phi)
            else:
                a = uv[:, 0] - 0.5
                b = uv[:, 1] - 0.5
            pos = light.position + (a * light.size_u)[:, None] * light.axis_u + (b * light.size_v)[:, None] * light.axis_v
        else:
            pos = light.position[None].copy()
            n = 1
        w = np.broadcast_to(rgb / n, (n, 3)).copy()
        return LightSamples(light.name, "point", pos, np.zeros((n, 3)), w, np.broadcast_to(axis, (n, 3)).copy(), spot_axis, spot_cos, spot_smooth)
    raise ValueError(f"unsupported light type {light.type!r}")


def emission_factor(samples, index, w):
    """Directional factor of sample ``index`` (int array) for unit emitted directions w (m,3)."""
    f = np.ones(w.shape[0])
    lobe = samples.lobe[index]
    has_lobe = np.any(lobe != 0.0, axis=1)
    if has_lobe.any():
        c = np.sum(lobe * w, axis=1)
        f = np.where(has_lobe, np.maximum(c, 0.0), f)
    if np.any(samples.spot_axis != 0.0):
        f = f * spot_factor(w @ samples.spot_axis, samples.spot_cos, samples.spot_smooth)
    return f


def zlib_hash(text):
    import zlib

    return zlib.crc32(text.encode("utf-8"))


def light_points(ls, m, tri_p, extent, sun_distance):
    """x0 per caster triangle for light sample ``m``: the sample's point, or for the sun a far
    point ``sun_distance`` x ``extent`` behind each triangle's centroid (the solvers take points;
    the relative error of the stand-in is the beam's divergence, about 2 L / D)."""
    if ls.kind == "sun":
        c = tri_p.mean(axis=1)
        return c - sun_distance * extent * ls.direction[m]
    return np.broadcast_to(ls.position[m], (tri_p.shape[0], 3)).copy()


def lit_casters(ls, m, x0, tri_p):
    """Mask of caster triangles that light sample ``m`` can reach (spot cone, Lambertian lobe;
    conservative: the cap of the triangle's vertex directions must meet the emitting cone)."""
    keep = np.ones(tri_p.shape[0], dtype=bool)
    lobe = ls.lobe[m]
    if ls.kind == "sun" or not (np.any(lobe != 0) or np.any(ls.spot_axis != 0)):
        return keep  # a sun, or a point light without a lobe or a cone: every direction
    a, alpha = vertex_cap(x0, tri_p)
    if np.any(lobe != 0):
        ang = np.arccos(np.clip(a @ lobe, -1, 1))
        keep &= ang - alpha < 0.5 * math.pi
    if np.any(ls.spot_axis != 0):
        ang = np.arccos(np.clip(a @ ls.spot_axis, -1, 1))
        keep &= ang - alpha < math.acos(max(-1.0, min(1.0, ls.spot_cos))) + 1e-9
    return keep
