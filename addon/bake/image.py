"""Two-bounce chains in the bake by forward-image seeding (no bpy; the maths is in
:mod:`addon.solver.forward_image`).

``BakeSettings.two_bounce == "image"`` (the default): for each light sample and two-bounce
chain, the first-vertex casters that the light reaches are cut into adaptive sub-triangles
whose forward-traced images on the receivers are straight to within half a texel
(:func:`prepare`, once per light sample and chain, shared by every receiver and band); per
band, every sample near a sub-triangle's image gets a seed, Newton solves the exact path
through the tuple the seed's ray passes, and duplicates are merged (:func:`band_paths`).
The paths then go through the driver's weighting, visibility and accumulation like the
exact solver's.  ``"exact"``: the cone cull and the two-bounce Specular Polynomials (every
path of every candidate tuple; complete, but 1–100 ms per tuple and sample).
"""

import time

import numpy as np

from ..solver.bvh import segments_occluded
from ..solver.forward_image import (ImageSeeds, corner_densities, dedupe_paths, light_area_density, refine_image_triangles,
                                    solid_angle, solve_image_seeds, splat_triangles, trace_chain_points)
from .lights import emission_factor

IMAGE_GRID = 4  # first level: G x G sub-triangles per caster triangle
IMAGE_TOLERANCE = 0.5  # texels: a final sub-triangle's image is straight to within this
IMAGE_MARGIN = 0.25  # texels added around every image (plus twice its measured deviation)


class ImageState:
    """The refined sub-triangles of one (light sample, chain) and what the solve needs."""

    def __init__(self, chain, emit_tri, x0, tris, arrays, report):
        self.chain = chain
        self.emit_tri = emit_tri  # (n,) global first-triangle id per emitter
        self.x0 = x0  # (n, 3) light point per emitter
        self.tris = tris  # dict of refine_image_triangles
        self.arrays = arrays
        self.report = report


def scene_arrays(scene, receivers, second):
    """receiver index and UVs per scene triangle, and the mask of valid second vertices."""
    n = scene.n_triangles
    tri_rec = np.full(n, -1, dtype=np.int64)
    tri_uv = np.zeros((n, 3, 2))
    for r, rec in enumerate(receivers):
        tri_rec[rec.tri_index] = r
        tri_uv[rec.tri_index] = rec.uv
    second_ok = np.zeros(n, dtype=np.bool_)
    second_ok[second] = True
    return tri_rec, tri_uv, second_ok


def _bvh_args(bvh):
    return (bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order, bvh.v0, bvh.e1, bvh.e2)


