"""The ``forward-flux`` estimator (the default): texel-averaged irradiance from the flux of
forward-traced sub-triangles.

Every final sub-triangle of a chain's forward image (:mod:`.forward_images`) carries the flux
the light sample sends through it — point: I f(w) Ω (Ω its solid angle from the light); sun:
S times its area across the beam — times the transport factor of the path through its
centroid (Fresnel, the receiver's cos_shading / cos_geometric), the tints of its vertices
and the fraction of its points that landed.  Shadows are in the points: each is traced from
the light with a shadow segment and a shadowed point is lost like one that misses the
receivers, so a shadow's edge across a caster is refined and cut as a border (the other
segments are closest hits, unoccluded by construction).  The flux is spread over its
straight image in UV space by exact texel overlap with a density linear over the image
(:func:`addon.solver.estimators.forward_image.corner_densities`, :func:`~addon.solver.estimators.splat.splat_triangles`);
divided by each texel's world area it is the texel-averaged irradiance, finite at focal
points.  Energy is conserved by construction; tested against photon references
(tests/bake/test_bake_two_bounce.py, tests/bake/test_bake_caustics.py) and bench/glass_target.py.

Two implementations of the same estimate: :func:`flux_textures` (the default) computes the
sub-triangles' geometry, power and corner densities in Numba kernels
(:mod:`addon.solver.estimators.flux_kernel`), refines with ``IMAGE_COARSE`` levels above the
first grid (small images stop early: :func:`~addon.solver.estimators.forward_image.refine_image_triangles`)
and, for one-vertex chains, takes the centroid's transport factor from the quadratic through
the 6 traced points instead of tracing the centroid (:func:`_centroid_transport`);
:func:`flux_textures_reference` is the numpy form, used with ``coarse`` 0 and every point
traced for each sub-triangle when ``ForwardFlux.reference`` is set (tests/bake/test_bake_forward_flux.py compares the two;
bench/animation.py times both).

With ``device="opencl[:N]"`` the default form refines, traces and splats on that OpenCL device
(``addon/solver/opencl``: refine.cl, trace.cl, splat.cl; a pass's textures stay there until its
end) and computes the per-sub-triangle terms on Numba between: the same texture bit for bit
(tests/bake/test_bake_opencl_trace.py).
"""

import time
import warnings

import numpy as np

from ...solver.geometry.bvh import segments_occluded
from ...solver.estimators.flux_kernel import corner_densities_kernel, subtriangle_geometry
from ...solver.estimators.forward_image import corner_densities, solid_angle
from ...solver.estimators.splat import region_shares, splat_triangles
from ...solver.geometry.receiver_planes import region_of
from ..lights import emission_factor
from .base import Estimator
from .forward_images import IMAGE_COARSE, ChunkSizer, image_chunks

CASTER_CHUNK = 16384  # at most this many first casters refined and splatted together (a chunk: memory, a progress step)
CHUNK_WORK = 1000000  # ... and about this many sub-triangles by their estimate (forward_images.image_chunks)
GPU_CHUNK_SCALE = 4  # both, times this on a GPU device (its refine launch has a work-item per caster of the chunk)


def _device_textures(index, sizes):
    """:class:`~addon.solver.opencl.splatting.OpenCLSplat` (imported when a bake asks for a device)."""
    from ...solver.opencl.splatting import OpenCLSplat

    return OpenCLSplat(index, sizes)


