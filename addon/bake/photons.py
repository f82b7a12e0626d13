"""The bake with method "photon": light tracing into texel histograms (no bpy).

Instead of the per-tuple loop of :mod:`addon.bake.driver`, photons are traced from the
lights as the bake models them (:func:`addon.bake.lights.sample_light`: points with their
emission profile, sun directions; ``settings.light_samples`` of them per light) by
:mod:`addon.solver.photon`, following only the chains the plan bakes, and their flux is
binned per receiver texel.  A texel's value is

    E = flux / A,   A = the world area the texel covers on the receiver,

the texel-averaged irradiance (W/m²): an unbiased estimate of the average over the texel of
the per-point irradiance the tuple methods take at their supersamples.  A is measured from
the receiver's UV -> world mapping with :func:`addon.bake.raster.rasterise`: every
supersample of an s x s grid (s >= 4, centred) that lies on receiver triangle t stands for
1 / (W H s²) of UV area, i.e. area_world(t) / area_uv(t) / (W H s²) m².  Texels with A = 0
(no supersample on the receiver) are uncovered: photons landing there are dropped (a thin
band at UV island borders), then the image is padded over UV seams as the other methods do.

The sun is traced as exactly parallel light (the tuple methods put it at a far point,
relative irradiance error ~2e-5).  ``settings.direct`` adds the direct light with the
supersampled pass of the driver.
"""

import time

import numpy as np

from ..solver.photon import make_emitters, photon_steps
from .lights import sample_light
from .raster import bands, grid_side, pad, rasterise
from .scene import triangle_areas, uv_areas

AREA_SAMPLES = 16  # at least this many supersamples per texel to measure its area


def texel_areas(scene, rec, samples=AREA_SAMPLES, band_samples=1 << 20):
    """(H*W,) world area (m²) each texel of receiver ``rec`` covers on it (see the module docstring)."""
    W, H = rec.resolution
    S = grid_side(max(int(samples), AREA_SAMPLES)) ** 2
    uva = uv_areas(rec.uv)
    wa = triangle_areas(scene.tri_p[rec.tri_index])
    ratio_local = np.divide(wa, uva, out=np.zeros_like(wa), where=uva > 0)
    ratio = np.zeros(scene.n_triangles)
    ratio[rec.tri_index] = ratio_local
    area = np.zeros(W * H)
    for j0, j1 in bands(rec, S, band_samples):
        band = rasterise(scene, rec, S, 0, False, rows=(j0, j1))
        if band.size:
            area += np.bincount(band.texel, weights=ratio[band.tri], minlength=W * H) / (W * H * S)
    return area


def light_sample_dicts(scene, settings):
    """The light samples of every light as :func:`addon.solver.photon.make_emitters` takes them."""
    out = []
    for light in scene.lights:
        ls = sample_light(light, settings.light_samples, settings.seed)
        for m in range(ls.size):
            if ls.kind == "sun":
                out.append(dict(kind="sun", direction=ls.direction[m], rgb=ls.rgb[m]))
            else:
                out.append(dict(kind="point", position=ls.position[m], rgb=ls.rgb[m], lobe=ls.lobe[m], spot_axis=ls.spot_axis,
                                spot_cos=ls.spot_cos, spot_smooth=ls.spot_smooth))
    return out


