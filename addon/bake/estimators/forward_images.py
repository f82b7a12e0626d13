"""Forward images: a chain's caster triangles cut into sub-triangles traced forward exactly
(the maths is in :mod:`addon.solver.estimators.forward_image`), shared by the ``forward-flux`` and
``path-seeded`` estimators.

For one light sample and chain, the first-vertex casters the light reaches, and whose scattered
light can reach the chain's next targets (:func:`addon.bake.cull.first_casters_reaching`), are cut into
adaptive sub-triangles whose forward-traced images on the receivers are straight to within
half a texel (:func:`prepare`), once per light sample and chain, for every receiver and band.
"""

import math
import time
import warnings

import numpy as np

from ...solver.estimators.forward_image import light_area_density, refine_image_triangles, trace_chain_points
from ...solver.geometry.receiver_planes import no_planes, receiver_planes
from ..cull import first_casters_reaching, sphere_tree
from ..lights import light_points, lit_casters

IMAGE_GRID = 4  # first level: G x G sub-triangles per caster triangle
IMAGE_TOLERANCE = 0.5  # texels: a final sub-triangle's image is straight to within this
IMAGE_RELATIVE = 0.01  # "flux": ... and its flux density linear over it to within this (refine_image_triangles' relative)
IMAGE_MARGIN = 0.25  # texels added around every image (plus twice its measured deviation)
IMAGE_COARSE = 2  # "flux": levels above the first grid where small images may stop (refine_image_triangles' coarse)
IMAGE_COARSE_LINEAR = 4.0  # texels: ... those longer than this linear to IMAGE_RELATIVE x (this / their length)²
EXTEND_FLAT_RECEIVERS = True  # rays that miss a flat receiver land on its plane, extended (False: cut by bisection; tests)
LANDED_KERNEL = True  # landed sub-triangles refined in one kernel, Numba or the OpenCL tracer's (False: numpy levels only; tests)
FIRST_STEP_WORK = 5000.0  # with a ChunkSizer: the first chunk, before any is timed, at most this much estimated work
FIRST_STEP_CASTERS = 16  # ... and at most this many casters (the estimate knows the caster's size, not its image's)
REACH_STEP = 32768  # ... lit casters cone-tested per progress step
MESH_STEP = 65536  # ... mesh points traced per progress step
LOST_PROBE_TEXELS = 4.0  # texels: lost sub-triangles are probed and dropped from the level where they are this small (world)


class ImageState:
    """The refined sub-triangles of one (light sample, chain) and what the solve needs."""

    def __init__(self, chain, emit_tri, x0, tris, arrays, report):
        self.chain = chain
        self.emit_tri = emit_tri  # (n,) global first-triangle id per emitter
        self.x0 = x0  # (n, 3) light point per emitter
        self.tris = tris  # dict of refine_image_triangles
        self.arrays = arrays
        self.report = report


def scene_arrays(scene, receivers, second, only=None):
    """Receiver index and UVs per scene triangle (receivers not in ``only``, when given, count
    as occluders), the mask of valid second vertices, and the ``planes`` of those receivers
    that are flat (:func:`~addon.solver.geometry.receiver_planes.receiver_planes`: rays that
    miss them are extended onto their planes; none when ``EXTEND_FLAT_RECEIVERS`` is False)."""
    n = scene.n_triangles
    tri_rec = np.full(n, -1, dtype=np.int64)
    tri_uv = np.zeros((n, 3, 2))
    flat = []
    for r, rec in enumerate(receivers):
        if only is None or r in only:
            tri_rec[rec.tri_index] = r
            tri_uv[rec.tri_index] = rec.uv
            flat.append((r, rec.tri_index, rec.uv))
    second_ok = np.zeros(n, dtype=np.bool_)
    second_ok[second] = True
    planes = receiver_planes(scene.tri_p, scene.tri_n, flat) if EXTEND_FLAT_RECEIVERS else no_planes()
    return tri_rec, tri_uv, second_ok, planes


