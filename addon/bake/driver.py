"""The bake: caustic irradiance per receiver texel, on the plain-data scene model (no bpy).

For every receiver, band of texel rows, light sample, chain and candidate tuple
(caster triangle(s), texel supersample): solve the specular paths with
``addon.solver.solve_tuples``, weigh each by the light's intensity and emission profile,
Fresnel x tint, and the cosine at the receiver (``path_irradiance`` gives the generalised
geometry term), test both segments for visibility against a BVH over every scene triangle,
and add it to its texel.  A texel's value is the mean over its covered supersamples
(irradiance in W/m², linear RGB); uncovered texels are then filled over UV seams
(:func:`addon.bake.raster.pad`).

Conventions (see also DESIGN.md):
- Only light arriving on the front of the receiver (geometric normal turned to the shading
  normal's side) counts; the cosine is max(0, n_shading . (-w)) as in Cycles' diffuse BSDF.
- R on a 'reflect' caster: tinted mirror (reflectance "mirror" x tint); R on a 'both' caster:
  dielectric Fresnel F(IOR) x tint; T ('refract' or 'both'): (1 - F) x tint.
- Sun: the solver takes points, so the sun is a point at distance D = ``sun_distance`` x scene
  size behind each caster triangle, with intensity S |x1 - x0|² per path.  The error is the
  beam's divergence from that point: relative irradiance error about 2 L / D (L the
  vertex-receiver distance), 2e-5 with the default D = 1e5 x scene size.
- Streaming: tuples are produced and solved in batches of at most ``batch_tuples``; samples are
  rasterised in bands of at most ``band_samples``; memory stays bounded.
- Deterministic for a seed: every parallel kernel writes disjoint outputs and the sums run
  in a fixed order.
"""

import json
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..solver import path_irradiance, solve_tuples
from ..solver.api import CHAIN_LENGTH
from ..solver.bvh import build_bvh, segments_occluded
from .cull import TupleCull, one_bounce_emitters, two_bounce_emitters, vertex_cap
from .lights import emission_factor, sample_light
from .raster import bands, grid_side, pad, rasterise
from .scene import ROLE_BOTH, ROLE_REFLECT, ROLE_REFRACT, SceneError

VISIBILITY_OFFSET = 1e-6  # x scene size: shadow-ray offset at both ends of a segment


METHODS = ("spoly", "newton", "sms", "curve", "photon")
"""Bake methods.  "spoly": Specular Polynomials (every path of each tuple, the default);
"newton": MNEE / Newton from Path Cuts' deterministic seeds; "sms": Specular Manifold Sampling
(``sms_seeds`` random seeds per tuple); "curve": the dimension-reduction MNEE curve walk
(``addon.solver.curve_walk``, imported when first used); "photon": forward light tracing of
``photons`` photons into a texel histogram (``addon.bake.photons``), no tuple loop."""

METHOD_CHAINS = {
    "spoly": ("R", "T", "RR", "RT", "TR", "TT"),
    "newton": ("R", "T"),
    "sms": ("R", "T"),
    "curve": ("T",),
    "photon": ("R", "T", "RR", "RT", "TR", "TT"),
}
"""The chains each method can bake; any other planned chain is skipped with a status."""

TWO_BOUNCE_MODES = ("flux", "seeded", "exact")
"""How method "spoly" bakes two-bounce chains (see BakeSettings.two_bounce and addon.bake.image)."""


def check_method(settings):
    """Raise ValueError for an unknown method or an out-of-range method knob."""
    if settings.method not in METHODS:
        raise ValueError(f"unknown bake method {settings.method!r}; expected one of {', '.join(METHODS)}")
    if not 1 <= int(settings.sms_seeds) <= 4096:
        raise ValueError(f"sms_seeds must be in [1, 4096], got {settings.sms_seeds}")
    if int(settings.photons) < 1:
        raise ValueError(f"photons must be at least 1, got {settings.photons}")
    if settings.two_bounce not in TWO_BOUNCE_MODES:
        raise ValueError(f"two_bounce must be one of {', '.join(TWO_BOUNCE_MODES)}, got {settings.two_bounce!r}")
    if settings.one_bounce not in ("points", "flux"):
        raise ValueError(f"one_bounce must be 'points' or 'flux', got {settings.one_bounce!r}")
    if not 0 <= int(settings.image_depth) <= 10:
        raise ValueError(f"image_depth must be in [0, 10], got {settings.image_depth}")
    if settings.pieces and not 1 <= int(settings.pieces) <= 1024:
        raise ValueError(f"pieces must be 0 (the solver's default) or in [1, 1024], got {settings.pieces}")


