"""The bake pipeline: a scene model in, caustic irradiance textures and a report out (no bpy).

1. set-up: the BVH over every triangle (visibility), the receivers at the bake's resolution,
   the light samples (:mod:`addon.bake.lights`);
2. plan (:mod:`addon.bake.plan`): which chains each light x caster x receiver needs;
3. the estimators of the planned chains (:mod:`addon.bake.estimators`): ``prepare``, then
   per receiver and band of texel rows ``accumulate`` (irradiance at the supersamples; a
   texel holds their mean), then per receiver ``receiver_flux`` (W per texel, divided by the
   texel's world area: texel-averaged irradiance);
4. padding over UV seams (:func:`addon.bake.raster.pad`) and the report (timings per stage,
   counts, the plan with estimated and baked energy shares, warnings).

:func:`bake_steps` is the resumable form (a generator yielding ``(fraction, message)`` between
bounded chunks; the Blender operator drives it from a timer); :func:`bake` is a loop over it.
Deterministic for a seed: every parallel kernel writes disjoint outputs and the sums run in
a fixed order.  What a texel holds (units, front side, cosine) is in addon/bake/README.md.
"""

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from ..solver.geometry.bvh import build_bvh, segments_occluded
from .context import VISIBILITY_OFFSET, BakeCancelled, BakeContext, with_resolution, world_per_uv_area
from .estimators import make_estimator
from .estimators.base import Estimator
from .exr import write_exr
from .lights import emission_factor, sample_light
from .plan import CHAINS, make_plan
from .raster import bands, grid_side, pad, rasterise
from .scene import SceneError
from .settings import BakeSettings, check_settings, resolve_aliases

__all__ = ["BakeSettings", "BakeResult", "BakeCancelled", "bake", "bake_steps", "make_context", "safe_filename",
           "direct_light", "texel_areas", "VISIBILITY_OFFSET"]


@dataclass
class BakeResult:
    images: dict  # receiver name -> (H, W, 3) float32 irradiance W/m², row 0 = bottom (v = 0), padded
    coverage: dict  # receiver name -> (H, W) bool, texels with samples on the receiver
    raw: dict  # receiver name -> (H, W, 3) float64 before padding
    report: dict = field(default_factory=dict)

    def write(self, out_dir):
        """Write ``<receiver>.exr`` per receiver and ``report.json`` into ``out_dir``."""
        os.makedirs(out_dir, exist_ok=True)
        t0 = time.perf_counter()
        files = {}
        for name, img in self.images.items():
            path = os.path.join(out_dir, safe_filename(name) + ".exr")
            write_exr(path, img)
            files[name] = os.path.basename(path)
        self.report.setdefault("timings", {})["write"] = time.perf_counter() - t0
        self.report["files"] = files
        with open(os.path.join(out_dir, "report.json"), "w") as fh:
            json.dump(self.report, fh, indent=2, default=_json_default)
        return files


def safe_filename(name):
    bad = '<>:"/\\|?*\0'
    out = "".join("_" if (c in bad or ord(c) < 32) else c for c in name).strip().rstrip(".")
    return out or "receiver"


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def bake(scene, settings=None, progress=None):
    """Bake every receiver of ``scene``; returns a :class:`BakeResult`.

    ``progress(fraction, message)`` is called between chunks (``fraction`` is None where the
    share of the work done is not known); returning False cancels (:class:`BakeCancelled`).
    A plain loop over :func:`bake_steps`.
    """
    steps = bake_steps(scene, settings)
    while True:
        try:
            fraction, message = next(steps)
        except StopIteration as done:
            return done.value
        if progress is not None and progress(fraction, message) is False:
            steps.close()
            raise BakeCancelled()


def bake_steps(scene, settings=None):
    """The resumable form of :func:`bake`: checks the settings and the scene now (raising
    :class:`SceneError`), then returns a generator that does the bake in bounded chunks,
    yielding ``(fraction, message)`` between them (``fraction`` in [0, 1], or None) and
    returning the :class:`BakeResult` (``StopIteration.value``).

    Closing the generator (``.close()``) abandons the bake; nothing outside it was changed.
    ``settings`` is not modified (its legacy aliases are resolved on a copy).
    """
    settings = resolve_aliases(dataclasses.replace(settings or BakeSettings()))
    if settings.samples < 1:
        raise SceneError("samples must be at least 1")
    if settings.resolution < 0 or settings.resolution > 16384:
        raise SceneError("resolution must be between 1 and 16384")
    try:
        check_settings(settings)
    except ValueError as ex:
        raise SceneError(str(ex)) from None
    scene.validate()
    return _bake_gen(scene, settings)


