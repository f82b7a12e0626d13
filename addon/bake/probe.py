"""The planner's flux probe: a cheap estimate of the caustic power each chain brings to each
receiver, per light and caster objects.

For one light (its centre: one sample) and one chain, the first-vertex casters the light
reaches are sampled at the centroids of a g x g grid of sub-triangles each (at most
``PROBE_POINTS`` points per light and chain: meshes with more triangles than that take every
s-th triangle, weighted s; ``PROBE_POINTS_TWO_BOUNCE`` for a two-bounce chain), and each point is traced forward exactly through the chain
(:func:`addon.solver.estimators.forward_image.trace_chain_points`: shadow ray from the light, scattering
with the interpolated normal and the contract's side rules, closest hits, Fresnel).  A point
that lands on a receiver carries its sub-triangle's flux, as the forward-flux estimator
computes it — point light: I f(w) Ω (Ω the sub-triangle's solid angle from the light); sun:
S times its area across the beam — times the transport factor and the tints.  The sums are a
midpoint quadrature of the flux the forward-flux estimator bakes; the plan only compares
them with a threshold (0.5 % of a receiver's caustic power by default), so a few per cent of
quadrature error do not matter.  Tested against full bakes (tests/bake/test_bake_plan.py).
"""

import math

import numpy as np

from ..solver.estimators.forward_image import solid_angle, trace_chain_points
from ..solver.geometry.receiver_planes import no_planes
from .lights import emission_factor, light_points, lit_casters

PROBE_POINTS = 1 << 15  # traced points per light and one-bounce chain at most
PROBE_POINTS_TWO_BOUNCE = 1 << 13  # ... and two-bounce chain (four of them per light: most of a plan's time)
PROBE_GRID_MAX = 64  # sub-triangles per side of a caster triangle (few large triangles: a dense grid)


def _grid_centroids(g):
    """(g², 3, 2) barycentric corners of a g x g grid of sub-triangles of the unit triangle."""
    corners = []
    for i in range(g):
        for j in range(g - i):
            corners.append(((i, j), (i + 1, j), (i, j + 1)))
            if i + j + 1 < g:
                corners.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
    return np.array(corners, dtype=np.float64) / g


def probe_chain(ctx, light_index, ls, chain, first, second, tri_rec, tri_uv, ledger, budget=PROBE_POINTS):
    """Add the estimated power (W, mean over RGB) of ``chain`` from light sample 0 of ``ls``
    (light ``light_index``) to ``ledger``, per first / second caster object and receiver.
    ``first`` / ``second``: global ids of the chain's first- and second-vertex casters;
    ``tri_rec`` / ``tri_uv``: receiver index and UVs per scene triangle.  Returns the number
    of points traced."""
    scene = ctx.scene
    first = np.asarray(first, dtype=np.int64)
    if first.size == 0:
        return 0
    stride = max(1, math.ceil(first.size / budget))
    first = first[::stride]  # every s-th caster, weighted s (mesh order is spatially coherent: a stratification)
    x0 = light_points(ls, 0, scene.tri_p[first], ctx.extent, ctx.settings.sun_distance)
    keep = lit_casters(ls, 0, x0, scene.tri_p[first])
    first, x0 = first[keep], np.ascontiguousarray(x0[keep])
    if first.size == 0:
        return 0
    g = int(min(PROBE_GRID_MAX, max(1, math.isqrt(budget // first.size))))
    base = _grid_centroids(g)
    k = base.shape[0]
    e = np.repeat(np.arange(first.size, dtype=np.int64), k)
    bary = np.tile(base, (first.size, 1, 1))
    uv1 = bary.mean(axis=1)
    n = e.size
    second_ok = np.zeros(scene.n_triangles, dtype=np.bool_)
    second_ok[np.asarray(second, dtype=np.int64)] = True
    t2 = np.empty(n, dtype=np.int64)
    rec = np.empty(n, dtype=np.int64)
    uv = np.empty((n, 2))
    fac = np.empty(n)
    bvh = ctx.bvh
    trace_chain_points(e, np.ascontiguousarray(uv1[:, 0]), np.ascontiguousarray(uv1[:, 1]), x0, first, len(chain),
                       chain[0] == "T", chain[-1] == "T", second_ok, tri_rec, tri_uv, scene.tri_p, scene.tri_n, scene.tri_ior,
                       scene.tri_role, bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order,
                       bvh.v0, bvh.e1, bvh.e2, float(ctx.eps), no_planes(), t2, rec, uv, fac)  # real landings only
    landed = np.flatnonzero(rec >= 0)
    if landed.size == 0:
        return n
    e, t2, rec, fac, bary = e[landed], t2[landed], rec[landed], fac[landed], bary[landed]
    t1 = first[e]
    P = scene.tri_p[t1]
    corners = P[:, None, 0] + bary[:, :, :1] * (P[:, None, 1] - P[:, None, 0]) + bary[:, :, 1:] * (P[:, None, 2] - P[:, None, 0])
    if ls.kind == "sun":
        gn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        power = 0.5 * np.abs(gn @ ls.direction[0])
    else:
        w0 = corners.mean(axis=1) - x0[e]
        w0 /= np.linalg.norm(w0, axis=1, keepdims=True)
        power = solid_angle(x0[e], corners) * emission_factor(ls, np.zeros(e.size, dtype=np.int64), w0)
    rgb = ls.rgb[0][None, :] * scene.tri_tint[t1]
    two = len(chain) == 2
    if two:
        rgb = rgb * scene.tri_tint[t2]
    power = power * fac * stride * rgb.mean(axis=1)
    ledger.add(light_index, chain, scene.tri_object[t1], scene.tri_object[t2] if two else None,
               tri_rec[rec], power)
    return n

