"""The ``path-points`` estimator: every exact specular path at every texel supersample.

For every receiver band, light sample and planned chain, a cull selects the candidate
(caster tuple, supersample) pairs: by default (``cull="bounds"``) the one- and two-bounce
Bernstein position bounds of Fan et al. 2025 §4 (:mod:`addon.bake.bounds_select`: R, T, RR,
RT, TR, TT, point lights and the sun); ``cull="cone"`` (or True) the side tests and cones of
scattered directions (:class:`addon.bake.cull.TupleCull`, also the fallback where the bounds
do not apply); the solver finds their paths (``spoly``: the
Specular Polynomials of Fan et al. 2024, every path; the baselines ``newton``, ``sms``,
``curve``), and each path is weighed and tested:

    E = I f(w0) (dΩ0/dA) F tint cos θr V

(docs/design.md; I the light's intensity, f its emission profile, dΩ0/dA the generalised geometry
term and F the Fresnel product from ``addon.solver.path_irradiance``, V the visibility of
every segment through the scene BVH).  A texel's value is the mean over its supersamples.
Tested against the image-source mirror, Snell through a flat interface and Cycles
(tests/bake/test_bake_mirror.py, test_bake_units.py, test_bake_caustics.py).
"""

import time

import numpy as np

from ...solver import path_irradiance, solve_tuples
from ...solver.spoly.api import CHAIN_LENGTH, TupleTable
from ...solver.geometry.bvh import segments_occluded
from ...solver.geometry.optics import fresnel_dielectric_many
from ..bounds_select import bounds_cull
from ..cull import TupleCull, one_bounce_emitters, two_bounce_emitters
from ..lights import emission_factor, light_points, lit_casters
from ..scene import ROLE_BOTH
from ..settings import SOLVER_CHAINS
from .base import Estimator

_SUPPORT = {}