def method_solver(settings):
    """(solve, error) for the per-tuple methods: ``solve(chain, x_start, x_end, P, N, eta) ->
    (tuple_index, uv)``, or None for the default path (``solve_tuples``, bit-identical to the
    bakes before methods existed); ``error`` a reason when the method cannot be loaded
    ("curve" before addon/solver/curve_walk.py exists)."""
    m = settings.method
    if m == "spoly" and not settings.pieces:
        return None, None
    if m == "spoly":
        from ..solver.api import SpecularPolynomialSolver

        solver, kw = SpecularPolynomialSolver(), {"pieces": int(settings.pieces), "device": settings.device}
    elif m == "newton":
        from ..solver.baselines import NewtonSolver

        solver, kw = NewtonSolver(), {}
    elif m == "sms":
        from ..solver.baselines import SMSSolver

        solver, kw = SMSSolver(int(settings.sms_seeds), int(settings.seed)), {}
    elif m == "curve":
        try:
            from ..solver.curve_walk import CurveWalkSolver

            solver, kw = CurveWalkSolver(), {}
        except Exception as ex:  # not there yet, or broken: the bake says so and skips its chains
            return None, f"method 'curve' is not available ({type(ex).__name__}: {ex})"
    else:
        return None, None

    def solve(chain, x_start, x_end, P, N, eta):
        kwargs = dict(kw)
        if "pieces" in kwargs and len(chain) == 1:
            kwargs.pop("pieces")
        res = solver.solve(chain, x_start, x_end, P, N, eta, **kwargs)
        return res.tuple_index, res.uv

    return solve, None


class BakeCancelled(Exception):
    """Raised when the progress callback asks to stop."""


@dataclass
class BakeSettings:
    resolution: int = 0  # texels per side for every receiver; 0: each receiver's own
    samples: int = 4  # supersamples per texel (an s x s stratified grid, rounded up to a square)
    bounces: int = 1  # 1: R, T; 2: also RR, RT, TR, TT (when the solver supports them)
    seed: int = 0
    jitter: bool = True  # jittered (True) or centred (False) supersamples
    light_samples: int = 1  # > 1: sample light radius / area / sun angle (soft caustics)
    margin: int = 16  # texels of padding over UV seams
    cull: object = True  # True / "cone": cone cull; "bounds": Bernstein position bounds for R/T from point-like lights
    #                       (cone elsewhere); False: side tests only
    gamma: float = math.inf  # bounds cull: solve a tuple with P = min(gamma Ẽ, 1) (Ẽ in W/m²), weight 1/P; inf: all
    batch_tuples: int = 1 << 18
    band_samples: int = 1 << 20
    sun_distance: float = 1e5  # x scene size
    caustics: bool = True  # the specular chains
    direct: bool = False  # also the direct light (chain of length 0; for the units test)
    chains: tuple = ()  # restrict to these chains (empty: all planned)
    threads: int = 0  # 0: Numba's default
    device: str = "numba"  # solver device: "numba", "opencl" or "opencl:N" (every chain; see solver.api)
    method: str = "spoly"  # see METHODS: the per-tuple solver, or "photon" (light tracing instead of the tuple loop)
    sms_seeds: int = 16  # method "sms": random Newton seeds per tuple
    photons: int = 1_000_000  # method "photon": photons traced (over all lights and light samples)
    pieces: int = 0  # method "spoly", two bounces: pieces of the resultant's sign scan (0: the solver's default)
    two_bounce: str = "flux"  # method "spoly", two-bounce chains (addon.bake.image): "flux" (forward-image sub-triangles,
    #                           their flux spread over their images: texel averages), "seeded" (exact paths at the samples
    #                           by Newton from forward-image seeds) or "exact" (cone cull + two-bounce Specular Polynomials)
    image_depth: int = 6  # "flux" / "seeded": subdivision levels of the caster triangles (4 x 4 first)
    one_bounce: str = "flux"  # method "spoly", R and T: "flux" (default) or "points" (every path at every supersample, exact)
    #                             (forward-image sub-triangles as two_bounce="flux": texel averages)

    def as_dict(self):
        d = asdict(self)
        d["chains"] = list(self.chains)
        return d


@dataclass
class BakeResult:
    images: dict  # receiver name -> (H, W, 3) float32 irradiance W/m², row 0 = bottom (v = 0), padded
    coverage: dict  # receiver name -> (H, W) bool, texels with samples on the receiver
    raw: dict  # receiver name -> (H, W, 3) float64 before padding
    report: dict = field(default_factory=dict)

    def write(self, out_dir):
        """Write ``<receiver>.exr`` per receiver and ``report.json`` into ``out_dir``."""
        import os

        from .exr import write_exr

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


_SUPPORT = {}