def _bvh_args(bvh):
    return (bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_start, bvh.node_count, bvh.order, bvh.v0, bvh.e1, bvh.e2)


def prepare(scene, bvh, eps, chain, emit_tri, x0, second, receivers, max_depth=6, mode="flux", parallel=False, only=None,
            coarse=0, shared=True, triangle_arrays=None, device="numba", caster_size=None, mesh_points=None):
    """Refine the sub-triangles of the emitters (first triangles ``emit_tri`` lit from ``x0``)
    for ``chain`` (one or two vertices; "seeded" needs two); ``second`` the global ids of
    the chain's second-vertex casters (ignored for one vertex); ``receivers`` the receivers at
    the bake's resolution; ``mode`` "flux" or "seeded" (how finely to refine); ``parallel``:
    a sun (the same flux per area all over a first triangle); ``only`` the receiver indices
    the chain is baked onto (None: all); ``coarse`` levels above the first grid where small
    images may stop and ``shared`` whether points shared by sub-triangles are traced once
    (:func:`refine_image_triangles`); ``triangle_arrays`` :func:`scene_arrays` of these
    arguments when the caller has them (a chunk of casters); ``device`` "opencl[:N]" refines
    the landed sub-triangles and traces the points on that OpenCL device (the same
    sub-triangles and points as Numba; without pyopencl or a device it warns and uses Numba); ``caster_size`` the emitters' :func:`caster_texels` when the caller
    has them; ``mesh_points`` the emitters' whole-triangle traces (:func:`pass_mesh_points`).
    Returns an ImageState, ``report["device"]`` where it traced (``report["refined_on_device"]``
    whether the landed refinement ran there too)."""
    t0 = time.perf_counter()
    trace_args = _trace_arguments(scene, bvh, eps, chain, emit_tri, x0,
                                  triangle_arrays or scene_arrays(scene, receivers, second, only))
    x0, emit_tri, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role = trace_args[:12]
    bvh_args = trace_args[12:21]
    planes = trace_args[22]
    clock = [0.0]  # seconds inside the tracing kernel (reported as trace_seconds)
    tracer = _device_tracer(device, trace_args)

    def trace(e, u, v):
        """(second triangle, receiver triangle, UV, transport factor) of the points."""
        t_in = time.perf_counter()
        m = e.shape[0]
        t2 = np.empty(m, dtype=np.int64)
        rec = np.empty(m, dtype=np.int64)
        uv = np.empty((m, 2))
        fac = np.empty(m)
        if m and tracer is not None:
            tracer.trace(e, u, v, t2, rec, uv, fac)
        elif m:
            trace_chain_points(np.ascontiguousarray(e), np.ascontiguousarray(u), np.ascontiguousarray(v), x0, emit_tri,
                               bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, *bvh_args,
                               float(eps), planes, t2, rec, uv, fac)
        clock[0] += time.perf_counter() - t_in
        return t2, rec, uv, fac

    def weight(e, bary):
        if parallel:
            return np.ones(bary.shape[:2])
        return light_area_density(x0[e], tri_p[emit_tri[e]], bary)

    texel = np.array([1.0 / max(r.resolution) for r in receivers]) if receivers else np.ones(1)
    # "seeded" needs images straight to the margin only (Newton does the rest); "flux" also a
    # near-uniform density and a finely resolved border of what lands.
    extra = dict(weight=weight, relative=IMAGE_RELATIVE, coarse_linear_texels=IMAGE_COARSE_LINEAR) if mode == "flux" else dict(
        relative=np.inf, partial_depth=max_depth)
    if coarse and receivers:
        if caster_size is None:
            caster_size = caster_texels(tri_p[emit_tri], tri_p, receivers, only)
        extra["keep_lost_depth"] = lost_probe_depth(caster_size, int(coarse))
    if LANDED_KERNEL:  # the landed sub-triangles refined in one kernel, on the tracer's device (the same rules)
        extra["kernel_scene"] = (trace_args, bool(parallel), tracer)
    tris = refine_image_triangles(trace, emit_tri.size, tri_rec, texel, grid=IMAGE_GRID, max_depth=max_depth,
                                  tolerance=IMAGE_TOLERANCE, coarse=coarse, shared=shared, top_points=mesh_points, planes=planes,
                                  **extra)
    r = tris["receiver"]
    tris["margin"] = IMAGE_MARGIN * texel[r] + 2.0 * tris["deviation"] if r.size else np.zeros(0)
    arrays = dict(tri_rec=tri_rec, second_ok=second_ok, refract1=refract1, refract2=refract2, tri_p=tri_p, tri_n=tri_n,
                  tri_ior=tri_ior, tri_role=tri_role, bvh=bvh_args, eps=float(eps), planes=planes, trace=trace)
    report = {"emitters": int(emit_tri.size), "points_traced": int(tris["traced"]), "sub_triangles": int(r.size),
              "dropped": int(tris["dropped"]), "partial": int(tris["partial"]), "border": int(tris["border"]), "final_per_depth": tris["final_per_depth"],
              "seconds": time.perf_counter() - t0, "trace_seconds": clock[0] + tris["kernel_seconds"],
              "device": "opencl: " + tracer.name if tracer is not None else "numba",
              "refined_on_device": tracer is not None and LANDED_KERNEL and tracer.refined_here,
              "extended_receivers": [receivers[int(r)].name for r in planes[:, 13]]}
    return ImageState(chain, emit_tri, x0, tris, arrays, report)