def photon_bake_gen(scene, settings):
    """The generator behind ``bake_steps`` for ``settings.method == "photon"``: yields
    ``(fraction, message)`` after every batch of photons and returns a BakeResult whose report
    has the driver's layout (counts: photons, photons_deposited; chains: deposited per chain)."""
    from .driver import BakeResult, _direct, _with_resolution, bake_setup

    timer, t_start, warnings, bvh, extent, eps, plan = bake_setup(scene, settings)
    baked = [it for it in plan if it["status"] == "baked"]
    chains = [it["chain"] for it in baked]
    yield 0.0, "preparing"
    receivers = [_with_resolution(r, settings.resolution) if settings.resolution else r for r in scene.receivers]
    tri_rec = np.full(scene.n_triangles, -1, dtype=np.int64)
    tri_uv = np.zeros((scene.n_triangles, 3, 2))
    for r, rec in enumerate(receivers):
        tri_rec[rec.tri_index] = r
        tri_uv[rec.tri_index] = rec.uv
    t0 = time.perf_counter()
    first = np.unique(np.concatenate([it["vertices"][0] for it in baked])) if baked else np.zeros(0, dtype=np.int64)
    samples = light_sample_dicts(scene, settings)
    emitters = make_emitters(samples, scene.tri_p[first].reshape(-1, 3), extent, settings.photons if chains else 0)
    timer.add("emit", time.perf_counter() - t0)
    n_tex = sum(r.resolution[0] * r.resolution[1] for r in receivers)
    flux = np.zeros((n_tex, 3))
    photons, deposited, per_chain = 0, 0, {}
    if chains and int(emitters.start[-1]) > 0:
        t0 = time.perf_counter()
        steps = photon_steps(scene.tri_p, scene.tri_n, scene.tri_role, scene.tri_ior, scene.tri_tint, tri_rec, tri_uv,
                             [r.resolution for r in receivers], emitters, chains, seed=settings.seed, bvh=bvh, eps=eps)
        while True:
            try:
                done, total = next(steps)
            except StopIteration as fin:
                res = fin.value
                break
            timer.add("trace", time.perf_counter() - t0)
            yield 0.9 * done / max(1, total), f"photons: {done:,}/{total:,}"
            t0 = time.perf_counter()
        timer.add("trace", time.perf_counter() - t0)
        flux, photons, deposited, per_chain = res.flux, res.photons, res.deposited, res.per_chain
    images, coverage, raw, rec_report = {}, {}, {}, {}
    offset = 0
    for rec in receivers:
        W, H = rec.resolution
        t0 = time.perf_counter()
        area = texel_areas(scene, rec, settings.samples, settings.band_samples)
        timer.add("area", time.perf_counter() - t0)
        covered = area > 0
        f = flux[offset:offset + W * H]
        offset += W * H
        img = np.zeros((W * H, 3))
        img[covered] = f[covered] / area[covered, None]
        if settings.direct:
            sums = np.zeros((W * H, 3))
            cover = np.zeros(W * H, dtype=np.int64)
            for j0, j1 in bands(rec, settings.samples, settings.band_samples):
                band = rasterise(scene, rec, settings.samples, settings.seed, settings.jitter, rows=(j0, j1))
                cover += np.bincount(band.texel, minlength=W * H)
                if band.size:
                    for light in scene.lights:
                        _direct(scene, bvh, eps, extent, sample_light(light, settings.light_samples, settings.seed), band, sums, timer)
            ok = covered & (cover > 0)
            img[ok] += sums[ok] / cover[ok, None]
        img = img.reshape(H, W, 3)
        cov2 = covered.reshape(H, W)
        t0 = time.perf_counter()
        padded, _ = pad(img, cov2, settings.margin)
        timer.add("pad", time.perf_counter() - t0)
        images[rec.name] = padded.astype(np.float32)
        coverage[rec.name] = cov2
        raw[rec.name] = img
        touched = int(np.count_nonzero(np.any(img.reshape(-1, 3) > 0, axis=1)))
        rec_report[rec.name] = {
            "resolution": [W, H], "uv_map": rec.uv_map, "texels_covered": int(covered.sum()), "texels_touched": touched,
            "max_irradiance": float(img.max()) if img.size else 0.0,
            "mean_irradiance_covered": float(img.reshape(-1, 3)[covered].mean()) if covered.any() else 0.0,
        }
        yield 0.9 + 0.1 * offset / max(1, n_tex), f"{rec.name}: texel areas"
    report = {
        "method": "photon",
        "settings": settings.as_dict(),
        "scene": {
            "frame": scene.frame, "triangles": int(scene.n_triangles), "casters": int(scene.casters().size),
            "objects": len(scene.objects), "receivers": [r.name for r in scene.receivers],
            "lights": [light.as_dict() for light in scene.lights], "extent": extent,
        },
        "chains": [{"chain": it["chain"], "casters_per_vertex": [int(v.size) for v in it["vertices"]], "status": it["status"],
                    **({"photons_deposited": per_chain.get(it["chain"], 0)} if it["status"] == "baked" else {})} for it in plan],
        "timings": {**timer.t, "bake_total": time.perf_counter() - t_start},
        "counts": {"photons": int(photons), "photons_deposited": int(deposited), "light_samples": len(samples),
                   "tuples": 0, "tuples_naive": 0, "paths_visible": int(deposited),
                   "texels": int(sum(r["resolution"][0] * r["resolution"][1] for r in rec_report.values())),
                   "texels_covered": int(sum(r["texels_covered"] for r in rec_report.values())),
                   "texels_touched": int(sum(r["texels_touched"] for r in rec_report.values()))},
        "receivers": rec_report,
        "warnings": warnings,
    }
    return BakeResult(images, coverage, raw, report)