def chain_supported(chain):
    """Whether addon.solver solves ``chain`` and gives its irradiance (probed once, with an
    empty batch: "not supported yet" is a ValueError; a solver module that fails to import
    counts as unsupported too, so one-bounce bakes keep working)."""
    if chain not in _SUPPORT:
        k = CHAIN_LENGTH[chain]
        z3 = np.zeros((0, 3))
        zp = np.zeros((0, k, 3, 3))
        try:
            ti, uv = solve_tuples(chain, z3, z3, zp, zp, 1.5)
            path_irradiance(chain, z3, z3, zp, zp, 1.5, ti, uv)
            _SUPPORT[chain] = True
        except (ValueError, NotImplementedError, ImportError):
            _SUPPORT[chain] = False
    return _SUPPORT[chain]


CHAIN_ROLES = {"R": (ROLE_REFLECT, ROLE_BOTH), "T": (ROLE_REFRACT, ROLE_BOTH)}


def plan_chains(scene, bounces=1, only=(), method="spoly", method_error=None):
    """The chains to bake: [{"chain", "vertices": [caster index arrays per vertex], "status"}].

    R for reflect and both (glass) casters, T for refract and both; with bounces = 2 also
    RR, RT, TR, TT over the same caster sets.  A single refraction (T) through a *closed*
    object (a solid: glass sphere, slab) ends inside it, so T leaves out closed objects (a
    receiver inside glass is not modelled); open refracting surfaces (water) keep it.  A chain
    the solver does not support yet is listed with status "skipped: ..." (and a warning), and
    so is a chain the bake ``method`` does not solve (:data:`METHOD_CHAINS`), or every chain
    when the method could not be loaded (``method_error``, the reason).
    """
    chains = ["R", "T"] + (["RR", "RT", "TR", "TT"] if bounces >= 2 else [])
    closed = scene.closed_objects() if np.any(np.isin(scene.tri_role, CHAIN_ROLES["T"])) else set()
    open_tri = ~np.isin(scene.tri_object, list(closed))
    plan = []
    for chain in chains:
        if only and chain not in only:
            continue
        verts = [np.flatnonzero(np.isin(scene.tri_role, CHAIN_ROLES[c])) for c in chain]
        if chain == "T":
            verts = [verts[0][open_tri[verts[0]]]]
        if any(v.size == 0 for v in verts):
            continue
        status = "baked"
        if method_error:
            status = f"skipped: {method_error}"
        elif chain not in METHOD_CHAINS.get(method, ()):
            status = f"skipped: the {method} method does not solve {chain} (it solves {', '.join(METHOD_CHAINS[method])})"
        elif method != "photon" and not chain_supported(chain):
            status = "skipped: not supported by the solver yet"
        plan.append({"chain": chain, "vertices": verts, "status": status})
    return plan


class _Timer:
    def __init__(self):
        self.t = {}

    def add(self, key, dt):
        self.t[key] = self.t.get(key, 0.0) + dt


def bake(scene, settings=None, progress=None):
    """Bake every receiver of ``scene``; returns a :class:`BakeResult`.

    ``progress(fraction, message)`` is called between batches (``fraction`` is None between
    tuple batches); returning False cancels (:class:`BakeCancelled`).  A plain loop over
    :func:`bake_steps`.
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
    :class:`SceneError`), then returns a generator that does the bake in bounded chunks (one
    band of texel rows, or one batch of at most ``settings.batch_tuples`` tuples), yielding
    ``(fraction, message)`` between chunks (``fraction`` in [0, 1], or None between tuple
    batches) and returning the :class:`BakeResult` (``StopIteration.value``).

    Closing the generator (``.close()``) abandons the bake; nothing outside it was changed.
    The Blender operator drives it from a timer; :func:`bake` drives it in a loop.
    """
    settings = settings or BakeSettings()
    if settings.bounces not in (1, 2):
        raise SceneError("bounces must be 1 or 2")
    if settings.samples < 1:
        raise SceneError("samples must be at least 1")
    if settings.resolution < 0 or settings.resolution > 16384:
        raise SceneError("resolution must be between 1 and 16384")
    check_method(settings)
    scene.validate()
    if settings.method == "photon":
        from .photons import photon_bake_gen

        return photon_bake_gen(scene, settings)
    return _bake_gen(scene, settings)


def bake_setup(scene, settings, method_error=None):
    """What every bake generator starts with: threads, timer, the scene's warnings, the BVH over
    all triangles, the scene extent and visibility offset, and the chain plan (its skipped
    chains added to the warnings).  Returns (timer, t_start, warnings, bvh, extent, eps, plan)."""
    if settings.threads:
        from ..solver.jit import set_num_threads

        set_num_threads(settings.threads)
    timer = _Timer()
    t_start = time.perf_counter()
    warnings = list(scene.warnings)
    t0 = time.perf_counter()
    bvh = build_bvh(scene.tri_p)
    timer.add("bvh", time.perf_counter() - t0)
    extent = scene.extent()
    eps = VISIBILITY_OFFSET * extent
    plan = plan_chains(scene, settings.bounces, settings.chains, settings.method, method_error) if settings.caustics else []
    for item in plan:
        if item["status"] != "baked":
            warnings.append(f"chain {item['chain']} {item['status']}")
    if settings.caustics and not plan:
        warnings.append("no casters: the scene has no reflecting or refracting surfaces (only the direct light is baked if asked)")
    return timer, t_start, warnings, bvh, extent, eps, plan