def prepare(scene, bvh, eps, chain, emit_tri, x0, second, receivers, max_depth=6, mode="flux", parallel=False):
    """Refine the sub-triangles of the emitters (first triangles ``emit_tri`` lit from ``x0``)
    for ``chain`` (one or two vertices; "seeded" needs two); ``second`` the global ids of
    the chain's second-vertex casters (ignored for one vertex); ``receivers`` the receivers at
    the bake's resolution; ``mode`` "flux" or "seeded" (how finely to refine); ``parallel``:
    a sun (the same flux per area all over a first triangle).  Returns an ImageState."""
    t0 = time.perf_counter()
    tri_rec, tri_uv, second_ok = scene_arrays(scene, receivers, second)
    refract1, refract2 = chain[0] == "T", chain[-1] == "T"
    bounces = len(chain)
    emit_tri = np.ascontiguousarray(emit_tri, dtype=np.int64)
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    tri_p = np.ascontiguousarray(scene.tri_p, dtype=np.float64)
    tri_n = np.ascontiguousarray(scene.tri_n, dtype=np.float64)
    tri_ior = np.ascontiguousarray(scene.tri_ior, dtype=np.float64)
    tri_role = np.ascontiguousarray(scene.tri_role, dtype=np.int64)
    bvh_args = _bvh_args(bvh)

    def trace(e, u, v):
        """(second triangle, receiver triangle, UV, transport factor) of the points."""
        m = e.shape[0]
        t2 = np.empty(m, dtype=np.int64)
        rec = np.empty(m, dtype=np.int64)
        uv = np.empty((m, 2))
        fac = np.empty(m)
        if m:
            trace_chain_points(np.ascontiguousarray(e), np.ascontiguousarray(u), np.ascontiguousarray(v), x0, emit_tri,
                               bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, *bvh_args,
                               float(eps), t2, rec, uv, fac)
        return t2, rec, uv, fac

    def weight(e, bary):
        if parallel:
            return np.ones(bary.shape[:2])
        return light_area_density(x0[e], tri_p[emit_tri[e]], bary)

    texel = np.array([1.0 / max(r.resolution) for r in receivers]) if receivers else np.ones(1)
    # "seeded" needs images straight to the margin only (Newton does the rest); "flux" also a
    # near-uniform density and a finely resolved border of what lands.
    extra = dict(weight=weight) if mode == "flux" else dict(relative=np.inf, partial_depth=max_depth)
    tris = refine_image_triangles(trace, emit_tri.size, tri_rec, texel, grid=IMAGE_GRID, max_depth=max_depth,
                                  tolerance=IMAGE_TOLERANCE, **extra)
    r = tris["receiver"]
    tris["margin"] = IMAGE_MARGIN * texel[r] + 2.0 * tris["deviation"] if r.size else np.zeros(0)
    arrays = dict(tri_rec=tri_rec, second_ok=second_ok, refract1=refract1, refract2=refract2, tri_p=tri_p, tri_n=tri_n,
                  tri_ior=tri_ior, tri_role=tri_role, bvh=bvh_args, eps=float(eps), trace=trace)
    report = {"emitters": int(emit_tri.size), "points_traced": int(tris["traced"]), "sub_triangles": int(r.size),
              "dropped": int(tris["dropped"]), "partial": int(tris["partial"]), "border": int(tris["border"]), "final_per_depth": tris["final_per_depth"],
              "seconds": time.perf_counter() - t0}
    return ImageState(chain, emit_tri, x0, tris, arrays, report)


def band_paths(state, rec_index, band, max_seeds=1 << 20):
    """The distinct exact paths of ``state``'s chain onto the samples of ``band`` (receiver
    number ``rec_index``): (tri (n, 2) global ids, x_start (n, 3), sample (n,), uv (n, 4),
    counts dict).  Seeds are solved in batches (bounded memory); duplicates are merged over
    the whole band."""
    tris = state.tris
    a = state.arrays
    sel = np.flatnonzero(tris["receiver"] == rec_index)
    seeds = ImageSeeds(tris["uv"][sel], tris["bary"][sel], tris["emitter"][sel], tris["margin"][sel], band.width,
                       band.height, band.row0, band.row1, band.texel, band.uv)
    position = np.ascontiguousarray(band.position, dtype=np.float64)
    found_e, found_s, found_t2, found_uv = [], [], [], []
    counts = {"seeds": seeds.total, "newton": 0, "hops": 0, "converged": 0, "paths": 0}
    for e, seed, s in seeds.batches(max_seeds):
        n = e.size
        ok = np.zeros(n, dtype=np.bool_)
        t2 = np.full(n, -1, dtype=np.int64)
        uv = np.zeros((n, 4))
        stats = np.zeros(((n + 255) // 256, 3), dtype=np.int64)
        solve_image_seeds(e, seed, s, state.x0, state.emit_tri, position, a["refract1"], a["refract2"], a["second_ok"],
                          a["tri_rec"], a["tri_p"], a["tri_n"], a["tri_ior"], a["tri_role"], *a["bvh"], a["eps"], ok, t2, uv,
                          stats)
        counts["newton"] += int(stats[:, 0].sum())
        counts["hops"] += int(stats[:, 1].sum())
        good = np.flatnonzero(ok)
        counts["converged"] += int(good.size)
        found_e.append(e[good])
        found_s.append(s[good])
        found_t2.append(t2[good])
        found_uv.append(uv[good])
    if not found_e:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 4)), counts
    e = np.concatenate(found_e)
    s = np.concatenate(found_s)
    t2 = np.concatenate(found_t2)
    uv = np.concatenate(found_uv)
    t1 = state.emit_tri[e]
    keep = dedupe_paths(s, t1, t2, uv)
    counts["paths"] = int(keep.size)
    tri = np.column_stack([t1[keep], t2[keep]])
    return tri, state.x0[e[keep]], s[keep], uv[keep], counts