def _trace_arguments(scene, bvh, eps, chain, emit_tri, x0, arrays):
    """``trace_chain_points``' arguments from x0 to planes for emitters (first triangles
    ``emit_tri`` lit from ``x0``) of ``chain``; ``arrays`` the pass's :func:`scene_arrays`."""
    tri_rec, tri_uv, second_ok, planes = arrays
    return (np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(emit_tri, dtype=np.int64), len(chain),
            chain[0] == "T", chain[-1] == "T", second_ok, tri_rec, tri_uv, np.ascontiguousarray(scene.tri_p, dtype=np.float64),
            np.ascontiguousarray(scene.tri_n, dtype=np.float64), np.ascontiguousarray(scene.tri_ior, dtype=np.float64),
            np.ascontiguousarray(scene.tri_role, dtype=np.int64)) + _bvh_args(bvh) + (float(eps), planes)


def _device_tracer(device, trace_args):
    """An OpenCLPointTracer on ``device`` ("opencl" / "opencl:N") of the scene and emitters in
    ``trace_args`` (:func:`_trace_arguments`), or None for Numba (also, with a warning, when
    pyopencl or the device is missing)."""
    if device in (None, "numba"):
        return None
    from ...solver.opencl.backend import OpenCLUnavailable, parse_device

    x0, emit_tri, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role = trace_args[:12]
    try:
        from ...solver.opencl.tracing import OpenCLPointTracer

        return OpenCLPointTracer(parse_device(device), bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n,
                                 tri_ior, tri_role, trace_args[12:21], x0, emit_tri, trace_args[21], trace_args[22])
    except OpenCLUnavailable as ex:
        warnings.warn(f"OpenCL unavailable ({ex}); tracing on Numba instead", RuntimeWarning, stacklevel=3)
        return None


def lost_probe_depth(size, coarse):
    """(n,) per first triangle of ``size`` (n,) texels (:func:`caster_texels`), the depth from
    which its lost sub-triangles are probed and dropped (``keep_lost_depth`` of
    :func:`~addon.solver.estimators.forward_image.refine_image_triangles`, whose refinement
    starts at depth -``coarse``): the first level whose sub-triangles are at most
    ``LOST_PROBE_TEXELS`` long, at most depth 1.  A lost sub-triangle's 13 points (corners,
    edge midpoints, the 7 probes) are then at most a quarter of it, about a texel, apart: the
    flux of a landed region hiding between them would fill at most a texel of the caster.
    Larger casters are probed from depth 1 (1/32 of the caster: every lost region of a large
    caster is split that far)."""
    size = np.asarray(size, dtype=np.float64)
    levels = np.ceil(np.log2(np.maximum(size, 1e-300) / LOST_PROBE_TEXELS))
    return np.clip(levels, 0, 1 + coarse).astype(np.int64) - coarse