def make_context(scene, settings):
    """The :class:`BakeContext` of a bake: threads, the BVH over every triangle, the scene
    extent and visibility offset, the receivers at the bake's resolution, the light samples."""
    if settings.threads:
        from ..solver.runtime.jit import set_num_threads

        set_num_threads(settings.threads)
    t0 = time.perf_counter()
    bvh = build_bvh(scene.tri_p)
    extent = scene.extent()
    receivers = [with_resolution(r, settings.resolution) if settings.resolution else r for r in scene.receivers]
    lsamples = [sample_light(light, settings.light_samples, settings.seed) for light in scene.lights]
    ctx = BakeContext(scene, settings, bvh, VISIBILITY_OFFSET * extent, extent, receivers, lsamples,
                      warnings=list(scene.warnings))
    ctx.timer.add("bvh", time.perf_counter() - t0)
    return ctx


def _bake_gen(scene, settings):
    t_start = time.perf_counter()
    ctx = make_context(scene, settings)
    timer = ctx.timer
    yield 0.0, "planning"
    t0 = time.perf_counter()
    plan = make_plan(ctx)
    timer.add("plan", time.perf_counter() - t0)
    if settings.caustics and not plan.items:
        ctx.warnings.append("no casters: the scene has no reflecting or refracting surfaces (only the direct light is baked if asked)")
    by_name = {}
    for it in plan.baked_items():
        by_name.setdefault(it.estimator, []).append(it)
    estimators = [make_estimator(name, ctx, items) for name, items in by_name.items()]
    for est in estimators:
        yield from est.prepare()
    images, coverage, raw, rec_report = {}, {}, {}, {}
    total_rows = sum(r.resolution[1] for r in ctx.receivers)
    rows_done = 0
    # only the supersamples' count per texel is needed when no estimator reads the samples:
    # a function of the receiver's UVs alone, kept like the texel areas
    counts_only = not settings.direct and all(type(e).accumulate is Estimator.accumulate for e in estimators)
    for rec_index, rec in enumerate(ctx.receivers):
        W, H = rec.resolution
        sums = np.zeros((W * H, 3))
        cover = np.zeros(W * H, dtype=np.int64)
        key = kept = None
        if counts_only:
            key = _receiver_key(rec, settings.samples, settings.seed, settings.jitter, settings.band_samples)
            kept = _kept(_COVER_CACHE, key)
            if kept is not None:
                cover = kept
                rows_done += H
                yield rows_done / max(1, total_rows), f"{rec.name}: rows {H}/{H}"
        for j0, j1 in (bands(rec, settings.samples, settings.band_samples) if cover is not kept else ()):
            t0 = time.perf_counter()
            band = rasterise(scene, rec, settings.samples, settings.seed, settings.jitter, rows=(j0, j1))
            cover += np.bincount(band.texel, minlength=W * H)
            timer.add("raster", time.perf_counter() - t0)
            if band.size:
                if settings.direct:
                    for ls in ctx.lsamples:
                        direct_light(ctx, ls, band, sums)
                for est in estimators:
                    yield from est.accumulate(rec_index, band, sums)
            rows_done += j1 - j0
            yield rows_done / max(1, total_rows), f"{rec.name}: rows {j1}/{H}"
        if key is not None:
            _keep(_COVER_CACHE, key, cover)
        covered = cover > 0
        img = np.zeros((W * H, 3))
        img[covered] = sums[covered] / cover[covered, None]
        flux = None
        for est in estimators:
            f = yield from est.receiver_flux(rec_index)
            if f is not None:
                flux = f if flux is None else flux + f
        if flux is not None:
            t0 = time.perf_counter()
            area = texel_areas(scene, rec, settings.samples, settings.band_samples)
            ok = covered & (area > 0)
            img[ok] += flux[ok] / area[ok, None]
            timer.add("texel_area", time.perf_counter() - t0)
        t0 = time.perf_counter()
        img = img.reshape(H, W, 3)
        cov2 = covered.reshape(H, W)
        padded, _ = pad(img, cov2, settings.margin)
        timer.add("pad", time.perf_counter() - t0)
        images[rec.name] = padded.astype(np.float32)
        coverage[rec.name] = cov2
        raw[rec.name] = img
        touched = int(np.count_nonzero(np.any(img.reshape(-1, 3) > 0, axis=1)))
        rec_report[rec.name] = {
            "resolution": [W, H], "uv_map": rec.uv_map, "texels_covered": int(covered.sum()), "texels_touched": touched,
            "caustic_power": ctx.ledger.total(receiver=rec_index),
            "max_irradiance": float(img.max()) if img.size else 0.0,
            "mean_irradiance_covered": float(img.reshape(-1, 3)[covered].mean()) if covered.any() else 0.0,
        }
    report = _report(ctx, plan, estimators, rec_report, time.perf_counter() - t_start)
    return BakeResult(images, coverage, raw, report)