class ForwardFlux(Estimator):
    name = "forward-flux"
    reference = False  # True: the numpy reference form (no coarse levels, every point traced; tests, benchmarks)

    def __init__(self, ctx, items):
        super().__init__(ctx, items)
        self.coarse = 0 if self.reference else IMAGE_COARSE
        self.flux_fn = flux_textures_reference if self.reference else flux_textures
        self.total = None  # (H W, 3) W per texel per receiver, summed over passes and caster chunks
        self.splat_device = None  # False once the bake's OpenCL device could not splat
        self.chunk_scale = 1
        if not self.reference and ctx.settings.device not in (None, "numba"):
            from ...solver.opencl.backend import device_is_gpu

            self.chunk_scale = GPU_CHUNK_SCALE if device_is_gpu(ctx.settings.device) else 1
        self.reports = []

    def prepare(self):
        """Per light sample and chain (a pass), the reaching first casters in chunks of at most
        ``CHUNK_WORK`` and ``CASTER_CHUNK`` (memory; both ``GPU_CHUNK_SCALE`` times larger on a
        GPU device, whose refine launch takes a chunk's casters as its work-items), sized by
        time when the settings' ``step_seconds`` is set (a ChunkSizer: so that a progress step,
        and Esc, come that often; the operator's bake): each chunk's forward images are refined
        and their flux splatted before the next.  The texture does not depend on the cut."""
        ctx = self.ctx
        passes = [(li, ls, m, item) for li, ls in enumerate(ctx.lsamples) for m in range(ls.size)
                  for item in self.items if item.light == li]
        for p, (li, ls, m, item) in enumerate(passes):
            where = f"{item.chain}: forward images (light {li + 1}, sample {m + 1})"
            yield p / len(passes), where
            report = None
            flux = None  # this pass's flux textures (HostFlux / OpenCLSplat): its chunks' splats, added to the total at its end
            step = float(ctx.settings.step_seconds)
            sizer = ChunkSizer(seconds=step) if step > 0.0 else None
            t0 = time.perf_counter()
            for got in image_chunks(ctx, item, ls, m, "flux", CHUNK_WORK * self.chunk_scale, CASTER_CHUNK * self.chunk_scale,
                                    self.coarse, shared=not self.reference, sizer=sizer):
                if isinstance(got, str):  # a step before the first chunk (cone tests, mesh points)
                    ctx.timer.add("image", time.perf_counter() - t0)
                    yield p / len(passes), f"{where}, {got}"
                    t0 = time.perf_counter()
                    continue
                state, done, count = got
                t_chunk = t0
                ctx.timer.add("image.trace", state.report["trace_seconds"])
                ctx.timer.add("image", time.perf_counter() - t0)
                t0 = time.perf_counter()
                if flux is None:
                    flux = self._pass_textures()
                self.flux_fn(ctx, item, state, ls, m, flux)
                ctx.timer.add("flux", time.perf_counter() - t0)
                if sizer is not None:
                    sizer.took(time.perf_counter() - t_chunk)
                report = _add_report(report, state.report)
                if state.report["device"] != "numba":
                    on = ["refinement"] * state.report["refined_on_device"] + ["tracing"] + ["splat"] * (not isinstance(flux, HostFlux))
                    self.device = f"{state.report['device']} ({', '.join(on)})"
                yield (p + done / count) / len(passes), f"{where}, casters {done}/{count}"
                t0 = time.perf_counter()
            ctx.timer.add("image", time.perf_counter() - t0)
            if report is not None:
                t0 = time.perf_counter()
                flux = flux.arrays()
                ctx.timer.add("flux.splat", time.perf_counter() - t0)
                self.total = flux if self.total is None else [a + b for a, b in zip(self.total, flux)]
                self.reports.append({"light": item.light, "light_sample": m, "chain": item.chain, **report})

    def _pass_textures(self):
        """A pass's flux textures, zero: on the bake's OpenCL device (the default form; the same
        bits as Numba's) or on the host."""
        ctx = self.ctx
        sizes = [tuple(r.resolution) for r in ctx.receivers]
        if not self.reference and ctx.settings.device not in (None, "numba") and self.splat_device is not False:
            from ...solver.opencl.backend import OpenCLUnavailable, parse_device

            try:
                return _device_textures(parse_device(ctx.settings.device), sizes)
            except OpenCLUnavailable as ex:  # no device, a program it rejects, no room for the textures
                self.splat_device = False
                warnings.warn(f"OpenCL unavailable ({ex}); splatting on Numba instead", RuntimeWarning, stacklevel=2)
        return HostFlux(sizes)

    def receiver_flux(self, rec_index):
        return None if self.total is None else self.total[rec_index]
        yield  # noqa: unreachable (a generator like the other estimators' stages)

    def report(self):
        passes = self.reports
        return {"passes": passes, "sub_triangles": int(sum(p["sub_triangles"] for p in passes)),
                "dropped_sub_triangles": int(sum(p["dropped"] for p in passes))}


def _add_report(total, chunk):
    """A pass's forward-image report: the chunks' counts and times summed (``final_per_depth``
    element by element), the cull's report from the first chunk, and the number of chunks."""
    if total is None:
        return {**chunk, "chunks": 1}
    out = dict(total)
    for k, v in chunk.items():
        if k == "final_per_depth":
            a, b = list(total[k]), list(v)
            n = max(len(a), len(b))
            out[k] = [(a[i] if i < len(a) else 0) + (b[i] if i < len(b) else 0) for i in range(n)]
        elif k not in ("reach", "device", "extended_receivers", "refined_on_device"):  # the same for every chunk
            out[k] = total[k] + v
    out["chunks"] = total["chunks"] + 1
    return out