def caster_texels(P, tri_p, receivers, only):
    """(n,) the longest edge of each first triangle P (n, 3, 3) in texels: against the
    smallest world texel of the receivers in ``only`` (None: all); 0 without receivers."""
    texel = np.inf
    for r, rec in enumerate(receivers):
        if only is not None and r not in only:
            continue
        e1 = rec.uv[:, 1] - rec.uv[:, 0]
        e2 = rec.uv[:, 2] - rec.uv[:, 0]
        uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
        w = tri_p[rec.tri_index]
        world_area = 0.5 * np.linalg.norm(np.cross(w[:, 1] - w[:, 0], w[:, 2] - w[:, 0]), axis=1).sum()
        if uv_area > 0:
            texel = min(texel, math.sqrt(world_area / uv_area) / max(rec.resolution))
    edge = np.sqrt(((P - P[:, [1, 2, 0]]) ** 2).sum(axis=2)).max(axis=1)
    return edge / texel


def caster_chunks(work, max_work, max_casters):
    """Cut casters with estimated ``work`` (n,) into consecutive runs [a, b): a caster whose
    work starts in the k-th ``max_work`` of the running total belongs to run k, and runs of
    more than ``max_casters`` casters are cut again.  A function of the scene and settings
    alone, so the cut, and with it the order in which flux is summed, is the same on every
    machine."""
    work = np.asarray(work, dtype=np.float64)
    if work.size == 0:
        return []
    start = np.cumsum(work) - work
    run = np.floor(start / float(max_work)).astype(np.int64)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(run)) + 1, [work.size]])
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        out.extend((int(c), int(min(b, c + max_casters))) for c in range(a, b, int(max_casters)))
    return out


class ChunkSizer:
    """Cuts a pass's casters into consecutive runs that each take about ``seconds`` to refine
    and splat (a progress step, and how long Esc waits): the first run holds ``first_work`` of
    the estimated work (:func:`image_chunks`) and at most FIRST_STEP_CASTERS casters, each next
    one what the last run's measured seconds per unit of work allow, at most twice the last
    run's work.  Where the runs end changes no bit of the texture: a caster's sub-triangles do not depend on the other casters' and
    are splatted in caster order (refine_image_triangles returns them in emitter order);
    tests/bake/test_bake_chunks.py."""

    def __init__(self, seconds, first_work=None):
        self.seconds = float(seconds)
        self.first_work = FIRST_STEP_WORK if first_work is None else float(first_work)
        self.rate = None  # seconds per unit of work of the last timed run
        self.last_work = 0.0

    def runs(self, work, max_work, max_casters):
        """Yields (a, b): the next run of casters (``work`` (n,) their estimates), at most
        ``max_work`` and ``max_casters`` (memory); :meth:`took` times each before the next."""
        cum = np.concatenate([[0.0], np.cumsum(np.asarray(work, dtype=np.float64))])
        n = cum.size - 1
        a = 0
        while a < n:
            budget = self.first_work if self.rate is None else min(self.seconds / self.rate, 2.0 * self.last_work)
            b = int(np.searchsorted(cum, cum[a] + min(budget, max_work), side="left"))
            b = min(max(b, a + 1), a + int(max_casters), n, a + FIRST_STEP_CASTERS if self.rate is None else n)
            self.last_work = float(cum[b] - cum[a])
            yield a, b
            a = b

    def took(self, seconds):
        """The last run took ``seconds`` (refined and splatted)."""
        if self.last_work > 0.0:
            self.rate = max(float(seconds), 1e-6) / self.last_work


