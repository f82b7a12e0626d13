"""What every stage of one bake shares (plain data, no bpy): the scene, the settings, the
visibility BVH, the receivers at the bake's resolution, the light samples, the stage timer
and the energy ledger the plan reads its baked shares from."""

import time
from dataclasses import dataclass, field

import numpy as np

from .raster import grid_side
from .scene import Receiver, triangle_areas, uv_areas

VISIBILITY_OFFSET = 1e-6  # x scene size: shadow-ray offset at both ends of a segment


class BakeCancelled(Exception):
    """Raised when the progress callback asks to stop."""


class Timer:
    """Seconds per stage, summed over calls."""

    def __init__(self):
        self.t = {}

    def add(self, key, dt):
        self.t[key] = self.t.get(key, 0.0) + dt

    def since(self, key, t0):
        """Add the time since ``t0`` (a perf_counter value) to ``key``; returns now."""
        now = time.perf_counter()
        self.add(key, now - t0)
        return now

    def timed_steps(self, key, steps, report):
        """Drive the generator ``steps`` for a caller that is a generator itself: yields
        ``report(*item)`` for each of its items and returns its return value (``yield from``),
        adding to ``key`` the time spent inside it, not in the consumer between items."""
        t0 = time.perf_counter()
        while True:
            try:
                item = next(steps)
            except StopIteration as done:
                self.since(key, t0)
                return done.value
            self.since(key, t0)
            yield report(*item)
            t0 = time.perf_counter()


class EnergyLedger:
    """Caustic power (W, mean over RGB) each estimator delivered, per (light, chain, first
    caster object, second caster object or -1, receiver index): the plan's baked shares."""

    def __init__(self):
        self.power = {}

    def add(self, light, chain, obj1, obj2, receiver, power):
        """Add ``power`` (n,) W of paths whose first / second caster objects are ``obj1`` /
        ``obj2`` (n,) (``obj2`` None for one vertex) landing on receivers ``receiver`` (n,)."""
        power = np.asarray(power, dtype=np.float64)
        if power.size == 0:
            return
        obj2 = np.full(power.size, -1, dtype=np.int64) if obj2 is None else np.asarray(obj2, dtype=np.int64)
        cols = [np.asarray(obj1, dtype=np.int64) + 1, obj2 + 1, np.asarray(receiver, dtype=np.int64) + 1]  # >= 0
        base = int(max(int(c.max()) for c in cols)) + 1
        key = (cols[0] * base + cols[1]) * base + cols[2]  # one integer per (obj1, obj2, receiver), in their order
        uniq, inverse = np.unique(key, return_inverse=True)
        sums = np.bincount(inverse.reshape(-1), weights=power, minlength=uniq.shape[0])
        for q, p in zip(uniq.tolist(), sums.tolist()):
            a, b, r = q // (base * base) - 1, (q // base) % base - 1, q % base - 1
            k = (int(light), chain, a, b, r)
            self.power[k] = self.power.get(k, 0.0) + p

    def total(self, **match):
        """Sum over the entries whose fields equal ``match`` (light, chain, obj1, obj2, receiver)."""
        names = ("light", "chain", "obj1", "obj2", "receiver")
        out = 0.0
        for k, p in self.power.items():
            if all(k[names.index(n)] == v for n, v in match.items()):
                out += p
        return out


@dataclass
class BakeContext:
    scene: object
    settings: object
    bvh: object
    eps: float
    extent: float
    receivers: list  # Receiver at the bake's resolution
    lsamples: list  # LightSamples per scene light
    timer: Timer = field(default_factory=Timer)
    warnings: list = field(default_factory=list)
    ledger: EnergyLedger = field(default_factory=EnergyLedger)
    _sample_area: dict = field(default_factory=dict)

    def sample_area(self, rec_index):
        """(n_triangles,) world area (m²) one supersample of receiver ``rec_index`` stands for
        on each of its triangles (0 elsewhere): area_world / area_uv / (W H S)."""
        if rec_index not in self._sample_area:
            rec = self.receivers[rec_index]
            W, H = rec.resolution
            S = grid_side(self.settings.samples) ** 2
            self._sample_area[rec_index] = world_per_uv_area(self.scene, rec) / (W * H * S)
        return self._sample_area[rec_index]

    def receiver_of_triangle(self, receivers=None):
        """(n_triangles,) receiver index per scene triangle (-1: none), and (n_triangles, 3, 2)
        UVs; ``receivers`` restricts to those receiver indices (others count as occluders)."""
        n = self.scene.n_triangles
        tri_rec = np.full(n, -1, dtype=np.int64)
        tri_uv = np.zeros((n, 3, 2))
        for r, rec in enumerate(self.receivers):
            if receivers is None or r in receivers:
                tri_rec[rec.tri_index] = r
                tri_uv[rec.tri_index] = rec.uv
        return tri_rec, tri_uv


def world_per_uv_area(scene, rec):
    """(n_triangles,) world area per unit UV area of each of receiver ``rec``'s triangles (0
    elsewhere and for triangles without UV area)."""
    uva = uv_areas(rec.uv)
    wa = triangle_areas(scene.tri_p[rec.tri_index])
    out = np.zeros(scene.n_triangles)
    out[rec.tri_index] = np.divide(wa, uva, out=np.zeros_like(wa), where=uva > 0)
    return out


def with_resolution(rec, res):
    """``rec`` with a square texture of ``res`` texels per side."""
    return Receiver(rec.name, rec.object_index, rec.tri_index, rec.uv, (res, res), rec.uv_map)