def flux_textures(ctx, item, state, ls, m, out):
    """Add the flux (W per texel, into ``out``: the pass's textures, :class:`HostFlux` or
    ``OpenCLSplat``) of planned chain ``item``'s final sub-triangles in ``state`` for light
    sample ``m`` (see the module doc); their power also goes into ``ctx.ledger``.  The estimate of
    :func:`flux_textures_reference`, its per-sub-triangle terms in kernels, without the
    centroid's shadow test (the points' shadow segments decide)."""
    extent = ctx.extent
    receivers = ctx.receivers
    tris = state.tris
    e = tris["emitter"]
    n = e.size
    if n == 0:
        return
    clock = time.perf_counter()
    t1 = state.emit_tri[e]
    b = np.ascontiguousarray(tris["bary_full"])
    sun = ls.kind == "sun"
    d = np.ascontiguousarray(ls.direction[m], dtype=np.float64) if sun else np.zeros(3)
    x1 = np.empty((n, 3))
    power = np.empty(n)
    tri_p = state.arrays["tri_p"]
    subtriangle_geometry(tri_p, state.emit_tri, e, b, state.x0, sun, d, x1, power)
    t2, rec, fac = _centroid_transport(state, item, tris)
    if not sun:
        w0 = x1 - state.x0[e]
        w0 /= np.linalg.norm(w0, axis=1, keepdims=True)
        power *= emission_factor(ls, np.full(n, m), w0)
    power *= np.where(rec >= 0, fac, 0.0) * tris["landed"]
    clock = ctx.timer.since("flux.trace", clock)
    density = np.empty((n, 3))
    corner_densities_kernel(np.ascontiguousarray(tris["uv"]), np.ascontiguousarray(tris["mid_uv"]), tri_p, state.emit_tri, e, b,
                            state.x0, sun, d, 1e6 * extent, np.ascontiguousarray(tris["factor"]), density)
    regions = _regions(state, len(receivers))
    share = _inside_shares(tris, density, regions)
    clock = ctx.timer.since("flux.density", clock)
    flux = _coloured_flux(ctx, item, tris, t1, t2, power, ls.rgb[m], share)
    _splat(receivers, tris, flux, density, out, regions)
    ctx.timer.since("flux.splat", clock)


def _regions(state, n_receivers):
    """Per receiver, the UV region edges of its flat plane when the pass extended it
    (:func:`~addon.solver.geometry.receiver_planes.region_of`), else None."""
    planes = state.arrays.get("planes")
    if planes is None or planes.shape[0] == 0:
        return [None] * n_receivers
    return [region_of(planes, r) for r in range(n_receivers)]


def _inside_shares(tris, density, regions):
    """(n,) the share of each sub-triangle's flux inside its receiver's region (1 but where an
    image reaches beyond a flat receiver's edge: :func:`~addon.solver.estimators.splat.region_shares`);
    the power booked is what the splat deposits."""
    share = np.ones(tris["emitter"].size)
    for r, region in enumerate(regions):
        if region is None:
            continue
        sel = np.flatnonzero(tris["receiver"] == r)
        if sel.size:
            share[sel] = region_shares(tris["uv"][sel], density[sel], region)
    return share


def _centroid_transport(state, item, tris):
    """(second triangle, receiver triangle (-1: lost), transport factor) at each sub-triangle's
    centre (its landed part's for a partly landed one).  One-vertex chains: a sub-triangle
    whose 6 points landed on one receiver (finite factors) takes the factor of the quadratic
    through its corners and edge midpoints at the centroid, (4 (f01 + f12 + f20) - (f0 + f1 +
    f2)) / 9 (the transport factor is smooth: error third order in its size); the others,
    and two-vertex chains (the second triangle's tint), trace the centre."""
    n = tris["emitter"].size
    f6 = tris["factor"]
    quad = np.all(np.isfinite(f6), axis=1) if len(item.chain) == 1 else np.zeros(n, dtype=np.bool_)
    t2 = np.full(n, -1, dtype=np.int64)
    rec = np.zeros(n, dtype=np.int64)
    fac = np.maximum((4.0 * f6[:, 3:].sum(axis=1) - f6[:, :3].sum(axis=1)) / 9.0, 0.0)
    rest = np.flatnonzero(~quad)
    if rest.size:
        bc = tris["bary"][rest].mean(axis=1)  # the landed part's centre (a partly landed sub-triangle's bary is shrunk to it)
        t2[rest], rec[rest], _uv, fac[rest] = state.arrays["trace"](tris["emitter"][rest], np.ascontiguousarray(bc[:, 0]),
                                                                    np.ascontiguousarray(bc[:, 1]))
    return t2, rec, fac