def _bake_gen(scene, settings):
    solve, method_error = method_solver(settings)
    timer, t_start, warnings, bvh, extent, eps, plan = bake_setup(scene, settings, method_error)
    yield 0.0, "preparing"
    lsamples = [sample_light(light, settings.light_samples, settings.seed) for light in scene.lights]
    counts = {"tuples_naive": 0, "tuples_tile_cull": 0, "tuples": 0, "paths": 0, "paths_front": 0, "paths_lit": 0, "paths_visible": 0}
    chain_counts = {item["chain"]: {"tuples": 0, "paths": 0, "paths_visible": 0} for item in plan}
    images, coverage, raw, rec_report = {}, {}, {}, {}
    S = grid_side(settings.samples) ** 2
    emitter_cache = {}  # (light, light sample, chain) -> emitters, shared by every band and receiver
    image_reports, image_counts = [], {"seeds": 0, "newton": 0, "hops": 0, "converged": 0, "paths": 0}
    total_rows = sum((settings.resolution or r.resolution[1]) for r in scene.receivers)
    rows_done = 0
    receivers = [_with_resolution(r, settings.resolution) if settings.resolution else r for r in scene.receivers]
    for rec_index, rec in enumerate(receivers):
        W, H = rec.resolution
        sums = np.zeros((W * H, 3))
        cover = np.zeros(W * H, dtype=np.int64)
        rec_paths = 0
        for j0, j1 in bands(rec, settings.samples, settings.band_samples):
            t0 = time.perf_counter()
            band = rasterise(scene, rec, settings.samples, settings.seed, settings.jitter, rows=(j0, j1))
            cover += np.bincount(band.texel, minlength=W * H)
            timer.add("raster", time.perf_counter() - t0)
            if band.size == 0:
                rows_done += j1 - j0
                continue
            if settings.direct:
                for ls in lsamples:
                    _direct(scene, bvh, eps, extent, ls, band, sums, timer)
            for li, ls in enumerate(lsamples):
                for m in range(ls.size):
                    for item in plan:
                        if item["status"] != "baked":
                            continue
                        key = (li, m, item["chain"])
                        image = _uses_image(settings, item["chain"])
                        if image == "flux":
                            continue  # whole textures at once, after the bands (_flux_pass)
                        if image:
                            state = _cached_image_state(scene, bvh, eps, extent, settings, item, li, ls, m, receivers,
                                                        emitter_cache, image_reports, timer)
                            st = _image_pass(scene, bvh, eps, extent, item, ls, m, band, rec_index, sums, timer, state,
                                             image_counts)
                        else:
                            if key not in emitter_cache:
                                t0 = time.perf_counter()
                                emitter_cache[key] = _emitters(scene, extent, settings, item, ls, m)
                                timer.add("cull", time.perf_counter() - t0)
                            st = yield from _chain_pass(scene, bvh, eps, extent, settings, item, ls, m, band, W, sums,
                                                        timer, emitter_cache[key], solve, rec=rec)
                        for k in st:
                            counts[k] += st[k]
                        cc = chain_counts[item["chain"]]
                        cc["tuples"] += st["tuples"]
                        cc["paths"] += st["paths"]
                        cc["paths_visible"] += st["paths_visible"]
                        rec_paths += st["paths_visible"]
            rows_done += j1 - j0
            yield rows_done / max(1, total_rows), f"{rec.name}: rows {j1}/{H}"
        covered = cover > 0
        img = np.zeros((W * H, 3))
        img[covered] = sums[covered] / cover[covered, None]
        flux = yield from _flux_pass(scene, bvh, eps, extent, settings, plan, lsamples, receivers, rec_index, emitter_cache,
                          image_reports, timer)
        if flux is not None:
            t0 = time.perf_counter()
            from .photons import texel_areas

            area = texel_areas(scene, rec, settings.samples, settings.band_samples)
            ok = covered & (area > 0)
            img[ok] += flux[ok] / area[ok, None]
            timer.add("flux", time.perf_counter() - t0)
            touched_flux = int(np.count_nonzero(np.any(flux[ok] > 0, axis=1)))
            image_counts["flux_texels"] = image_counts.get("flux_texels", 0) + touched_flux
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
            "paths": rec_paths, "max_irradiance": float(img.max()) if img.size else 0.0,
            "mean_irradiance_covered": float(img.reshape(-1, 3)[covered].mean()) if covered.any() else 0.0,
        }
    for item in plan:
        if item["status"] != "baked":
            continue
        n_cast = int(np.prod([v.size for v in item["vertices"]]))
        n_samples = sum(S * (settings.resolution or r.resolution[0]) * (settings.resolution or r.resolution[1]) for r in scene.receivers)
        counts["tuples_naive"] += n_cast * n_samples * sum(ls.size for ls in lsamples)
    total = time.perf_counter() - t_start
    report = {
        "method": settings.method,
        "settings": settings.as_dict(),
        "scene": {
            "frame": scene.frame, "triangles": int(scene.n_triangles), "casters": int(scene.casters().size),
            "objects": len(scene.objects), "receivers": [r.name for r in scene.receivers],
            "lights": [light.as_dict() for light in scene.lights], "extent": extent,
        },
        "chains": [{"chain": it["chain"], "casters_per_vertex": [int(v.size) for v in it["vertices"]], "status": it["status"],
                    **chain_counts.get(it["chain"], {})} for it in plan],
        "timings": {**timer.t, "bake_total": total},
        "counts": {**counts, "texels": int(sum(r["resolution"][0] * r["resolution"][1] for r in rec_report.values())),
                   "texels_covered": int(sum(r["texels_covered"] for r in rec_report.values())),
                   "texels_touched": int(sum(r["texels_touched"] for r in rec_report.values()))},
        "receivers": rec_report,
        "warnings": warnings,
    }
    if image_reports:
        dropped = sum(r["dropped"] for r in image_reports)
        report["two_bounce_image"] = {"passes": image_reports, "counts": image_counts, "dropped_sub_triangles": dropped}
        if dropped:
            warnings.append(f"two-bounce image seeding: {dropped:,} sub-triangles partly lost (rays missing the receivers "
                            "or total internal reflection at the deepest level) were not seeded")
    return BakeResult(images, coverage, raw, report)