def chain_supported(chain):
    """Whether addon.solver solves ``chain`` and gives its irradiance (probed once, with an
    empty batch: "not supported" is a ValueError; a solver module that fails to import
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


def chain_status(settings, chain):
    """Why the path-points estimator cannot bake ``chain`` with ``settings.solver`` (a
    "skipped: ..." status), or None when it can."""
    solver = settings.solver
    if chain not in SOLVER_CHAINS[solver]:
        return f"skipped: the {solver} solver does not solve {chain} (it solves {', '.join(SOLVER_CHAINS[solver])})"
    if solver == "curve":
        error = make_solver(settings)[1]
        if error:
            return f"skipped: {error}"
    if solver == "spoly" and not chain_supported(chain):
        return "skipped: not supported by the solver"
    return None


def make_solver(settings):
    """(solve, error): ``solve(chain, x_start, x_end, P, N, eta) -> (tuple_index, uv)`` for
    ``settings.solver``, or None for the default path (``solve_tuples`` on
    ``settings.device``); ``error`` a reason when the solver cannot be loaded."""
    name = settings.solver
    if name == "spoly" and not settings.pieces:
        return None, None
    if name == "spoly":
        from ...solver.spoly.api import SpecularPolynomialSolver

        solver, kw = SpecularPolynomialSolver(), {"pieces": int(settings.pieces), "device": settings.device}
    elif name == "newton":
        from ...solver.baselines.newton_sms import NewtonSolver

        solver, kw = NewtonSolver(), {}
    elif name == "sms":
        from ...solver.baselines.newton_sms import SMSSolver

        solver, kw = SMSSolver(int(settings.sms_seeds), int(settings.seed)), {}
    else:
        try:
            from ...solver.baselines.curve_walk import CurveWalkSolver

            solver, kw = CurveWalkSolver(), {}
        except Exception as ex:  # broken install: the bake says so and skips its chains
            return None, f"solver 'curve' is not available ({type(ex).__name__}: {ex})"

    def solve(chain, x_start, x_end, P, N, eta):
        kwargs = dict(kw)
        if "pieces" in kwargs and len(chain) == 1:
            kwargs.pop("pieces")
        res = solver.solve(chain, x_start, x_end, P, N, eta, **kwargs)
        return res.tuple_index, res.uv

    return solve, None


class PathPoints(Estimator):
    name = "path-points"

    def __init__(self, ctx, items):
        super().__init__(ctx, items)
        self.solve = make_solver(ctx.settings)[0]
        self.emitter_cache = {}  # (item id, light sample) -> emitters, shared by every band and receiver
        if ctx.settings.device != "numba" and ctx.settings.solver == "spoly":
            self.device = _device_label(ctx.settings.device)

    def accumulate(self, rec_index, band, sums):
        ctx = self.ctx
        rec = ctx.receivers[rec_index]
        for li, ls in enumerate(ctx.lsamples):
            for m in range(ls.size):
                for idx, item in enumerate(self.items):
                    if item.light != li or rec_index not in item.receivers:
                        continue
                    key = (idx, m)
                    if key not in self.emitter_cache:
                        t0 = time.perf_counter()
                        self.emitter_cache[key] = chain_emitters(ctx, item, ls, m)
                        ctx.timer.add("cull", time.perf_counter() - t0)
                    st = yield from chain_pass(ctx, item, ls, m, band, rec_index, sums, self.emitter_cache[key], self.solve,
                                               rec=rec)
                    self.add_counts(item.chain, st)

    def report(self):
        return {"solver": self.ctx.settings.solver, "cull": _cull_name(self.ctx.settings.cull)}


def _device_label(device):
    """Where the Specular Polynomials of this bake run, for report.json's devices: "opencl: " and
    the device's name, or "cpu (numba)" where there is no such OpenCL device (the solve then warns
    and runs on Numba)."""
    from ...solver.opencl.backend import OpenCLUnavailable, device_name, parse_device

    try:
        return "opencl: " + device_name(parse_device(device))
    except OpenCLUnavailable:
        return "cpu (numba)"


def _cull_name(cull):
    if cull == "bounds":
        return "bounds"
    return "cone" if cull else "sides"


def chain_emitters(ctx, item, ls, m):
    """(emitters, global caster ids per emitter (n, k), light point per emitter (n, 3)) or None."""
    scene, settings = ctx.scene, ctx.settings
    chain = item.chain
    cast1 = item.vertices[0]
    x0_all = light_points(ls, m, scene.tri_p[cast1], ctx.extent, settings.sun_distance)
    keep = lit_casters(ls, m, x0_all, scene.tri_p[cast1])
    cast1 = cast1[keep]
    x0_all = x0_all[keep]
    if cast1.size == 0:
        return None
    if len(chain) == 1:
        em = one_bounce_emitters(chain, x0_all, scene.tri_p[cast1], scene.tri_n[cast1], scene.tri_ior[cast1])
        tri_of = cast1[em.index]
    else:
        cast2 = item.vertices[1]
        em = two_bounce_emitters(chain, x0_all, scene.tri_p[cast1], scene.tri_n[cast1], scene.tri_ior[cast1],
                                 scene.tri_p[cast2], scene.tri_n[cast2], scene.tri_ior[cast2], ids1=cast1, ids2=cast2)
        tri_of = np.column_stack([cast1[em.index[:, 0]], cast2[em.index[:, 1]]]) if em.size else np.zeros((0, 2), dtype=np.int64)
    if not settings.cull:
        em.without_cone()
    return em, tri_of, x0_all[em.index[:, 0]]


def new_counts():
    return {"tuples_tile_cull": 0, "tuples": 0, "paths": 0, "paths_front": 0, "paths_lit": 0, "paths_visible": 0}


def chain_pass(ctx, item, ls, m, band, rec_index, sums, emitters, solve=None, rec=None):
    """One chain, one light sample, one band: cull, solve in batches, weigh, test, accumulate.
    ``solve``: the solver (:func:`make_solver`; None: ``solve_tuples``).
    A generator: yields ``(None, message)`` after every batch, returns the counts."""
    scene, settings, timer = ctx.scene, ctx.settings, ctx.timer
    chain = item.chain
    st = new_counts()
    if emitters is None or emitters[0].size == 0:
        return st
    em, tri_of, x0_of = emitters
    W = ctx.receivers[rec_index].resolution[0]
    t0 = time.perf_counter()
    cull = bounds_cull(scene, settings, chain, ls, m, em, tri_of, x0_of, band, W, rec) if settings.cull == "bounds" else None
    if cull is None:
        cull = TupleCull(em, band.position, band.geo_normal, band.texel, W)
    st["tuples_tile_cull"] = cull.upper_bound
    timer.add("cull", time.perf_counter() - t0)
    t0 = time.perf_counter()
    table = None
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
        if solve is None and settings.device != "numba":
            # the emitter and point tables go to the device once per pass, then pairs per batch
            if table is None:
                table = TupleTable(chain, x0_of, scene.tri_p[tri_of], scene.tri_n[tri_of], scene.tri_ior[tri_of[:, 0]],
                                   band.position, device=settings.device)
            result = table.solve(e, s)
            ti, uv = result.tuple_index, result.uv
        elif solve is None:
            ti, uv = solve_tuples(chain, x_start, x_end, P, N, eta)
        else:
            ti, uv = solve(chain, x_start, x_end, P, N, eta)
        timer.add("solve", time.perf_counter() - t0)
        st["paths"] += ti.size
        accumulate_paths(ctx, item, ls, m, band, rec_index, sums, tri, x_start, x_end, P, N, eta, ti, uv, s, inv_p, st)
        yield None, f"{chain}: {st['tuples']:,} tuples"
        t0 = time.perf_counter()
    return st


def accumulate_paths(ctx, item, ls, m, band, rec_index, sums, tri, x_start, x_end, P, N, eta, ti, uv, s, inv_p, st):
    """Weigh solved paths (row r: tuple ti[r] with barycentrics uv[r]), test their visibility
    and add their irradiance to their samples' texels; counts into ``st``, power into the
    ledger (irradiance x the world area a supersample stands for)."""
    scene, timer, extent, eps = ctx.scene, ctx.timer, ctx.extent, ctx.eps
    chain = item.chain
    k = len(chain)
    if not ti.size:
        return
    t0 = time.perf_counter()
    weight, front, rgb, verts = path_values(scene, chain, ls, m, x_start, x_end, P, N, eta, tri, ti, uv, band, s)
    timer.add("irradiance", time.perf_counter() - t0)
    st["paths_front"] += int(front.sum())
    idx = np.flatnonzero(front & (weight > 0))
    st["paths_lit"] += idx.size
    if not idx.size:
        return
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
        blocked[live] = segments_occluded(ctx.bvh, points[j][live], points[j + 1][live], ig[live], eps)
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
    pt = tri[ti[vis]]
    power = w.mean(axis=1) * ctx.sample_area(rec_index)[band.tri[s[ti[vis]]]]
    ctx.ledger.add(item.light, chain, scene.tri_object[pt[:, 0]], scene.tri_object[pt[:, 1]] if k > 1 else None,
                   np.full(vis.size, rec_index), power)
    timer.add("accumulate", time.perf_counter() - t0)


def path_values(scene, chain, ls, m, x_start, x_end, P, N, eta, tri, ti, uv, band, s):
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
            cos_i = np.ascontiguousarray(np.abs(np.sum(wi * n, axis=1)), dtype=np.float64)
            eta_i = np.ascontiguousarray(np.where(outside, 1.0, e), dtype=np.float64)
            eta_t = np.ascontiguousarray(np.where(outside, e, 1.0), dtype=np.float64)
            extra[glass] *= fresnel_dielectric_many(cos_i, eta_i, eta_t)
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