def _shadow(ctx, t1, first, x1, power):
    """Zero the ``power`` of the sub-triangles whose light segment ``first`` -> ``x1`` (their
    centre on the first triangle ``t1``) is blocked."""
    live = np.flatnonzero(power > 0)
    if live.size:
        ig = np.column_stack([t1[live], np.full(live.size, -1)])
        blocked = segments_occluded(ctx.bvh, first[live], x1[live], ig, ctx.eps)
        power[live[blocked]] = 0.0


def _coloured_flux(ctx, item, tris, t1, t2, power, rgb, share):
    """The sub-triangles' RGB flux (n, 3): ``power`` x the light's ``rgb`` x the tints of the
    chain's triangles (one-vertex chains: no second tint); booked in ``ctx.ledger`` times
    ``share``, the part the splat deposits (:func:`_inside_shares`)."""
    scene = ctx.scene
    tint2 = np.where((t2 >= 0)[:, None], scene.tri_tint[np.maximum(t2, 0)], 1.0)
    flux = power[:, None] * rgb[None, :] * scene.tri_tint[t1] * tint2
    two = len(item.chain) == 2
    ctx.ledger.add(item.light, item.chain, scene.tri_object[t1], scene.tri_object[np.maximum(t2, 0)] if two else None,
                   tris["receiver"], flux.mean(axis=1) * share)
    return flux


class HostFlux:
    """A pass's flux textures on the host, (H W, 3) per receiver of ``sizes`` ((W, H) each),
    splatted by Numba (:func:`~addon.solver.estimators.splat.splat_triangles`); the interface
    of :class:`~addon.solver.opencl.splatting.OpenCLSplat`."""

    def __init__(self, sizes):
        self.sizes = [(int(w), int(h)) for w, h in sizes]
        self.out = [np.zeros((w * h, 3)) for w, h in self.sizes]

    def add(self, r, tri_uv, flux, density, region=None):
        W, H = self.sizes[r]
        splat_triangles(np.ascontiguousarray(tri_uv), np.ascontiguousarray(flux), W, H, self.out[r],
                        np.ascontiguousarray(density), region=region)

    def arrays(self):
        return self.out


def _splat(receivers, tris, flux, density, out, regions=None):
    """Splat the sub-triangles' ``flux`` with corner ``density`` onto their receivers' textures
    in ``out`` (:class:`HostFlux` or an OpenCL one), clipped to the receiver's ``regions[r]``
    where it has one (:func:`_regions`)."""
    for r in range(len(receivers)):
        sel = np.flatnonzero(tris["receiver"] == r)
        if sel.size:
            out.add(r, tris["uv"][sel], flux[sel], density[sel], region=None if regions is None else regions[r])


def flux_textures_reference(ctx, item, state, ls, m, out):
    """:func:`flux_textures` in numpy (the reference form), which also zeroes a sub-triangle
    whose centroid the light does not see (a seventh shadow sample: where an occluder hides
    between its 6 lit points the default keeps its whole flux, an error of the hidden share f
    instead of 1 - f with probability f)."""
    scene, extent = ctx.scene, ctx.extent
    receivers = ctx.receivers
    tris = state.tris
    e = tris["emitter"]
    n = e.size
    if n == 0:
        return
    t1 = state.emit_tri[e]
    P = scene.tri_p[t1]
    b = tris["bary_full"]
    corners = P[:, None, 0] + b[:, :, :1] * (P[:, None, 1] - P[:, None, 0]) + b[:, :, 1:] * (P[:, None, 2] - P[:, None, 0])
    bc = tris["bary"].mean(axis=1)  # the landed part's centre (a partly landed sub-triangle's bary is shrunk to it)
    clock = time.perf_counter()
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
    clock = ctx.timer.since("flux.trace", clock)
    _shadow(ctx, t1, first, x1, power)
    clock = ctx.timer.since("flux.visibility", clock)
    # the transport factor at the corners (Fresnel varies over large images); partly landed
    # sub-triangles have no midpoints and get the uniform splat anyway
    cf = np.nan_to_num(tris["factor"][:, :3], nan=1.0)
    if ls.kind == "sun":  # parallel light: the same solid angle per area everywhere
        far = corners.mean(axis=1) - 1e6 * extent * d
        density = corner_densities(tris["uv"], tris["mid_uv"], far, P, b, cf)
    else:
        density = corner_densities(tris["uv"], tris["mid_uv"], x0, P, b, cf)
    regions = _regions(state, len(receivers))
    share = _inside_shares(tris, density, regions)
    clock = ctx.timer.since("flux.density", clock)
    flux = _coloured_flux(ctx, item, tris, t1, t2, power, ls.rgb[m], share)
    _splat(receivers, tris, flux, density, out, regions)
    ctx.timer.since("flux.splat", clock)