def _reaching_casters(ctx, item, ls, m, block=None):
    """The first-vertex casters of planned chain ``item`` that light sample ``m`` reaches and
    whose scattered light can reach the chain's next targets: returns (their global triangle
    ids, their light points, the chain's second-vertex casters, the cull's report), or None
    when there are none.  A generator: the lit casters are cone-tested in blocks of ``block``
    (None: one), with a ``yield`` between two blocks (a progress step)."""
    scene = ctx.scene
    cast1 = item.vertices[0]
    x0_all = light_points(ls, m, scene.tri_p[cast1], ctx.extent, ctx.settings.sun_distance)
    keep = lit_casters(ls, m, x0_all, scene.tri_p[cast1])
    second = item.vertices[1] if len(item.vertices) > 1 else np.zeros(0, dtype=np.int64)
    # Casters whose scattered light cannot reach the chain's next targets (receivers, or the
    # second-vertex casters) are not traced at all: a conservative cone test.
    t0 = time.perf_counter()
    lit = np.flatnonzero(keep)
    if second.size:
        targets = scene.tri_p[second]
    else:
        targets = scene.tri_p[np.concatenate([ctx.receivers[r].tri_index for r in item.receivers]
                                             or [np.zeros(0, dtype=np.int64)])]
    tree = sphere_tree(targets) if lit.size and targets.shape[0] else None
    reach = np.zeros(lit.size, dtype=np.bool_)
    step = max(1, lit.size if block is None else int(block))
    for a in range(0, lit.size, step):
        if block is not None:
            yield f"cone tests {a}/{lit.size}"
        s = lit[a:a + step]
        reach[a:a + step] = first_casters_reaching(item.chain, x0_all[s], scene.tri_p[cast1[s]], scene.tri_n[cast1[s]],
                                                   scene.tri_ior[cast1[s]], targets, tree)
    keep[lit[~reach]] = False
    reach_report = {"lit": int(lit.size), "reaching": int(reach.sum()), "seconds": time.perf_counter() - t0}
    if not keep.any():
        return None
    return cast1[keep], x0_all[keep], second, reach_report


def image_state(ctx, item, ls, m, mode, coarse=0, shared=True):
    """The refined sub-triangles (:func:`prepare`) of planned chain ``item`` for light sample
    ``m`` (:func:`image_chunks` in one piece), or None when the light reaches none of its
    first casters."""
    one_piece = image_chunks(ctx, item, ls, m, mode, math.inf, np.iinfo(np.int64).max, coarse, shared)
    return next(one_piece, (None,))[0]


def image_chunks(ctx, item, ls, m, mode, max_work, max_casters, coarse=0, shared=True, sizer=None):
    """The refined sub-triangles (:func:`prepare`) of planned chain ``item`` for light sample
    ``m`` in pieces: the reaching first casters, in their order, cut into runs of at most
    ``max_casters`` casters and about ``max_work`` sub-triangles (a caster's estimate: the
    first grid's IMAGE_GRID² times 1 + its size in texels squared, :func:`caster_texels`, at
    most 4^image_depth) (:func:`caster_chunks`), each refined on its own (a caster's
    sub-triangles do not depend on the others'), so that memory and the time between two
    progress steps follow the chunk, not the caster count.  With ``sizer`` (a
    :class:`ChunkSizer`, which the caller tells how long each chunk took) the runs are sized
    by time within those bounds, and the work before the first chunk comes in steps too: a
    message (str) is yielded between blocks of cone tests (``REACH_STEP`` casters) and slices
    of mesh points (``MESH_STEP``).  Yields (state, casters done, casters) per chunk; nothing
    when the light reaches none.  The cull's report is in the first chunk's
    ``state.report["reach"]``."""
    casters = yield from _reaching_casters(ctx, item, ls, m, None if sizer is None else REACH_STEP)
    if casters is None:
        return
    emit_tri, x0, second, reach_report = casters
    arrays = scene_arrays(ctx.scene, ctx.receivers, second, item.receivers)
    n = emit_tri.size
    size = caster_texels(ctx.scene.tri_p[emit_tri], ctx.scene.tri_p, ctx.receivers, item.receivers)
    work = IMAGE_GRID ** 2 * (1.0 + np.minimum(size ** 2, 4.0 ** int(ctx.settings.image_depth)))
    mesh, mesh_traced, mesh_seconds = None, 0, 0.0
    if shared and IMAGE_GRID >> int(coarse) == 1:
        t0 = time.perf_counter()
        mesh, mesh_traced = yield from pass_mesh_points(ctx, item.chain, emit_tri, x0, arrays,
                                                        None if sizer is None else MESH_STEP)
        mesh_seconds = time.perf_counter() - t0
    runs = caster_chunks(work, max_work, max_casters) if sizer is None else sizer.runs(work, max_work, max_casters)
    for a, b in runs:
        state = prepare(ctx.scene, ctx.bvh, ctx.eps, item.chain, emit_tri[a:b], x0[a:b], second, ctx.receivers,
                        max_depth=int(ctx.settings.image_depth), mode=mode, parallel=ls.kind == "sun",
                        only=item.receivers, coarse=coarse, shared=shared, triangle_arrays=arrays,
                        device=ctx.settings.device, caster_size=size[a:b],
                        mesh_points=None if mesh is None else tuple(np.ascontiguousarray(v[a:b]) for v in mesh))
        if a == 0:
            state.report["reach"] = reach_report
            state.report["points_traced"] += mesh_traced  # the pass's mesh points, traced once for all chunks
            state.report["trace_seconds"] += mesh_seconds
        yield state, b, n


