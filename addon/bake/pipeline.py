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
The fraction (:class:`Progress`) follows each stage's own count of work (probes, forward
images, texel rows, texel areas, padding), and the message ends with the time left once it
can be estimated.
Deterministic for a seed: every parallel kernel writes disjoint outputs and the sums run in
a fixed order.  What a texel holds (units, front side, cosine) is in addon/bake/README.md.
"""

import dataclasses
import hashlib
import json
import os
import re
import time
from dataclasses import dataclass, field

import numpy as np

from ..solver.geometry.bvh import box_area, build_bvh, refit_bvh, segments_occluded
from .checks import scene_warnings
from .context import VISIBILITY_OFFSET, BakeCancelled, BakeContext, with_resolution, world_per_uv_area
from .estimators import make_estimator
from . import exr
from .estimators.base import Estimator
from .lights import emission_factor, sample_light
from .kept import keep_recent
from .memory import check_budget, out_of_memory
from .output import write_files, write_text
from .names import frame_report_filename, safe_filename, texture_filename
from .plan import CHAINS, candidate_chains, plan_steps
from .raster import bands, grid_side, pad, raster_texels, rasterise, texel_irradiance
from .scene import SceneError
from .settings import BakeSettings, check_settings, resolve_aliases

__all__ = ["BakeSettings", "BakeResult", "BakeCancelled", "bake", "bake_steps", "make_context", "safe_filename",
           "texture_filename", "frame_report_filename", "write_sequence_report", "direct_light", "texel_areas",
           "VISIBILITY_OFFSET"]


@dataclass
class BakeResult:
    images: dict  # receiver name -> (H, W, 3) float32 irradiance W/m², row 0 = bottom (v = 0), padded
    coverage: dict  # receiver name -> (H, W) bool, texels with samples on the receiver
    raw: dict  # receiver name -> (H, W, 3) float64 before padding
    report: dict = field(default_factory=dict)

    def write(self, out_dir, frame=None, record=True):
        """Write the textures and the report into ``out_dir``, all or nothing
        (:func:`addon.bake.output.write_files`: temporary files renamed over the final names once
        every one is complete; :class:`~addon.bake.output.OutputError` otherwise, with the
        files already there untouched): per receiver the file :func:`texture_filename` names
        (``<receiver>.exr``, or ``<receiver>.<frame>.exr`` with ``frame``, unique among the
        receivers) and ``report.json``, or with ``frame`` that frame's report
        (:func:`frame_report_filename`; :func:`write_sequence_report` then indexes the frames).
        ``record``: list the files in the folder's manifest.  Returns {receiver: file name}."""
        t0 = time.perf_counter()
        files = {name: texture_filename(name, frame, receivers=self.images) for name in self.images}
        self.report["files"] = files
        writers = {files[name]: (lambda tmp, img=img: exr.write_exr(tmp, img)) for name, img in self.images.items()}

        def write_report(tmp):
            self.report.setdefault("timings", {})["write"] = time.perf_counter() - t0
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(self.report, fh, indent=2, default=_json_default)

        writers["report.json" if frame is None else frame_report_filename(frame)] = write_report
        write_files(out_dir, writers, record=record)
        return files

    def output_names(self, frame=None):
        """The names :meth:`write` writes (textures, then the report)."""
        return [texture_filename(n, frame, receivers=self.images) for n in self.images] + [
            "report.json" if frame is None else frame_report_filename(frame)]


SEQUENCE_REPORT = "report.json"
_FRAME_REPORT = re.compile(r"report\.(\d+)\.json")