def _uses_image(settings, chain):
    """"flux" or "seeded" when the chain goes through forward-image sub-triangles (addon.bake.image), else None."""
    if settings.method != "spoly":
        return None
    if len(chain) == 2 and settings.two_bounce in ("flux", "seeded"):
        return settings.two_bounce
    if len(chain) == 1 and settings.one_bounce == "flux":
        return "flux"
    return None


def _image_state(scene, bvh, eps, extent, settings, item, ls, m, receivers):
    """The refined sub-triangles (addon.bake.image.prepare) of one light sample and chain, or None."""
    from .image import prepare

    cast1 = item["vertices"][0]
    x0_all = _light_points(ls, m, scene.tri_p[cast1], extent, settings)
    keep = _emitting(ls, m, x0_all, scene.tri_p[cast1])
    if not keep.any():
        return None
    second = item["vertices"][1] if len(item["vertices"]) > 1 else np.zeros(0, dtype=np.int64)
    return prepare(scene, bvh, eps, item["chain"], cast1[keep], x0_all[keep], second, receivers,
                   max_depth=int(settings.image_depth), mode=_uses_image(settings, item["chain"]), parallel=ls.kind == "sun")


def _cached_image_state(scene, bvh, eps, extent, settings, item, li, ls, m, receivers, emitter_cache, image_reports, timer):
    """:func:`_image_state` once per (light, light sample, chain), kept in ``emitter_cache`` for
    every band and receiver; its report joins ``image_reports``."""
    key = (li, m, item["chain"])
    if key not in emitter_cache:
        t0 = time.perf_counter()
        emitter_cache[key] = _image_state(scene, bvh, eps, extent, settings, item, ls, m, receivers)
        if emitter_cache[key] is not None:
            image_reports.append({"light": li, "light_sample": m, "chain": item["chain"], **emitter_cache[key].report})
        timer.add("image", time.perf_counter() - t0)
    return emitter_cache[key]


def _flux_pass(scene, bvh, eps, extent, settings, plan, lsamples, receivers, rec_index, emitter_cache, image_reports, timer):
    """Flux (W per texel, (H W, 3)) of every "flux" two-bounce chain onto receiver ``rec_index``,
    or None when there is none (addon.bake.image.flux_textures; states cached per light sample
    and chain, shared by every receiver).  A generator: yields ``(None, message)`` before each
    light sample and chain (a chance to cancel), returns the flux."""
    from .image import flux_textures

    total = None
    for li, ls in enumerate(lsamples):
        for m in range(ls.size):
            for item in plan:
                if item["status"] != "baked" or _uses_image(settings, item["chain"]) != "flux":
                    continue
                yield None, f"{item['chain']}: forward images (light {li + 1}, sample {m + 1})"
                state = _cached_image_state(scene, bvh, eps, extent, settings, item, li, ls, m, receivers, emitter_cache,
                                            image_reports, timer)
                if state is None:
                    continue
                t0 = time.perf_counter()
                fkey = ("flux", li, m, item["chain"])
                if fkey not in emitter_cache:
                    emitter_cache[fkey] = flux_textures(state, scene, bvh, eps, extent, ls, m, receivers)
                f = emitter_cache[fkey][rec_index]
                total = f.copy() if total is None else total + f
                timer.add("flux", time.perf_counter() - t0)
    return total


