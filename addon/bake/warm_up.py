"""Compile (or load from Numba's cache) the kernels a bake uses, ahead of it, by baking a tiny
scene with them: a floor under a glass cube, two mirrors and a water sheet at 8 x 8 texels.

:func:`prepare_for` does it for a given scene: it plans that scene (the planner's probe and
the BVH compile on the way) and bakes the tiny scene with exactly the chains the plan bakes,
lit by one light of each type the scene has.  :func:`warm_up` without a scene forces every
chain the settings allow (any of them may be planned later) under a point light.  The Blender
operator *Prepare Caustic Solver* calls :func:`prepare_for` with the open scene, so that the
next bake of it compiles nothing (tests/bake/test_bake_warm_up.py counts the signatures)."""

import dataclasses
import time

import numpy as np

from .pipeline import bake, make_context
from .plan import make_plan
from .scene import Light, build_scene

LIGHT_TYPES = ("point", "spot", "sun", "area")


def _cube(offset, size):
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size + offset
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[v[q[0]], v[q[i]], v[q[i + 1]]] for q in faces for i in (1, 2)])


def _light(kind):
    down = (0.0, 0.0, -1.0)
    if kind == "sun":
        return Light("sun", "sun", (1, 1, 1), 3.0, direction=(0.1, 0.05, -1.0), angle=0.01)
    if kind == "spot":
        return Light("spot", "spot", (1, 1, 1), 100.0, position=(0.2, 0.1, 3.0), direction=down, spot_size=1.2,
                     spot_blend=0.2, radius=0.05)
    if kind == "area":
        return Light("area", "area", (1, 1, 1), 30.0, position=(0.2, 0.1, 3.0), direction=down, axis_u=(1, 0, 0),
                     axis_v=(0, 1, 0), size_u=0.2, size_v=0.2)
    return Light("light", "point", (1, 1, 1), 100.0, position=(0.2, 0.1, 3.0), radius=0.05)


def warm_up_scene(light_types=("point",)):
    """The tiny scene: floor (receiver), glass cube (closed: R, TT), tilted mirror (R, RR with
    the cube), a steep mirror whose R reaches the floor, an open refracting sheet (T), one light
    of each of ``light_types``."""
    floor = np.array([[[-2, -2, 0], [2, -2, 0], [2, 2, 0]], [[-2, -2, 0], [2, 2, 0], [-2, 2, 0]]], float)
    uv = (floor[:, :, :2] + 2.0) / 4.0
    mirror = np.array([[[0.8, -0.5, 0.5], [1.4, -0.5, 1.2], [0.8, 0.5, 0.5]]], float)
    wall = np.array([[[1.0, -0.5, 0.3], [1.3, 0.0, 1.25], [1.0, 0.5, 0.3]]], float)  # steep: R lands on the floor
    sheet = np.array([[[-1.4, -0.6, 1.4], [-0.6, -0.6, 1.5], [-1.0, 0.6, 1.4]]], float)  # open: T
    kinds = [k for k in LIGHT_TYPES if k in set(light_types)] or ["point"]
    return build_scene([dict(name="floor", tri_p=floor, uv=uv, receiver=True, resolution=8),
                        dict(name="glass", tri_p=_cube((-0.3, -0.3, 0.6), 0.6), role="both"),
                        dict(name="mirror", tri_p=mirror, role="reflect"),
                        dict(name="wall mirror", tri_p=wall, role="reflect"),
                        dict(name="water", tri_p=sheet, role="refract", ior=1.33)],
                       [_light(k) for k in kinds])


def _quick(settings, **kw):
    return dataclasses.replace(settings, resolution=8, samples=1, photons=min(int(settings.photons), 4096),
                               memory_budget=0.0, **kw)


def warm_up(settings):
    """Bake :func:`warm_up_scene` with ``settings``' estimator, solver and bounces (every chain
    forced, then the planner's probe when bounces are "auto"); returns the seconds taken."""
    t0 = time.perf_counter()
    quick = _quick(settings, light_samples=1, chains=(),
                   bounces=settings.max_bounces() if settings.bounces == "auto" else settings.bounces)
    bake(warm_up_scene(), quick)
    if settings.bounces == "auto":  # the planner's probe
        bake(warm_up_scene(), dataclasses.replace(quick, bounces="auto"))
    return time.perf_counter() - t0


def prepare_for(scene, settings):
    """Compile what a bake of ``scene`` with ``settings`` uses: plan it, then bake the tiny scene
    with the planned chains and the scene's light types (``settings.light_samples`` kept).
    Returns (seconds, the chains planned)."""
    t0 = time.perf_counter()
    ctx = make_context(scene, settings)
    chains = tuple(sorted({it.chain for it in make_plan(ctx).baked_items()}, key=len))
    kinds = {light.type for light in scene.lights}
    if chains or settings.direct:
        bounces = max((len(c) for c in chains), default=1)
        bake(warm_up_scene(kinds), _quick(settings, chains=chains or ("R",), bounces=bounces,
                                          caustics=bool(chains)))
    return time.perf_counter() - t0, chains