def texel_areas(scene, rec, samples=16, band_samples=1 << 20):
    """(H*W,) world area (m²) each texel of receiver ``rec`` covers on it: every supersample
    of an s x s grid (s >= 4, centred) on receiver triangle t stands for
    area_world(t) / area_uv(t) / (W H s²) m².  A function of the receiver's triangles, UVs
    and resolution only: the last ``AREA_CACHE_SIZE`` results are kept (read-only) under a
    hash of those, so a receiver that does not move between frames is measured once."""
    key = _receiver_key(rec, samples, band_samples, scene.tri_p[rec.tri_index])
    area = _kept(_AREA_CACHE, key)
    if area is None:
        area = _texel_areas(scene, rec, samples, band_samples)
    return _keep(_AREA_CACHE, key, area)


_AREA_CACHE = {}  # texel areas per receiver key, most recent last
_COVER_CACHE = {}  # supersamples per texel per receiver key (bake_steps, when only their count is needed)
AREA_CACHE_SIZE = 8


def _receiver_key(rec, *values):
    """A hash of receiver ``rec``'s triangles, UVs and resolution and of ``values``."""
    parts = [rec.tri_index, rec.uv, np.asarray(rec.resolution, dtype=np.int64)]
    parts += [np.asarray(v, dtype=np.float64) for v in values]
    return hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in parts)).hexdigest()


def _kept(cache, key):
    """The result kept under ``key`` (None: none)."""
    return cache.get(key)


def _keep(cache, key, value):
    """Keep ``value`` (made read-only) under ``key``, the most recent last, at most
    AREA_CACHE_SIZE entries; returns it."""
    cache.pop(key, None)
    value.flags.writeable = False
    cache[key] = value
    while len(cache) > AREA_CACHE_SIZE:
        cache.pop(next(iter(cache)))
    return value

def _texel_areas(scene, rec, samples, band_samples):
    W, H = rec.resolution
    S = grid_side(max(int(samples), AREA_SAMPLES)) ** 2
    ratio = world_per_uv_area(scene, rec)
    area = np.zeros(W * H)
    for j0, j1 in bands(rec, S, band_samples):
        band = rasterise(scene, rec, S, 0, False, rows=(j0, j1))
        if band.size:
            area += np.bincount(band.texel, weights=ratio[band.tri], minlength=W * H) / (W * H * S)
    return area


AREA_SAMPLES = 16  # at least this many supersamples per texel to measure a texel's world area