def _image_pass(scene, bvh, eps, extent, item, ls, m, band, rec_index, sums, timer, state, image_counts):
    """One two-bounce chain, one light sample, one band by forward-image seeding: seeds, exact
    Newton, merge, then the same weighting / visibility / accumulation as the tuple solver."""
    from .image import band_paths

    chain = item["chain"]
    st = {"tuples_tile_cull": 0, "tuples": 0, "paths": 0, "paths_front": 0, "paths_lit": 0, "paths_visible": 0}
    if state is None:
        return st
    t0 = time.perf_counter()
    tri, x_start, s, uv, c = band_paths(state, rec_index, band)
    timer.add("solve", time.perf_counter() - t0)
    for key in c:
        image_counts[key] = image_counts.get(key, 0) + c[key]
    st["tuples_tile_cull"] = st["tuples"] = c["seeds"]
    st["paths"] = c["paths"]
    n = tri.shape[0]
    if n:
        ti = np.arange(n, dtype=np.int64)
        x_end = band.position[s]
        P = scene.tri_p[tri]
        N = scene.tri_n[tri]
        eta = scene.tri_ior[tri[:, 0]]
        _accumulate(scene, bvh, extent, eps, chain, ls, m, band, sums, timer, tri, x_start, x_end, P, N, eta, ti, uv, s, None, st)
    return st


def _with_resolution(rec, res):
    from .scene import Receiver

    return Receiver(rec.name, rec.object_index, rec.tri_index, rec.uv, (res, res), rec.uv_map)


def _light_points(ls, m, tri_p, extent, settings):
    """x0 per caster triangle for light sample m: the point, or a far point behind each triangle (sun)."""
    if ls.kind == "sun":
        c = tri_p.mean(axis=1)
        return c - settings.sun_distance * extent * ls.direction[m]
    return np.broadcast_to(ls.position[m], (tri_p.shape[0], 3)).copy()


def _emitting(ls, m, x0, tri_p):
    """Mask of caster triangles that the light sample can reach (spot cone, Lambertian lobe)."""
    keep = np.ones(tri_p.shape[0], dtype=bool)
    if ls.kind == "sun":
        return keep
    a, alpha = vertex_cap(x0, tri_p)
    lobe = ls.lobe[m]
    if np.any(lobe != 0):
        ang = np.arccos(np.clip(a @ lobe, -1, 1))
        keep &= ang - alpha < 0.5 * math.pi
    if np.any(ls.spot_axis != 0):
        ang = np.arccos(np.clip(a @ ls.spot_axis, -1, 1))
        keep &= ang - alpha < math.acos(max(-1.0, min(1.0, ls.spot_cos))) + 1e-9
    return keep


def _emitters(scene, extent, settings, item, ls, m):
    """(emitters, global caster ids per emitter (n, k), light point per emitter (n, 3)) or None."""
    chain = item["chain"]
    cast1 = item["vertices"][0]
    x0_all = _light_points(ls, m, scene.tri_p[cast1], extent, settings)
    keep = _emitting(ls, m, x0_all, scene.tri_p[cast1])
    cast1 = cast1[keep]
    x0_all = x0_all[keep]
    if cast1.size == 0:
        return None
    if len(chain) == 1:
        em = one_bounce_emitters(chain, x0_all, scene.tri_p[cast1], scene.tri_n[cast1], scene.tri_ior[cast1])
        tri_of = cast1[em.index]
    else:
        cast2 = item["vertices"][1]
        em = two_bounce_emitters(chain, x0_all, scene.tri_p[cast1], scene.tri_n[cast1], scene.tri_ior[cast1],
                                 scene.tri_p[cast2], scene.tri_n[cast2], scene.tri_ior[cast2], ids1=cast1, ids2=cast2)
        tri_of = np.column_stack([cast1[em.index[:, 0]], cast2[em.index[:, 1]]]) if em.size else np.zeros((0, 2), dtype=np.int64)
    if not settings.cull:
        em.without_cone()
    return em, tri_of, x0_all[em.index[:, 0]]