def write_sequence_report(out_dir):
    """Rebuild ``out_dir/report.json`` from the frame reports in ``out_dir`` (the files
    :func:`frame_report_filename` names, each written once by whichever process baked that
    frame, so that jobs baking different frames into one folder never write the same report)
    and return it: ``frames`` (sorted), ``files`` ({receiver: [file per frame]}), ``timings``
    (the frames' sums), ``warnings`` (each prefixed with its frame) and ``per_frame``: per
    frame its report's file and the essentials of it (input, files, plan summary, estimators'
    names, timings, counts, per-receiver figures, warnings)."""
    per_frame = {}
    for fname in sorted(os.listdir(out_dir)):
        m = _FRAME_REPORT.fullmatch(fname)
        if m is None:
            continue
        try:
            with open(os.path.join(out_dir, fname), encoding="utf-8") as fh:
                per_frame[int(m.group(1))] = (fname, json.load(fh))
        except (OSError, ValueError):
            continue  # not a report this module wrote (they are written whole, by renaming)
    frames = sorted(per_frame)
    files, timings, entries = {}, {}, {}
    for f in frames:
        fname, rep = per_frame[f]
        for name, tex in rep.get("files", {}).items():
            files.setdefault(name, []).append(tex)
        for stage, t in rep.get("timings", {}).items():
            timings[stage] = timings.get(stage, 0.0) + t
        entries[str(f)] = {"report": fname, "input": rep.get("input", {}), "files": rep.get("files", {}),
                           "plan_summary": rep.get("plan", {}).get("summary", []),
                           "estimators": sorted(rep.get("estimators", {})), "timings": rep.get("timings", {}),
                           "counts": rep.get("counts", {}), "receivers": rep.get("receivers", {}),
                           "warnings": rep.get("warnings", [])}
    report = {
        "sequence": True,
        "frames": frames,
        "files": files,
        "timings": timings,
        "warnings": [f"frame {f}: {w}" for f in frames for w in per_frame[f][1].get("warnings", [])],
        "per_frame": entries,
    }
    _write_json(os.path.join(out_dir, SEQUENCE_REPORT), report)
    return report


def _write_json(path, data):
    """Write ``data`` as JSON to ``path`` through a temporary file renamed over it (a reader
    never sees half a file)."""
    write_text(path, json.dumps(data, indent=2, default=_json_default))


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
    return run_steps(bake_steps(scene, settings), progress)


def run_steps(steps, progress=None):
    """Drive the generator of :func:`bake_steps` to its :class:`BakeResult`, calling
    ``progress`` as :func:`bake` does."""
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
    resolutions = [(settings.resolution, settings.resolution) if settings.resolution else tuple(r.resolution)
                   for r in scene.receivers]
    check_budget(resolutions, settings, flux_textures=1 if settings.estimator in _FLUX_ESTIMATORS else 0,
                 triangles=scene.n_triangles)
    return _memory_guarded(_bake_gen(scene, settings))


def _memory_guarded(steps):
    """``steps`` with a ``MemoryError`` turned into a one-line :class:`~addon.bake.memory.BakeMemoryError`
    naming the step that ran out."""
    stage = "setting up the bake"
    try:
        while True:
            try:
                item = next(steps)
            except StopIteration as done:
                return done.value
            stage = re.sub(r" \(about .* left\)$", "", item[1] or stage)
            yield item
    except MemoryError:
        raise out_of_memory(stage) from None
    finally:
        steps.close()


def make_context(scene, settings):
    """The :class:`BakeContext` of a bake: threads, the BVH over every triangle, the scene
    extent and visibility offset, the receivers at the bake's resolution, the light samples."""
    if settings.threads:
        from ..solver.runtime.jit import set_num_threads

        set_num_threads(settings.threads)
    t0 = time.perf_counter()
    bvh = scene_bvh(scene.tri_p)
    extent = scene.extent()
    receivers = [with_resolution(r, settings.resolution) if settings.resolution else r for r in scene.receivers]
    lsamples = [sample_light(light, settings.light_samples, settings.seed) for light in scene.lights]
    ctx = BakeContext(scene, settings, bvh, VISIBILITY_OFFSET * extent, extent, receivers, lsamples,
                      warnings=list(scene.warnings) + scene_warnings(scene, receivers))
    ctx.timer.add("bvh", time.perf_counter() - t0)
    return ctx


REFIT_GROWTH = 1.5  # a refitted tree is kept while its boxes' area is at most this times its build's


