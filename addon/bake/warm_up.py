"""Compile (or load from Numba's cache) exactly the kernels a bake with given settings uses,
by baking a tiny scene with them: a floor under a glass cube and a mirror, lit by a point
light, at 8 x 8 texels, with every chain the settings allow forced (the planner of a real
bake may pick any of them).  The Blender operator *Prepare Caustic Solver* and the CLI call
it ahead of the first bake, so that compile latency is not paid in the middle of one."""

import dataclasses
import time

import numpy as np

from .pipeline import bake
from .scene import Light, build_scene


def _cube(offset, size):
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size + offset
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[v[q[0]], v[q[i]], v[q[i + 1]]] for q in faces for i in (1, 2)])


def warm_up_scene():
    """The tiny scene: floor (receiver), glass cube (closed: R, TT), tilted mirror (R, RR with the cube)."""
    floor = np.array([[[-2, -2, 0], [2, -2, 0], [2, 2, 0]], [[-2, -2, 0], [2, 2, 0], [-2, 2, 0]]], float)
    uv = (floor[:, :, :2] + 2.0) / 4.0
    mirror = np.array([[[0.8, -0.5, 0.5], [1.4, -0.5, 1.2], [0.8, 0.5, 0.5]]], float)
    return build_scene([dict(name="floor", tri_p=floor, uv=uv, receiver=True, resolution=8),
                        dict(name="glass", tri_p=_cube((-0.3, -0.3, 0.6), 0.6), role="both"),
                        dict(name="mirror", tri_p=mirror, role="reflect")],
                       [Light("light", "point", (1, 1, 1), 100.0, position=(0.2, 0.1, 3.0))])


def warm_up(settings):
    """Bake :func:`warm_up_scene` with ``settings``' estimator, solver and bounces (every chain
    forced); returns the seconds taken."""
    t0 = time.perf_counter()
    quick = dataclasses.replace(settings, resolution=8, samples=1, light_samples=1, photons=min(int(settings.photons), 4096),
                                bounces=settings.max_bounces() if settings.bounces == "auto" else settings.bounces,
                                chains=())
    bake(warm_up_scene(), quick)
    if settings.bounces == "auto":  # the planner's probe
        bake(warm_up_scene(), dataclasses.replace(quick, bounces="auto"))
    return time.perf_counter() - t0