def _chain_pass(scene, bvh, eps, extent, settings, item, ls, m, band, W, sums, timer, emitters, solve=None, rec=None):
    """One chain, one light sample, one band: cull, solve in batches, weigh, test, accumulate.
    ``solve``: the method's solver (:func:`method_solver`; None: ``solve_tuples``).
    A generator: yields ``(None, message)`` after every batch, returns the counts."""
    chain = item["chain"]
    k = len(chain)
    st = {"tuples_tile_cull": 0, "tuples": 0, "paths": 0, "paths_front": 0, "paths_lit": 0, "paths_visible": 0}
    if emitters is None or emitters[0].size == 0:
        return st
    em, tri_of, x0_of = emitters
    t0 = time.perf_counter()
    cull = _bounds_cull(scene, settings, chain, ls, m, em, tri_of, x0_of, band, W, rec, emitters)
    if cull is None:
        cull = TupleCull(em, band.position, band.geo_normal, band.texel, W)
    st["tuples_tile_cull"] = cull.upper_bound
    timer.add("cull", time.perf_counter() - t0)
    t0 = time.perf_counter()
    for batch in cull.batches(settings.batch_tuples):
        e, s = batch[0], batch[1]
        inv_p = batch[2] if len(batch) > 2 else None  # bounds cull with gamma < inf: 1/P per tuple (eq 24)
        timer.add("cull", time.perf_counter() - t0)
        st["tuples"] += e.size
        t0 = time.perf_counter()
        tri = tri_of[e]  # (n, k) global triangle ids in path order
        x_start = x0_of[e]
        x_end = band.position[s]
        P = scene.tri_p[tri]
        N = scene.tri_n[tri]
        eta = scene.tri_ior[tri[:, 0]]
        # The device only when it is not the default (solve_tuples' signature stays optional).
        if solve is None:
            ti, uv = solve_tuples(chain, x_start, x_end, P, N, eta, **({} if settings.device == "numba" else {"device": settings.device}))
        else:
            ti, uv = solve(chain, x_start, x_end, P, N, eta)
        timer.add("solve", time.perf_counter() - t0)
        st["paths"] += ti.size
        _accumulate(scene, bvh, extent, eps, chain, ls, m, band, sums, timer, tri, x_start, x_end, P, N, eta, ti, uv, s, inv_p, st)
        yield None, f"{chain}: {st['tuples']:,} tuples"
        t0 = time.perf_counter()
    return st


def _accumulate(scene, bvh, extent, eps, chain, ls, m, band, sums, timer, tri, x_start, x_end, P, N, eta, ti, uv, s, inv_p, st):
    """Weigh solved paths (row r: tuple ti[r] with barycentrics uv[r]), test their visibility
    and add their irradiance to their samples' texels; counts into ``st``."""
    k = len(chain)
    if ti.size:
        t0 = time.perf_counter()
        weight, front, rgb, verts = _path_values(scene, chain, ls, m, x_start, x_end, P, N, eta, tri, ti, uv, band, s)
        timer.add("irradiance", time.perf_counter() - t0)
        st["paths_front"] += int(front.sum())
        idx = np.flatnonzero(front & (weight > 0))
        st["paths_lit"] += idx.size
        if idx.size:
            t0 = time.perf_counter()
            tt = ti[idx]
            first = x_start[tt] if ls.kind != "sun" else verts[0][idx] - 2.0 * extent * ls.direction[m]
            points = [first] + [v[idx] for v in verts] + [x_end[tt]]
            blocked = np.zeros(idx.size, dtype=bool)
            for j in range(k + 1):
                ig = np.column_stack([tri[tt, j - 1] if j > 0 else np.full(idx.size, -1),
                                      tri[tt, j] if j < k else band.tri[s[tt]]])
                if j == 0:
                    ig = ig[:, ::-1].copy()
                live = np.flatnonzero(~blocked)
                blocked[live] = segments_occluded(bvh, points[j][live], points[j + 1][live], ig[live], eps)
            vis = idx[~blocked]
            timer.add("visibility", time.perf_counter() - t0)
            st["paths_visible"] += vis.size
            t0 = time.perf_counter()
            tex = band.texel[s[ti[vis]]]
            w = weight[vis][:, None] * rgb[vis]
            if inv_p is not None:
                w *= inv_p[ti[vis]][:, None]
            for c in range(3):
                sums[:, c] += np.bincount(tex, weights=w[:, c], minlength=sums.shape[0])
            timer.add("accumulate", time.perf_counter() - t0)


def _bounds_cull(scene, settings, chain, ls, m, em, tri_of, x0_of, band, W, rec, emitters):
    """A :class:`BoundsCull` when ``settings.cull == "bounds"`` applies (one-bounce chain, one
    light point for every caster), ``bounds_select.bounds_cull`` for two bounces and the sun,
    else None.  Bounds are cached per receiver on the chain's emitters (shared by every band)."""
    if settings.cull == "bounds" and rec is not None and em.size and (len(chain) == 2 or not np.all(x0_of == x0_of[:1])):
        from .bounds_select import bounds_cull  # two bounces, and one bounce from a light point per caster (sun)
        return bounds_cull(scene, settings, chain, ls, m, em, tri_of, x0_of, band, W, rec)
    if settings.cull != "bounds" or len(chain) != 1 or ls.kind == "sun" or rec is None or em.size == 0:
        return None
    if not np.all(x0_of == x0_of[:1]):
        return None
    from .cull import BoundsCull

    cache = em.extra.setdefault(("bounds", rec.name, rec.resolution), {})
    tri = tri_of[:, 0]
    seed = [int(settings.seed) & 0x7FFFFFFF, m, "RT".index(chain), band.row0]
    H = rec.resolution[1]
    return BoundsCull(chain, em, x0_of[0], scene.tri_p[tri], scene.tri_n[tri], scene.tri_ior[tri], scene.tri_p[rec.tri_index],
                      rec.tri_index, rec.uv, band, W, H, gamma=settings.gamma, intensity=float(np.max(ls.rgb[m])),
                      rng=np.random.default_rng(seed), cache=cache)