def scene_bvh(tri_p):
    """The BVH of the triangles ``tri_p``: the last bake's tree refitted when it has as many
    triangles (an animation's next frame; :func:`~addon.solver.geometry.bvh.refit_bvh`, the same
    answers as a fresh build) and its boxes' area grew at most ``REFIT_GROWTH`` times, else a
    fresh build.  ``_BVH_KEPT`` holds the last tree and its build's box area."""
    kept = _BVH_KEPT.get("tree")
    if kept is not None and kept[0].order.shape[0] == tri_p.shape[0]:
        bvh = refit_bvh(kept[0], tri_p)
        if box_area(bvh) <= REFIT_GROWTH * kept[1]:
            _BVH_KEPT["refits"] = _BVH_KEPT.get("refits", 0) + 1
            return bvh
    bvh = build_bvh(tri_p)
    _BVH_KEPT["tree"] = (bvh, box_area(bvh))
    return bvh


_BVH_KEPT = {}


class Progress:
    """The share of a bake done and the time left, from the time each stage takes: planning
    (the probes), the estimators' preparation (forward images, photons), the texel rows
    (supersamples, direct light, exact paths), the texel areas (the flux estimators) and the
    padding.  A stage under way is extrapolated from its own count of work done (the time it
    took for its ``inner`` share); a stage not started from a guess of its seconds
    (:meth:`set_guesses`, from the work it holds), the texel stages' scaled by how the texel
    work so far compared with its guesses (:meth:`speed`).  The fraction is elapsed / (elapsed + left): it never goes
    back and reaches 1 only when the last stage ends."""

    STAGES = ("plan", "prepare", "rows", "areas", "pad")
    ONCE = ("plan", "prepare")

    def __init__(self):
        self.t0 = self.t_last = time.perf_counter()
        self.guess = {"plan": 0.5, "prepare": 0.0, "rows": 1.0, "areas": 0.0, "pad": 0.05}
        self.spent = dict.fromkeys(self.STAGES, 0.0)
        self.inner = dict.fromkeys(self.STAGES, 0.0)
        self.stage = "plan"
        self.last = 0.0
        self.left = None

    def set_guesses(self, **seconds):
        """Guessed seconds of stages not started yet."""
        for s, t in seconds.items():
            self.guess[s] = max(0.0, float(t))

    def speed(self):
        """Measured / guessed seconds over the texel work done so far (rows, areas, padding; 1
        before there is any): how much faster or slower this machine does it than guessed."""
        texel_stages = self.STAGES[len(self.ONCE):]
        guessed = sum(self.guess[s] * self.inner[s] for s in texel_stages)
        spent = sum(self.spent[s] for s in texel_stages if self.inner[s] > 0)
        return min(10.0, max(0.1, spent / guessed)) if guessed > 0.05 and spent > 0.05 else 1.0

    def fraction(self, stage, inner):
        """The share done at ``inner`` (0..1, that stage's own count of work) through ``stage``
        (never decreasing; stages may come again, e.g. per receiver)."""
        now = time.perf_counter()
        self.spent[self.stage] += now - self.t_last
        self.t_last, self.stage = now, stage
        self.inner[stage] = min(1.0, max(self.inner[stage], float(inner)))
        for s in self.ONCE:  # planning and preparation happen once: done when a later stage runs
            if self.STAGES.index(stage) > self.STAGES.index(s):
                self.inner[s] = 1.0
        speed = self.speed()
        left = 0.0
        for s in self.STAGES:
            done, spent = self.inner[s], self.spent[s]
            if done > 0.0 and spent > 0.0:
                left += spent * (1.0 - done) / done
            else:
                left += max(0.0, self.guess[s] * speed - spent)
        self.left = left
        elapsed = now - self.t0
        if stage == self.STAGES[-1] and self.inner[stage] >= 1.0:
            f = 1.0
        else:
            f = min(0.999, elapsed / (elapsed + left)) if elapsed + left > 0 else 0.0
        self.last = max(self.last, f)
        return self.last

    def eta(self):
        """Seconds left (None until 3 s and 2 % of the work have passed)."""
        if time.perf_counter() - self.t0 < 3.0 or self.last < 0.02 or self.left is None:
            return None
        return self.left

    def tell(self, stage, inner, message):
        """(fraction, message with the time left when known) for a step."""
        f = self.fraction(stage, inner)
        left = self.eta()
        return f, (f"{message} (about {format_seconds(left)} left)" if left is not None and f < 1.0 else message)