def _report(ctx, plan, estimators, rec_report, total):
    scene, settings = ctx.scene, ctx.settings
    counts = dict.fromkeys(("tuples_naive", "tuples_tile_cull", "tuples", "paths", "paths_front", "paths_lit", "paths_visible"), 0)
    chain_counts = {}
    est_reports = {}
    for est in estimators:
        for k, v in est.counts.items():
            counts[k] += v
        for c, cc in est.chain_counts.items():
            tgt = chain_counts.setdefault(c, {"tuples": 0, "paths": 0, "paths_visible": 0})
            for k, v in cc.items():
                tgt[k] += v
        est_reports[est.name] = {"chains": sorted({it.chain for it in est.items}, key=_chain_order), "device": est.device,
                                 **est.report()}
    S = grid_side(settings.samples) ** 2
    n_samples = sum(S * r.resolution[0] * r.resolution[1] for r in ctx.receivers)
    for it in plan.baked_items():
        if it.estimator == "path-points":
            counts["tuples_naive"] += int(np.prod([v.size for v in it.vertices])) * n_samples * ctx.lsamples[it.light].size
    chains = []
    for c in sorted({it.chain for it in plan.items}, key=_chain_order):
        its = [it for it in plan.items if it.chain == c]
        baked = [it for it in its if it.baked]
        status = "baked" if baked else its[0].status
        chains.append({"chain": c, "estimator": its[0].estimator, "status": status,
                       "casters_per_vertex": [int(v.size) for v in its[0].vertices],
                       "lights": [scene.lights[it.light].name for it in baked],
                       "receivers": sorted({ctx.receivers[r].name for it in baked for r in it.receivers}),
                       **chain_counts.get(c, {"tuples": 0, "paths": 0, "paths_visible": 0})})
        if not baked and not _planned_skip(status):
            ctx.warnings.append(f"chain {c} {status}")
    passes = [p for r in est_reports.values() for p in r.get("passes", [])]
    dropped = sum(p["dropped"] for p in passes)
    if dropped:
        ctx.warnings.append(f"forward images: {dropped:,} sub-triangles partly lost (rays missing the receivers or total "
                            "internal reflection at the deepest level) were not counted")
    photon = est_reports.get("photon")
    if photon:
        counts["photons"], counts["photons_deposited"] = photon["photons"], photon["photons_deposited"]
    ff = est_reports.get("forward-flux")
    if ff:
        counts["sub_triangles"] = ff["sub_triangles"]
    report = {
        "estimator": ", ".join(est_reports) or settings.estimator,  # what ran
        "solver": settings.solver if "path-points" in est_reports else None,
        "estimators": est_reports,
        "devices": {name: r["device"] for name, r in est_reports.items()},
        "settings": settings.as_dict(),
        "scene": {
            "frame": scene.frame, "triangles": int(scene.n_triangles), "casters": int(scene.casters().size),
            "objects": len(scene.objects), "receivers": [r.name for r in scene.receivers],
            "lights": [light.as_dict() for light in scene.lights], "extent": ctx.extent,
        },
        "plan": plan.report(scene, ctx.receivers, ctx.ledger),
        "chains": chains,
        "timings": {**ctx.timer.t, "bake_total": total},
        "counts": {**counts, "texels": int(sum(r["resolution"][0] * r["resolution"][1] for r in rec_report.values())),
                   "texels_covered": int(sum(r["texels_covered"] for r in rec_report.values())),
                   "texels_touched": int(sum(r["texels_touched"] for r in rec_report.values()))},
        "receivers": rec_report,
        "warnings": ctx.warnings,
    }
    return report


def _planned_skip(status):
    """Whether ``status`` is the planner's energy decision (reported in the plan, not a warning)."""
    return status.startswith(("skipped: the probe", "skipped: at most"))


def _chain_order(c):
    return CHAINS.index(c)


def direct_light(ctx, ls, band, sums, chunk=1 << 21):
    """Direct light onto the samples (the chain of length 0): I f(w) cos / d², or S cos for the
    sun; all light samples at once, in chunks of (light sample, receiver sample) pairs."""
    scene, bvh, eps, extent, timer = ctx.scene, ctx.bvh, ctx.eps, ctx.extent, ctx.timer
    t0 = time.perf_counter()
    n = band.size
    per = max(1, chunk // max(1, n))
    for m0 in range(0, ls.size, per):
        ms = np.arange(m0, min(ls.size, m0 + per))
        mi = np.repeat(ms, n)
        si = np.tile(np.arange(n), ms.size)
        x2 = band.position[si]
        if ls.kind == "sun":
            w = ls.direction[mi]
            a = x2 - 2.0 * extent * w
            val = np.maximum(0.0, -np.sum(w * band.normal[si], axis=1))
        else:
            a = ls.position[mi]
            d = x2 - a
            dist = np.linalg.norm(d, axis=1)
            w = d / dist[:, None]
            val = np.maximum(0.0, -np.sum(w * band.normal[si], axis=1)) / (dist * dist)
            val *= emission_factor(ls, mi, w)
        front = -np.sum(w * band.geo_normal[si], axis=1) > 0
        val = np.where(front, val, 0.0)
        idx = np.flatnonzero(val > 0)
        ig = np.column_stack([band.tri[si[idx]], np.full(idx.size, -1)])
        blocked = segments_occluded(bvh, a[idx], x2[idx], ig, eps)
        vis = idx[~blocked]
        for c in range(3):
            sums[:, c] += np.bincount(band.texel[si[vis]], weights=val[vis] * ls.rgb[mi[vis], c], minlength=sums.shape[0])
    timer.add("direct", time.perf_counter() - t0)