def _fresnel_dielectric(cos_i, eta_i, eta_t):
    """Unpolarised dielectric Fresnel reflectance (vectorised; 1 under total internal reflection)."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t = eta_i / eta_t * np.sqrt(np.maximum(0.0, 1.0 - cos_i * cos_i))
    tir = sin_t >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin_t * sin_t))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t)
        rp = (eta_i * cos_t - eta_t * cos_i) / (eta_i * cos_t + eta_t * cos_i)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))


def _path_values(scene, chain, ls, m, x_start, x_end, P, N, eta, tri, ti, uv, band, s):
    """Per path: scalar weight (W/m² per unit RGB), front-facing mask, RGB factor (m,3), and the
    specular vertices [x1, ..., xk] ((m,3) each)."""
    k = len(chain)
    ptri = tri[ti]  # (m, k)
    role = scene.tri_role[ptri]
    verts = []
    for j in range(k):
        p = P[ti, j]
        verts.append(p[:, 0] + uv[:, 2 * j:2 * j + 1] * (p[:, 1] - p[:, 0]) + uv[:, 2 * j + 1:2 * j + 2] * (p[:, 2] - p[:, 0]))
    geometry = np.zeros(ti.size)
    fresnel = np.zeros(ti.size)
    direction = np.zeros((ti.size, 3))
    extra = np.ones(ti.size)
    if k == 1 and chain == "R":
        groups = (("mirror", role[:, 0] != ROLE_BOTH), ("dielectric", role[:, 0] == ROLE_BOTH))
    else:
        groups = (("mirror", np.ones(ti.size, dtype=bool)),)
        # Glass ('both') reflections of longer chains: dielectric Fresnel at that vertex.
        for j in range(k):
            if chain[j] != "R":
                continue
            glass = np.flatnonzero(role[:, j] == ROLE_BOTH)
            if glass.size == 0:
                continue
            prev = x_start[ti[glass]] if j == 0 else verts[j - 1][glass]
            x = verts[j][glass]
            nn = N[ti[glass], j]
            u, v = uv[glass, 2 * j:2 * j + 1], uv[glass, 2 * j + 1:2 * j + 2]
            n = nn[:, 0] + u * (nn[:, 1] - nn[:, 0]) + v * (nn[:, 2] - nn[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            pg = P[ti[glass], j]
            ng = np.cross(pg[:, 1] - pg[:, 0], pg[:, 2] - pg[:, 0])
            ng *= np.where(np.sum(ng * n, axis=1) >= 0, 1.0, -1.0)[:, None]
            wi = x - prev
            wi /= np.linalg.norm(wi, axis=1, keepdims=True)
            outside = np.sum(wi * ng, axis=1) < 0
            e = eta[ti[glass]]
            extra[glass] *= _fresnel_dielectric(np.abs(np.sum(wi * n, axis=1)), np.where(outside, 1.0, e), np.where(outside, e, 1.0))
    for model, mask in groups:
        idx = np.flatnonzero(mask)
        if idx.size == 0:
            continue
        res = path_irradiance(chain, x_start, x_end, P, N, eta, ti[idx], uv[idx], receiver_normal=None, reflectance=model)
        geometry[idx] = res.geometry
        fresnel[idx] = res.fresnel
        direction[idx] = res.direction
    x_last = verts[-1]
    x2 = x_end[ti]
    sample = s[ti]
    front = np.sum((x_last - x2) * band.geo_normal[sample], axis=1) > 0
    cos_r = np.maximum(0.0, -np.sum(direction * band.normal[sample], axis=1))
    d0 = verts[0] - x_start[ti]
    l0 = np.linalg.norm(d0, axis=1)
    w0 = d0 / l0[:, None]
    prof = emission_factor(ls, np.full(ti.size, m), w0)
    weight = geometry * fresnel * extra * cos_r * prof
    if ls.kind == "sun":
        weight = weight * l0 * l0
    rgb = np.broadcast_to(ls.rgb[m], (ti.size, 3)) * np.prod(scene.tri_tint[ptri], axis=1)
    weight = np.where(front, weight, 0.0)
    return weight, front, rgb, verts


def _direct(scene, bvh, eps, extent, ls, band, sums, timer, chunk=1 << 21):
    """Direct light onto the samples (the chain of length 0): I f(w) cos / d², or S cos for the
    sun; all light samples at once, in chunks of (light sample, receiver sample) pairs."""
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