#: Guessed costs (seconds) for the stages not started yet, per unit of work.
GUESS_FORWARD_IMAGE = 2.0  # one forward image (chain x light sample)
GUESS_PHOTON = 1e-6
GUESS_SAMPLE = 1e-6  # one texel supersample: raster and estimators' bookkeeping
GUESS_DIRECT = 0.3e-6  # one supersample x light sample of direct light
GUESS_EXACT = 10e-6  # one supersample x chain of exact paths
GUESS_AREA_SAMPLE = 0.5e-6  # one supersample of the texel areas


def format_seconds(t):
    """``42 s``, ``3 min 5 s``, ``2 h 7 min``."""
    t = int(round(t))
    if t < 60:
        return f"{t} s"
    if t < 3600:
        return f"{t // 60} min {t % 60} s"
    return f"{t // 3600} h {(t % 3600) // 60} min"


_FLUX_ESTIMATORS = ("forward-flux", "photon")  # their receiver_flux needs the texel areas


def _prepare_steps(est, ctx):
    """How many steps ``est.prepare()`` yields (forward-flux: one per light sample and chain), or None."""
    if est.name == "forward-flux":
        return sum(int(ctx.lsamples[it.light].size) for it in est.items)
    return None


def _bake_gen(scene, settings):
    t_start = time.perf_counter()
    progress = Progress()
    ctx = make_context(scene, settings)
    timer = ctx.timer
    texels = sum(r.resolution[0] * r.resolution[1] for r in ctx.receivers)
    n_samples = texels * grid_side(settings.samples) ** 2
    n_light = sum(ls.size for ls in ctx.lsamples)
    if settings.caustics and settings.estimator == "forward-flux":  # until the plan says which chains
        progress.set_guesses(prepare=GUESS_FORWARD_IMAGE * len(candidate_chains(settings)) * n_light,
                             areas=texels * grid_side(max(settings.samples, AREA_SAMPLES)) ** 2 * GUESS_AREA_SAMPLE)
    progress.set_guesses(rows=n_samples * (GUESS_SAMPLE + (GUESS_DIRECT * n_light if settings.direct else 0.0)),
                         pad=texels * 0.05e-6)
    yield progress.tell("plan", 0.0, "planning")
    plan = yield from timer.timed_steps("plan", plan_steps(ctx), lambda f, message: progress.tell("plan", f, message))
    if settings.caustics and not plan.items:
        ctx.warnings.append("no casters: the scene has no reflecting or refracting surfaces (only the direct light is baked if asked)")
    by_name = {}
    for it in plan.baked_items():
        by_name.setdefault(it.estimator, []).append(it)
    estimators = [make_estimator(name, ctx, items) for name, items in by_name.items()]
    n_exact = sum(len(items) for name, items in by_name.items() if name in ("path-points", "path-seeded"))
    progress.set_guesses(
        prepare=sum(GUESS_FORWARD_IMAGE * (_prepare_steps(e, ctx) or 0) for e in estimators)
        + (GUESS_PHOTON * settings.photons if "photon" in by_name else 0.0),
        rows=n_samples * (GUESS_SAMPLE + GUESS_EXACT * n_exact
                          + (GUESS_DIRECT * n_light if settings.direct else 0.0)),
        areas=texels * grid_side(max(settings.samples, AREA_SAMPLES)) ** 2 * GUESS_AREA_SAMPLE
        if set(by_name) & set(_FLUX_ESTIMATORS) else 0.0,
        pad=texels * 0.05e-6)
    n_est = max(1, len(estimators))
    for e, est in enumerate(estimators):
        expected, k = _prepare_steps(est, ctx), 0
        for f, message in est.prepare():
            if f is None:
                f = k / expected if expected else 0.0
            else:
                f = f / 0.9 if est.name == "photon" else f
            k += 1
            yield progress.tell("prepare", (e + min(1.0, f)) / n_est, message)
    images, coverage, raw, rec_report = {}, {}, {}, {}
    total_rows = sum(r.resolution[1] for r in ctx.receivers)
    rows_done = area_rows = 0
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
                yield progress.tell("rows", rows_done / max(1, total_rows), f"{rec.name}: rows {H}/{H}")
        for j0, j1 in (bands(rec, settings.samples, settings.band_samples) if cover is not kept else ()):
            t0 = time.perf_counter()
            if counts_only:  # no estimator reads the samples: their texels only
                texel, _tri = raster_texels(rec, settings.samples, settings.seed, settings.jitter, rows=(j0, j1))
                band = None
            else:
                band = rasterise(scene, rec, settings.samples, settings.seed, settings.jitter, rows=(j0, j1))
                texel = band.texel
            cover += np.bincount(texel, minlength=W * H)
            timer.add("raster", time.perf_counter() - t0)
            if band is not None and band.size:
                if settings.direct:
                    for ls in ctx.lsamples:
                        direct_light(ctx, ls, band, sums)
                for est in estimators:
                    for _, message in est.accumulate(rec_index, band, sums):
                        yield progress.tell("rows", (rows_done + 0.5 * (j1 - j0)) / max(1, total_rows), message)
            rows_done += j1 - j0
            yield progress.tell("rows", rows_done / max(1, total_rows), f"{rec.name}: rows {j1}/{H}")
        if key is not None:
            _keep(_COVER_CACHE, key, cover)
        flux = area = None
        for est in estimators:
            f = yield from est.receiver_flux(rec_index)
            if f is not None:
                flux = f if flux is None else flux + f
        if flux is not None:
            t0 = time.perf_counter()
            key = _receiver_key(rec, settings.samples, settings.band_samples, scene.tri_p[rec.tri_index])
            area = _kept(_AREA_CACHE, key)  # texel areas of a receiver that did not move: kept (exact)
            if area is None:
                area = np.zeros(W * H)
                for j1 in _texel_area_steps(scene, rec, settings.samples, settings.band_samples, area):
                    timer.add("texel_area", time.perf_counter() - t0)
                    yield progress.tell("areas", (area_rows + j1) / max(1, total_rows), f"{rec.name}: texel areas, rows {j1}/{H}")
                    t0 = time.perf_counter()
                area = _keep(_AREA_CACHE, key, area)
            timer.add("texel_area", time.perf_counter() - t0)
        t0 = time.perf_counter()
        img, stats = texel_irradiance(sums, cover, flux, area)
        covered = cover > 0
        timer.add("texels", time.perf_counter() - t0)
        area_rows += H
        t0 = time.perf_counter()
        img = img.reshape(H, W, 3)
        cov2 = covered.reshape(H, W)
        padded, _ = pad(img, cov2, settings.margin)
        timer.add("pad", time.perf_counter() - t0)
        yield progress.tell("pad", (rec_index + 1) / len(ctx.receivers), f"{rec.name}: padded")
        images[rec.name] = padded.astype(np.float32)
        coverage[rec.name] = cov2
        raw[rec.name] = img
        rec_report[rec.name] = {"resolution": [W, H], "uv_map": rec.uv_map, "texels_covered": stats["texels_covered"],
                                "texels_touched": stats["texels_touched"], "caustic_power": ctx.ledger.total(receiver=rec_index),
                                "max_irradiance": stats["max_irradiance"],
                                "mean_irradiance_covered": stats["mean_irradiance_covered"]}
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
    value.flags.writeable = False
    return keep_recent(cache, key, value, AREA_CACHE_SIZE)

def _texel_areas(scene, rec, samples, band_samples):
    W, H = rec.resolution
    area = np.zeros(W * H)
    for _ in _texel_area_steps(scene, rec, samples, band_samples, area):
        pass
    return area


def _texel_area_steps(scene, rec, samples, band_samples, area):
    """:func:`texel_areas` into ``area`` band by band, yielding the rows done after each band."""
    W, H = rec.resolution
    S = grid_side(max(int(samples), AREA_SAMPLES)) ** 2
    ratio = world_per_uv_area(scene, rec)
    for j0, j1 in bands(rec, S, band_samples):
        texel, tri = raster_texels(rec, S, 0, False, rows=(j0, j1))
        if texel.size:
            area += np.bincount(texel, weights=ratio[tri], minlength=W * H) / (W * H * S)
        yield j1


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
    bvh, eps, extent, timer = ctx.bvh, ctx.eps, ctx.extent, ctx.timer
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