def flux_textures(state, scene, bvh, eps, extent, ls, m, receivers):
    """The "flux" estimator: every final sub-triangle carries the flux the light sample sends
    through it (point: I f(w) Ω, Ω its solid angle from the light; sun: S times its area
    across the beam), times the transport factor of the path through its centroid (Fresnel,
    the receiver's cos_shading / cos_geometric), the tints of both vertices, the fraction of
    its points that landed, and the visibility of the light from its centroid; the flux is
    spread over its straight image in UV space by exact texel overlap with a density linear
    over the image (forward_image.corner_densities) (the other two path
    segments are unoccluded by construction: they are closest hits).  Returns one (H W, 3)
    array of W per texel per receiver; divided by the texels' world areas it is the
    texel-averaged irradiance, finite at focal points where point samples are not."""
    tris = state.tris
    out = [np.zeros((r.resolution[0] * r.resolution[1], 3)) for r in receivers]
    e = tris["emitter"]
    n = e.size
    if n == 0:
        return out
    t1 = state.emit_tri[e]
    P = scene.tri_p[t1]
    b = tris["bary_full"]
    corners = P[:, None, 0] + b[:, :, :1] * (P[:, None, 1] - P[:, None, 0]) + b[:, :, 1:] * (P[:, None, 2] - P[:, None, 0])
    bc = tris["bary"].mean(axis=1)  # the landed part's centre (a partly landed sub-triangle's bary is shrunk to it)
    t2, rec, _uv, fac = state.arrays["trace"](e, np.ascontiguousarray(bc[:, 0]), np.ascontiguousarray(bc[:, 1]))
    x1 = corners.mean(axis=1)
    x0 = state.x0[e]
    if ls.kind == "sun":
        d = ls.direction[m]
        g = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        power = 0.5 * np.abs(g @ d)
        first = x1 - 2.0 * extent * d
    else:
        w0 = x1 - x0
        w0 /= np.linalg.norm(w0, axis=1, keepdims=True)
        power = solid_angle(x0, corners) * emission_factor(ls, np.full(n, m), w0)
        first = x0
    power = power * np.where(rec >= 0, fac, 0.0) * tris["landed"]
    live = np.flatnonzero(power > 0)
    if live.size:
        ig = np.column_stack([t1[live], np.full(live.size, -1)])
        blocked = segments_occluded(bvh, first[live], x1[live], ig, eps)
        power[live[blocked]] = 0.0
    tint2 = np.where((t2 >= 0)[:, None], scene.tri_tint[np.maximum(t2, 0)], 1.0)  # one-vertex chains: no second tint
    flux = power[:, None] * ls.rgb[m][None, :] * scene.tri_tint[t1] * tint2
    # the transport factor at the corners (Fresnel varies over large images); partly landed
    # sub-triangles have no midpoints and get the uniform splat anyway
    cf = np.nan_to_num(tris["factor"][:, :3], nan=1.0)
    if ls.kind == "sun":  # parallel light: the same solid angle per area everywhere
        far = corners.mean(axis=1) - 1e6 * extent * d
        density = corner_densities(tris["uv"], tris["mid_uv"], far, P, b, cf)
    else:
        density = corner_densities(tris["uv"], tris["mid_uv"], x0, P, b, cf)
    for r, recv in enumerate(receivers):
        sel = np.flatnonzero(tris["receiver"] == r)
        if sel.size:
            W, H = recv.resolution
            splat_triangles(np.ascontiguousarray(tris["uv"][sel]), np.ascontiguousarray(flux[sel]), int(W), int(H), out[r],
                            np.ascontiguousarray(density[sel]))
    return out