def pass_mesh_points(ctx, chain, emit_tri, x0, arrays, step=None):
    """The whole-triangle traces of a pass's emitters (first triangles ``emit_tri``, light points
    ``x0``; ``arrays`` its :func:`scene_arrays`), each mesh vertex and edge midpoint traced once
    for all of them (:func:`~addon.solver.estimators.refine_kernel.mesh_points`), before
    the casters are cut into chunks, so that which emitter traces a shared point, and with it
    every bit of the result, does not depend on the cut; traced on the bake's device (the same
    points on OpenCL as on Numba), used by the refine kernel and by the numpy levels alike.
    None (and 0) without refine_kernel.MESH_SHARED.  A generator: the points are traced in
    slices of ``step`` (None: one), with a ``yield`` between two (a progress step); returns
    (mesh points, points traced)."""
    from ...solver.estimators import refine_kernel

    if not refine_kernel.MESH_SHARED or emit_tri.size == 0:
        return None, 0
    args = _trace_arguments(ctx.scene, ctx.bvh, ctx.eps, chain, emit_tri, x0, arrays)
    tracer = _device_tracer(ctx.settings.device, args)
    e, u, v, index = refine_kernel.mesh_points(args[1].size, args)
    m = e.size
    out = (np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64), np.empty((m, 2)), np.empty(m))
    sliced = step is not None
    step = max(1, m if step is None else int(step))
    for a in range(0, m, step):
        if sliced:
            yield f"mesh points {a}/{m}"
        b = min(m, a + step)
        part = tuple(o[a:b] for o in out)
        if tracer is not None:
            tracer.trace(e[a:b], u[a:b], v[a:b], *part)
        else:
            trace_chain_points(e[a:b], u[a:b], v[a:b], *args, *part)
    return refine_kernel.gather_mesh_points(out, index), m


class ImageCache:
    """:func:`image_state` once per (planned chain, light sample), with its report; ``coarse``
    and ``shared`` as in :func:`prepare`."""

    def __init__(self, ctx, mode, coarse=0, shared=True):
        self.ctx, self.mode, self.coarse, self.shared = ctx, mode, coarse, shared
        self.states = {}
        self.reports = []

    def get(self, item_index, item, ls, m):
        key = (item_index, m)
        if key not in self.states:
            t0 = time.perf_counter()
            state = image_state(self.ctx, item, ls, m, self.mode, self.coarse, self.shared)
            self.states[key] = state
            if state is not None:
                self.ctx.timer.add("image.trace", state.report["trace_seconds"])
                self.reports.append({"light": item.light, "light_sample": m, "chain": item.chain, **state.report})
            self.ctx.timer.add("image", time.perf_counter() - t0)
        return self.states[key]
