"""The ``path-seeded`` estimator: exact two-bounce paths at the texel supersamples by Newton
from forward-image seeds.

Per band, every supersample near a forward-image sub-triangle's image (:mod:`.forward_images`)
gets a seed; Newton on the exact two-vertex constraint (eq. 3 of Fan et al. 2024 at both
vertices, :func:`addon.solver.estimators.forward_image.solve_image_seeds`) solves the path through the
tuple the seed's ray passes, duplicates are merged, and the paths are weighed, tested and
accumulated exactly as :mod:`.path_points` does.  Every path is a validated exact path;
completeness is measured against the exact solver (tests/bake/test_bake_two_bounce.py).
One-bounce chains planned for this estimator run ``path-points`` (BakeSettings.estimator_for).
"""

import time

import numpy as np

from ...solver.estimators.forward_image import ImageSeeds, dedupe_paths, solve_image_seeds
from .base import Estimator
from .forward_images import ImageCache
from .path_points import accumulate_paths, new_counts

SEED_COUNTS = ("seeds", "newton", "hops", "converged", "paths")


class PathSeeded(Estimator):
    name = "path-seeded"

    def __init__(self, ctx, items):
        super().__init__(ctx, items)
        self.images = ImageCache(ctx, "seeded")
        self.seed_counts = dict.fromkeys(SEED_COUNTS, 0)

    def accumulate(self, rec_index, band, sums):
        ctx = self.ctx
        for li, ls in enumerate(ctx.lsamples):
            for m in range(ls.size):
                for idx, item in enumerate(self.items):
                    if item.light != li or rec_index not in item.receivers:
                        continue
                    state = self.images.get(idx, item, ls, m)
                    if state is not None and state.report["device"] != "numba":  # its images' refinement, tracing
                        on = "refinement, tracing" if state.report["refined_on_device"] else "tracing"
                        self.device = f"{state.report['device']} ({on} of the forward images; Newton on the CPU)"
                    st = self._pass(item, ls, m, band, rec_index, sums, state)
                    self.add_counts(item.chain, st)
        return
        yield  # noqa: unreachable

    def _pass(self, item, ls, m, band, rec_index, sums, state):
        """One chain, one light sample, one band: seeds, exact Newton, merge, weigh, test, add."""
        ctx = self.ctx
        st = new_counts()
        if state is None:
            return st
        t0 = time.perf_counter()
        tri, x_start, s, uv, c = band_paths(state, rec_index, band)
        ctx.timer.add("solve", time.perf_counter() - t0)
        for key in c:
            self.seed_counts[key] += c[key]
        st["tuples_tile_cull"] = st["tuples"] = c["seeds"]
        st["paths"] = c["paths"]
        n = tri.shape[0]
        if n:
            ti = np.arange(n, dtype=np.int64)
            x_end = band.position[s]
            scene = ctx.scene
            P = scene.tri_p[tri]
            N = scene.tri_n[tri]
            eta = scene.tri_ior[tri[:, 0]]
            accumulate_paths(ctx, item, ls, m, band, rec_index, sums, tri, x_start, x_end, P, N, eta, ti, uv, s, None, st)
        return st

    def report(self):
        passes = self.images.reports
        return {"passes": passes, "counts": dict(self.seed_counts),
                "dropped_sub_triangles": int(sum(p["dropped"] for p in passes))}


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
                          a["tri_rec"], a["tri_p"], a["tri_n"], a["tri_ior"], a["tri_role"], *a["bvh"], a["eps"], a["planes"], ok, t2, uv,
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
