"""Bernstein-bounds tuple selection in the bake: which (tuple, texel sample) pairs the
path-points estimator solves (Fan et al. 2025, "Bernstein Bounds for Caustics").

Path-points (``BakeSettings(cull="bounds")``, the default; ``estimators.path_points.chain_pass``):

* one bounce (R, T): :class:`BoundsCull` (``one_bounce``'s position bounds, §4.2–4.3,
  eq 3–13, §6.1 subdivision); from the sun (a far light point per caster, lights.light_points)
  the bounds are taken with every caster's own point (:func:`one_bounce_bounds_points`), so the
  selection stays exact for the points the solver is given;
* two bounces (RR, RT, TR, TT): :class:`TwoBounceBoundsCull`.  Per (light point, receiver) the
  (t1, t2) pairs of the chain's cone emitters (``cull.two_bounce_emitters``) are intersected
  with the BVH pairs of §6.1 "Tuple construction" (``tuples.two_bounce_pairs``), each (pair, receiver
  triangle) that the cone test of ``cull.py`` admits gets the reach grid of
  ``two_bounce_irradiance.receivers_reached`` (the exact two-vertex map in affine arithmetic on 4 x 4
  cells of t1) and then the position quadtree of ``two_bounce_position`` (§4.3 with the remainder
  variables of eq 12–13 and the degree reduction of §6.1); the irradiance pass (eq 14–16,
  ``two_bounce_irradiance.piece_irradiance_two``) drops the pieces it proves empty and gives Ē for
  γ-sampling (§5, eq 21, 24, 28).  Each piece's (u1, v1) box is then cut into
  ``image_split``² sub-boxes whose receiver box is the piece's Bernstein box intersected with
  the enclosure of the exact map (eq 6–11 with the exact √β, eq 9 at both planes) in the affine
  arithmetic of ``affine`` (``two_bounce_image.image_box``): where only part of a box's light meets
  triangle 2 the position bound falls back to a constant form of (u2, v2) and loses the
  correlation of x2 with x1, the affine map keeps it (a 32 x 16 glass sphere's TT at 64², one
  sample per texel: the same paths from about a third of the pairs).  A band then keeps a sample for an emitter when a piece
  of (emitter, the sample's receiver triangle) holds it (:class:`PieceCull`,
  margin ``BOUNDS_MARGIN``) and the emitter's cone accepts it.

  Each step is conservative (no path is lost), so the selection is a subset of the cone cull's
  and holds every pair with a path; ``tests/bake/test_bake_bounds_select.py`` checks both against
  the exact paths of the cone cull.  The light point may differ per first triangle (the sun):
  the engines' drivers take one light point per caster, pair or piece.

  Fallback: where the bounds do not apply path-points keeps the cone cull
  (:class:`addon.bake.cull.TupleCull`): ``BakeSettings.cull`` other than "bounds", a chain
  other than R, T, RR, RT, TR, TT, no receiver, or no emitter.

:func:`reachable_first`: the first-vertex casters whose light can reach a receiver by these
bounds (a reference for the cone test that forward-flux uses, ``cull.first_casters_reaching``,
which costs far less).
"""

import math
import time

import numpy as np

from ..solver.bounds.layout import CHAIN_CODES, P_EHI, P_ELO, P_RECEIVER, PIECE_FIELDS
from ..solver.bounds.one_bounce import batch as one_bounce_batch
from ..solver.bounds.one_bounce import bound_one_bounce
from ..solver.bounds.tuples import two_bounce_pairs
from ..solver.bounds.two_bounce_image import split_pieces_chunk
from ..solver.bounds.two_bounce_irradiance import irradiance_chunk, reach_chunk
from ..solver.bounds.two_bounce_position import pair_pieces_chunk
from ..solver.runtime.jit import parallel_range, run_chunks
from .cull import count_cone_pairs, fill_cone_pairs, sample_in_cones, one_bounce_emitters, tri_spheres, two_bounce_emitters

# ---------------------------------------------------------------------------------------
# Bounds-driven cull (Fan et al. 2025; two bounces and the sun below,
# on :class:`PieceCull`): per (light point, caster triangle, receiver triangle)
# the Bernstein position bound (addon.solver.bounds.one_bounce) says which receiver points any
# admissible path can reach; only samples inside a piece's box are kept.  The cone test of
# the sample (``sample_in_cones``) is applied as well, so this cull keeps a subset of the cone
# cull's tuples, and every (caster, sample) pair holding a path survives both (both are
# conservative: no path is lost).  Optional γ-sampling (§5, eq 24, 28): each kept pair is
# solved with probability P = min(γ Ẽ, 1), Ẽ the largest Ē of the pieces covering the sample
# (eq 21, m = 1) times the light sample's largest RGB intensity, and weighted 1/P.

BOUNDS_MARGIN = 1e-7  # barycentric margin around the pieces' boxes (solver tolerance is 1e-9)
BOUNDS_SETTINGS = dict(max_depth=3, sigma=1e-4, alpha=2.0)


def one_bounce_bounds(chain, x0, tri_p, tri_n, eta, rec_p, rec_uv, irradiance=False, irr_refine=2):
    """Bounds of every (caster, receiver triangle) pair for the point x0 (one call per IOR).

    Returns (tuples (m, 2) local (caster, receiver) indices, piece_start (m+1,), pieces
    (p, PIECE_FIELDS), report)."""
    tuples, pieces, counts, reports = [], [], [], []
    for e in np.unique(eta):
        idx = np.flatnonzero(eta == e)
        res = bound_one_bounce(chain, x0, tri_p[idx], tri_n[idx], rec_p, rec_uv, eta=float(e), irradiance=irradiance,
                               irr_refine=irr_refine, **BOUNDS_SETTINGS)
        t = res.tuples.copy()
        t[:, 0] = idx[t[:, 0]]
        tuples.append(t)
        pieces.append(res.pieces)
        counts.append(np.bincount(res.piece_tuple, minlength=t.shape[0]))
        reports.append(res.report)
    tuples = np.concatenate(tuples) if tuples else np.zeros((0, 2), dtype=np.int64)
    pieces = np.ascontiguousarray(np.concatenate(pieces)) if pieces else np.zeros((0, PIECE_FIELDS))
    counts = np.concatenate(counts) if counts else np.zeros(0, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return np.ascontiguousarray(tuples, dtype=np.int64), start, pieces, reports


@parallel_range("tup_e")
def _bounds_pairs(fill, tup_e, tup_r, piece_start, pieces, tex_start, tex_order, band_rec, bary, W, H, row0, row1, margin,
                  part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, pos, rec_ng, offset, count, out_e,
                  out_s, out_E, first, last):
    for t in range(first, last):
        e = tup_e[t]
        r = tup_r[t]
        k0 = piece_start[t]
        k1 = piece_start[t + 1]
        xlo = np.inf
        xhi = -np.inf
        ylo = np.inf
        yhi = -np.inf
        for k in range(k0, k1):
            xlo = min(xlo, pieces[k, 8])
            xhi = max(xhi, pieces[k, 9])
            ylo = min(ylo, pieces[k, 10])
            yhi = max(yhi, pieces[k, 11])
        c = 0
        o = offset[t] if fill else 0
        if k1 > k0:
            i0 = max(0, int(math.floor(xlo * W)) - 1)
            i1 = min(W - 1, int(math.floor(xhi * W)) + 1)
            j0 = max(row0, int(math.floor(ylo * H)) - 1)
            j1 = min(row1 - 1, int(math.floor(yhi * H)) + 1)
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    tex = (j - row0) * W + i
                    for z in range(tex_start[tex], tex_start[tex + 1]):
                        s = tex_order[z]
                        if band_rec[s] != r:
                            continue
                        u = bary[s, 0]
                        v = bary[s, 1]
                        best = -1.0
                        for k in range(k0, k1):
                            if (u >= pieces[k, 4] - margin and u <= pieces[k, 5] + margin and v >= pieces[k, 6] - margin
                                    and v <= pieces[k, 7] + margin):
                                best = max(best, pieces[k, 12])
                        if best < 0.0:
                            continue
                        if not sample_in_cones(e, s, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, pos,
                                          rec_ng):
                            continue
                        if fill:
                            out_e[o] = e
                            out_s[o] = s
                            out_E[o] = best
                            o += 1
                        c += 1
        count[t] = c


class PieceCull:
    """Candidate (emitter, sample) tuples of one band from bound pieces (Fan et al. 2025 §4.2,
    eq 4–5; the position bounds of :func:`one_bounce_bounds`, or of the two-bounce bounds of
    ``addon.bake.bounds_select``): a sample of receiver triangle r is kept for emitter e when
    the tuple (e, r) has a piece whose receiver-barycentric box holds it (``BOUNDS_MARGIN``
    wider) and the emitter's cone accepts it (``sample_in_cones``), so the selection is a subset of
    :class:`TupleCull`'s.  ``tuples`` (m, 2) (emitter index, local receiver index into
    ``rec_tri``), pieces of tuple t at rows piece_start[t]:piece_start[t+1] of ``pieces``
    (the P_* columns of ``bounds.layout``).  ``gamma``: inf enumerates, else each pair is kept with
    P = min(γ Ẽ, 1) (eq 28, Ẽ the largest Ē of the pieces holding the sample, eq 21 with
    m = 1); :meth:`batches` yields (emitter index, sample index, 1/P or None)."""

    def _prepare(self, tuples, start, pieces, emitters, rec_tri, band, width, height, gamma, intensity, rng):
        self.n_bound_tuples = tuples.shape[0]
        e = emitters
        local = np.full(int(rec_tri.max()) + 1 if rec_tri.size else 1, -1, dtype=np.int64)
        local[rec_tri] = np.arange(rec_tri.size)
        band_rec = np.where(band.tri <= local.size - 1, local[np.minimum(band.tri, local.size - 1)], -1)
        row0, row1 = band.row0, band.row1
        tex = band.texel - row0 * width
        order = np.argsort(tex, kind="stable").astype(np.int64)
        tex_start = np.searchsorted(tex[order], np.arange((row1 - row0) * width + 1)).astype(np.int64)
        self.gamma = gamma
        self.intensity = intensity
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._args = (np.ascontiguousarray(tuples[:, 0]), np.ascontiguousarray(tuples[:, 1]), start, pieces, tex_start, order,
                      np.ascontiguousarray(band_rec), np.ascontiguousarray(band.bary), int(width), int(height), int(row0),
                      int(row1), BOUNDS_MARGIN, e.part_start, e.part_c, e.part_r, e.part_d, e.part_t, e.tri_ng, e.tri_p0,
                      e.side_req,
                      np.ascontiguousarray(band.position), np.ascontiguousarray(band.geo_normal))
        n = tuples.shape[0]
        self.count = np.zeros(n, dtype=np.int64)
        z = np.zeros(0, dtype=np.int64)
        if n:
            _bounds_pairs(False, *self._args, z, self.count, z, z, np.zeros(0))

    @property
    def upper_bound(self):
        return int(self.count.sum())

    def batches(self, max_tuples):
        from ..solver.bounds.sampling import selection_probability

        n = self.count.shape[0]
        csum = np.cumsum(self.count)
        q = 0
        while q < n:
            base = csum[q - 1] if q else 0
            q1 = max(q + 1, int(np.searchsorted(csum, base + max_tuples, side="right")))
            cnt = np.zeros(q1 - q, dtype=np.int64)
            sel = self.count[q:q1]
            offset = np.concatenate([[0], np.cumsum(sel)[:-1]]).astype(np.int64)
            total = int(sel.sum())
            out_e = np.empty(total, dtype=np.int64)
            out_s = np.empty(total, dtype=np.int64)
            out_E = np.empty(total)
            if total:
                a = self._args  # the tuples [q, q1) only (their piece rows are absolute)
                _bounds_pairs(True, a[0][q:q1], a[1][q:q1], a[2][q:q1 + 1], a[3], *a[4:], offset, cnt, out_e, out_s, out_E)
            q = q1
            if not total:
                continue
            if math.isinf(self.gamma):
                yield out_e, out_s, None
                continue
            p = selection_probability(out_E * self.intensity, self.gamma)
            keep = self.rng.random(p.shape[0]) < p
            if keep.any():
                yield out_e[keep], out_s[keep], 1.0 / p[keep]


class BoundsCull(PieceCull):
    """Candidate (caster, sample) tuples of a one-bounce chain from the Bernstein position
    bounds (see above; :class:`PieceCull`).  ``emitters``: the chain's :class:`Emitters` (one
    per caster, its cone used as an extra test); ``x0``: the light point, (3,) for all
    casters, or (T, 3) one per caster (the sun's far points: the bounds are then taken with
    each caster's own point, ``addon.bake.bounds_select.one_bounce_bounds_points``);
    ``tri_p, tri_n, eta``: the casters in emitter order; ``rec_tri`` (r,) global receiver
    triangle ids and ``rec_uv`` (r,3,2) their UVs; the band as for :class:`TupleCull`.
    ``gamma``: inf enumerates, else each tuple is kept with P = min(γ Ẽ, 1) (eq 28);
    :meth:`batches` yields (emitter index, sample index, 1/P).  ``cache``: a dict to keep the
    bounds in between bands.  ``parallel``: the light points stand for the sun (Ē scaled by
    |x1 - x0|², ``bounds_select.parallel_scale``).
    """

    def __init__(self, chain, emitters, x0, tri_p, tri_n, eta, rec_p, rec_tri, rec_uv, band, width, height, gamma=math.inf,
                 intensity=1.0, rng=None, cache=None, parallel=False):
        t0 = time.perf_counter()
        key = "bounds"
        if cache is not None and key in cache:
            tuples, start, pieces = cache[key]
        else:
            x0 = np.asarray(x0, dtype=np.float64)
            if x0.ndim == 2 and not np.all(x0 == x0[:1]):
                tuples, start, pieces, _ = one_bounce_bounds_points(chain, x0, tri_p, tri_n, eta, rec_p, rec_uv,
                                                                    irradiance=not math.isinf(gamma))
            else:
                tuples, start, pieces, _ = one_bounce_bounds(chain, x0.reshape(-1, 3)[0], tri_p, tri_n, eta, rec_p,
                                                             rec_uv, irradiance=not math.isinf(gamma))
            if parallel and not math.isinf(gamma):
                x0s = np.broadcast_to(x0.reshape(-1, 3), (tri_p.shape[0], 3))
                parallel_scale(pieces, start, tri_p[tuples[:, 0]], x0s[tuples[:, 0]])
            if cache is not None:
                cache[key] = (tuples, start, pieces)
        self.bounds_seconds = time.perf_counter() - t0
        self._prepare(tuples, start, pieces, emitters, rec_tri, band, width, height, gamma, intensity, rng)


TWO_BOUNCE_SETTINGS = dict(max_depth=3, sigma=1e-4, reach_depth=2, levels=1, refine=2, capacity=64, prune=True,
                           irr_depth=1, irr_ratio=2.0, image_split=4)
"""Two-bounce bounds of the bake: quadtree depth and σ (§6.1 stopping rules: 4 x 4 x 4 pieces of
t1 at most), the reach grid's 2^reach_depth cells, the BVH pair search's quadtree (levels,
refine; ``tuples.two_bounce_pairs``), most pieces per (pair, receiver), and the irradiance pass
(prune: drop the pieces it proves empty; irr_depth, irr_ratio as ``bound_irradiance_two``).
Measured by ``bench/bounds_select.py``."""

ROW_BUDGET = 1 << 25  # float64s of piece rows (or reach cells) per chunk of pairs: 256 MB


# ---------------------------------------------------------------------------------------
# bounds with a light point per caster / pair


def _points(x0, n):
    x0 = np.asarray(x0, dtype=np.float64)
    return np.array(np.broadcast_to(x0.reshape(-1, 3), (n, 3)) if x0.size == 3 else x0.reshape(n, 3))


def _cone_pairs(emitters, rec_p):
    """(emitter, receiver triangle) pairs that the cone test of ``cull.py`` admits (the tile
    test ``_tile_ok`` with the receiver triangles' bounding spheres as tiles): (m, 2) int64."""
    c, r = tri_spheres(np.asarray(rec_p, dtype=np.float64))
    e = emitters
    arrays = (e.part_start, e.part_c, e.part_r, e.part_d, e.part_t, e.tri_ng, e.tri_p0, e.side_req)
    count = np.zeros(e.size, dtype=np.int64)
    c = np.ascontiguousarray(c)
    r = np.ascontiguousarray(r)
    if e.size and c.shape[0]:
        count_cone_pairs(*arrays, c, r, count)
    offset = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    out = np.zeros(offset[-1], dtype=np.int64)
    if offset[-1]:
        fill_cone_pairs(*arrays, c, r, offset[:-1].copy(), out)
    return np.stack([np.repeat(np.arange(e.size, dtype=np.int64), count), out], axis=1)


def one_bounce_bounds_points(chain, x0, tri_p, tri_n, eta, rec_p, rec_uv, irradiance=False, irr_refine=2, pairs=None,
                             settings=None):
    """Position (and irradiance) bounds of every (caster, receiver triangle) pair with a light
    point per caster (Fan et al. 2025 §4.2–4.4, eq 3–19, §6.1; ``one_bounce.batch``):
    ``x0`` (T, 3) or (3,), ``eta`` (T,) or scalar; ``pairs`` (m, 2) candidate (caster, receiver)
    pairs (default all).  Returns (tuples (m, 2), piece_start (m+1,), pieces, report) as
    ``cull.one_bounce_bounds``."""
    t0 = time.perf_counter()
    s = dict(BOUNDS_SETTINGS, **(settings or {}))
    T = tri_p.shape[0]
    x0 = _points(x0, T)
    eta = np.array(np.broadcast_to(np.asarray(eta, dtype=np.float64), (T,)))  # writeable: one kernel signature
    P = np.ascontiguousarray(tri_p, dtype=np.float64)
    N = np.ascontiguousarray(tri_n, dtype=np.float64)
    Q = np.ascontiguousarray(rec_p, dtype=np.float64)
    UV = np.ascontiguousarray(rec_uv, dtype=np.float64)
    if pairs is None:
        ci, ri = np.meshgrid(np.arange(T), np.arange(Q.shape[0]), indexing="ij")
        pairs = np.stack([ci.ravel(), ri.ravel()], axis=1)
    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    capacity = max(1, min(64, 4 ** int(s["max_depth"])))
    tuples, pieces_all, counts_all = [], [], []
    for e in np.unique(eta[pairs[:, 0]]) if pairs.shape[0] else []:
        sel = pairs[eta[pairs[:, 0]] == e]
        step = max(1, ROW_BUDGET // (capacity * PIECE_FIELDS))
        for a in range(0, sel.shape[0], step):
            pr = np.ascontiguousarray(sel[a:a + step])
            n = pr.shape[0]
            out = np.empty((n, capacity, PIECE_FIELDS))
            counts = np.zeros(n, dtype=np.int64)
            stats = np.zeros((n, 4), dtype=np.int64)
            one_bounce_batch(chain == "T", x0, P, N, Q, UV, float(e), pr, int(s["max_depth"]), float(s["sigma"]),
                             float(s["alpha"]), bool(irradiance), int(irr_refine), out, counts, stats, 32)
            keep = np.flatnonzero(counts > 0)
            kc = counts[keep]
            owner = np.repeat(keep, kc)
            slot = np.arange(owner.shape[0]) - np.repeat(np.cumsum(kc) - kc, kc)
            tuples.append(pr[keep])
            pieces_all.append(out[owner, slot])
            counts_all.append(kc)
    tuples = np.concatenate(tuples) if tuples else np.zeros((0, 2), dtype=np.int64)
    pieces = np.ascontiguousarray(np.concatenate(pieces_all)) if pieces_all else np.zeros((0, PIECE_FIELDS))
    counts = np.concatenate(counts_all) if counts_all else np.zeros(0, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    report = {"pairs": int(pairs.shape[0]), "tuples": int(tuples.shape[0]), "pieces": int(pieces.shape[0]),
              "seconds": time.perf_counter() - t0}
    return np.ascontiguousarray(tuples, dtype=np.int64), start, pieces, report


def bvh_pairs(chain, x0_first, P, N, eta_first, first, levels=1, refine=2, capacity=64):
    """The (t1, t2) pairs of §6.1 "Tuple construction" (``tuples.two_bounce_pairs``: BVH over
    ``P``, bounds of x1 and d̃1 per box of t1, eq 9–10 in affine arithmetic) with a light point
    x0_first[i] and IOR eta_first[i] per first triangle first[i].  Returns (m, 2) int64 sorted."""
    first = np.ascontiguousarray(first, dtype=np.int64)
    if first.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs, _ = two_bounce_pairs(chain, _points(x0_first, first.shape[0]), P, N, eta=eta_first, levels=levels, first=first,
                                capacity=capacity, refine=refine)
    return pairs.astype(np.int64)


def two_bounce_bounds_points(chain, x0, P, N, eta, pairs, rec_p, rec_uv, mask=None, settings=None):
    """Position bounds of two-bounce tuples (pair, receiver triangle) with a light point and an
    IOR per pair (Fan et al. 2025 §4.3, eq 3–13 with remainder variables; §6.1 subdivision), as
    ``two_bounce.bound_two_bounce`` and ``two_bounce_irradiance.receivers_reached``
    (depth ``reach_depth``) before it; then, with ``prune``, the irradiance pass (eq 14–16) drops
    the pieces it proves to hold no path and fills Ē, E̲.

    ``P``, ``N``: (n,3,3) casters (both vertices index them); ``pairs`` (t, 2); ``x0`` (t, 3)
    or (3,); ``eta`` (t,) or scalar; ``rec_p`` (r,3,3), ``rec_uv`` (r,3,2); ``mask``: the
    (pair, receiver) tuples to bound, (t, r) bool or (k, 2) int (pair, receiver) rows (default
    all; the others get no piece).
    Returns (tuples (m, 2) (pair index, receiver index), piece_start (m+1,), pieces
    (p, PIECE_FIELDS), report)."""
    t_start = time.perf_counter()
    s = dict(TWO_BOUNCE_SETTINGS, **(settings or {}))
    code = CHAIN_CODES[chain]
    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    n = pairs.shape[0]
    x0 = _points(x0, n)
    eta = np.array(np.broadcast_to(np.asarray(eta, dtype=np.float64), (n,)))
    P = np.ascontiguousarray(P, dtype=np.float64)
    N = np.ascontiguousarray(N, dtype=np.float64)
    Q = np.ascontiguousarray(rec_p, dtype=np.float64)
    UV = np.ascontiguousarray(rec_uv, dtype=np.float64)
    nr = Q.shape[0]
    if mask is not None and mask.dtype != np.bool_:  # sparse (pair, receiver) rows
        rows_of = np.asarray(mask, dtype=np.int64).reshape(-1, 2)
        rows_of = rows_of[np.argsort(rows_of[:, 0], kind="stable")]
        at = np.searchsorted(rows_of[:, 0], np.arange(n + 1))
    else:
        rows_of = None
    cells = 1 << int(s["reach_depth"])
    depth = int(s["max_depth"])
    capacity = max(1, min(int(s["capacity"]), 4 ** depth))
    n_mask = n * nr if mask is None else (rows_of.shape[0] if rows_of is not None else int(np.count_nonzero(mask)))
    rep = {"pairs": int(n), "receivers": int(nr), "cone_tuples": int(n_mask), "reach_tuples": 0, "box_evaluations": 0,
           "capacity_stops": 0, "seconds": {"reach": 0.0, "bound": 0.0, "irradiance": 0.0}}
    step = max(1, ROW_BUDGET // max(1, nr * cells * cells))
    tup, pcs, cnts = [], [], []
    for a in range(0, n, step):
        b = min(n, a + step)
        m = b - a
        pr = np.ascontiguousarray(pairs[a:b])
        xs = np.ascontiguousarray(x0[a:b])
        es = np.ascontiguousarray(eta[a:b])
        t0 = time.perf_counter()
        if mask is None:
            mk = np.ones((m, nr), dtype=np.bool_)
        elif rows_of is not None:
            mk = np.zeros((m, nr), dtype=np.bool_)
            sub = rows_of[at[a]:at[b]]
            mk[sub[:, 0] - a, sub[:, 1]] = True
        else:
            mk = np.ascontiguousarray(mask[a:b], dtype=np.bool_)
        reach = np.zeros((m, nr, cells, cells), dtype=np.bool_)
        if m and nr:
            run_chunks(reach_chunk, (code, xs, P, N, Q, es, pr, mk, reach), m, 256)
        alive = reach.any(axis=(2, 3))
        n_alive = alive.sum(axis=1).astype(np.int64)
        rep["reach_tuples"] += int(n_alive.sum())
        t1 = time.perf_counter()
        rep["seconds"]["reach"] += t1 - t0
        row_start = np.concatenate([[0], np.cumsum(capacity * n_alive)]).astype(np.int64)
        rows = np.empty((int(row_start[-1]), PIECE_FIELDS + 1))
        counts = np.zeros(m, dtype=np.int64)
        stats = np.zeros((m, 4), dtype=np.int64)
        if row_start[-1]:
            run_chunks(pair_pieces_chunk, (code, xs, P, N, Q, UV, es, pr, reach, n_alive, row_start, depth, float(s["sigma"]), rows,
                                    counts, stats), m, 256)
        rep["box_evaluations"] += int(stats[:, 0].sum())
        rep["capacity_stops"] += int(stats[:, 3].sum())
        rep["seconds"]["bound"] += time.perf_counter() - t1
        owner = np.repeat(np.arange(m), counts)
        slot = np.arange(owner.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
        rws = rows[row_start[owner] + slot]
        receiver = rws[:, P_RECEIVER].astype(np.int64)
        pieces = np.ascontiguousarray(rws[:, :PIECE_FIELDS])
        if s["prune"] and pieces.shape[0]:
            t2 = time.perf_counter()
            pp = np.ascontiguousarray(pr[owner])
            istats = np.zeros((pieces.shape[0], 6), dtype=np.int64)
            run_chunks(irradiance_chunk, (code, np.ascontiguousarray(xs[owner]), P, N, Q, np.ascontiguousarray(es[owner]), pp,
                                    np.ascontiguousarray(receiver), pieces, int(s["irr_depth"]), float(s["irr_ratio"]), istats),
                       pieces.shape[0], 256)
            keep = ~((pieces[:, P_EHI] == 0.0) & (pieces[:, P_ELO] == 0.0))
            owner, receiver, pieces = owner[keep], receiver[keep], np.ascontiguousarray(pieces[keep])
            rep["seconds"]["irradiance"] += time.perf_counter() - t2
        split = int(s["image_split"])
        if split > 1 and pieces.shape[0]:
            t3 = time.perf_counter()
            k = split * split
            srows = np.empty((pieces.shape[0] * k, PIECE_FIELDS))
            scount = np.zeros(pieces.shape[0], dtype=np.int64)
            run_chunks(split_pieces_chunk, (code, xs, P, N, Q, UV, es, pr, np.ascontiguousarray(owner), np.ascontiguousarray(receiver),
                                      pieces, split, srows, scount), pieces.shape[0], 256)
            within = np.arange(int(scount.sum())) - np.repeat(np.cumsum(scount) - scount, scount)
            idx = np.repeat(np.arange(pieces.shape[0]) * k, scount) + within
            owner, receiver, pieces = np.repeat(owner, scount), np.repeat(receiver, scount), np.ascontiguousarray(srows[idx])
            rep["seconds"]["split"] = rep["seconds"].get("split", 0.0) + time.perf_counter() - t3
        order = np.lexsort((receiver, owner))
        owner, receiver, pieces = owner[order] + a, receiver[order], pieces[order]
        key = owner * max(nr, 1) + receiver
        new = np.ones(key.shape[0], dtype=bool)
        new[1:] = key[1:] != key[:-1]
        st = np.flatnonzero(new)
        tup.append(np.stack([owner[st], receiver[st]], axis=1))
        pcs.append(pieces)
        cnts.append(np.diff(np.append(st, key.shape[0])))
    tuples = np.concatenate(tup) if tup else np.zeros((0, 2), dtype=np.int64)
    pieces = np.ascontiguousarray(np.concatenate(pcs)) if pcs else np.zeros((0, PIECE_FIELDS))
    counts = np.concatenate(cnts) if cnts else np.zeros(0, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    rep.update({"tuples": int(tuples.shape[0]), "pieces": int(pieces.shape[0])})
    rep["seconds"]["total"] = time.perf_counter() - t_start
    return np.ascontiguousarray(tuples, dtype=np.int64), start, pieces, rep


def parallel_scale(pieces, start, first_p, x0):
    """Ē, E̲ of pieces for a parallel light (the sun) stood in for by far points x0 (lights.light_points:
    intensity S |x1 - x0|² per path, where the bounds take I0 = 1, eq 14): Ē times the largest
    |x1 - x0|² over the first triangle (its corners), E̲ times the smallest (the distance to its
    bounding sphere).  ``start`` (m+1,) the pieces of tuple t, ``first_p`` (m,3,3) and ``x0``
    (m,3) its first triangle and light point.  In place; returns ``pieces``."""
    if pieces.shape[0] == 0:
        return pieces
    d = np.linalg.norm(first_p - x0[:, None, :], axis=2)
    c, r = tri_spheres(first_p)
    hi = np.max(d, axis=1) ** 2
    lo = np.maximum(0.0, np.linalg.norm(c - x0, axis=1) - r) ** 2
    n = np.diff(start)
    pieces[:, P_EHI] *= np.repeat(hi, n)
    pieces[:, P_ELO] *= np.repeat(lo, n)
    return pieces


def _union(tri_of):
    """Local ids of the triangles of ``tri_of`` (n, k): (global ids (u,), local (n, k))."""
    ids, inv = np.unique(tri_of.ravel(), return_inverse=True)
    return ids, inv.reshape(tri_of.shape).astype(np.int64)


def emitter_bounds_two(chain, emitters, tri_of, x0_of, scene_p, scene_n, scene_ior, rec_p, rec_uv, settings=None):
    """Two-bounce bounds of the cone emitters (``cull.two_bounce_emitters``; ``tri_of`` (n, 2)
    global ids, ``x0_of`` (n, 3) the light point of each) against the receiver triangles
    ``rec_p`` / ``rec_uv``: the emitter pairs that §6.1's BVH pair search also finds, the
    (emitter, receiver triangle) tuples that the cone test admits, bounded by
    :func:`two_bounce_bounds_points`.  Returns (tuples (m, 2) (emitter index, receiver index),
    piece_start, pieces, report)."""
    t0 = time.perf_counter()
    s = dict(TWO_BOUNCE_SETTINGS, **(settings or {}))
    ids, loc = _union(tri_of)
    P = np.ascontiguousarray(scene_p[ids], dtype=np.float64)
    N = np.ascontiguousarray(scene_n[ids], dtype=np.float64)
    eta_e = np.asarray(scene_ior, dtype=np.float64)[tri_of[:, 0]]
    # §6.1 pairs (per first triangle: its light point, its IOR)
    first, at = np.unique(loc[:, 0], return_index=True)
    bp = bvh_pairs(chain, x0_of[at], P, N, eta_e[at], first, levels=s["levels"], refine=s["refine"])
    nu = max(1, ids.shape[0])
    in_bvh = np.isin(loc[:, 0] * nu + loc[:, 1], bp[:, 0] * nu + bp[:, 1])
    sel = np.flatnonzero(in_bvh)
    t1 = time.perf_counter()
    # cone test per (emitter, receiver triangle), as sparse (row of sel, receiver) rows
    cp = _cone_pairs(emitters, rec_p)
    row_of = np.full(emitters.size, -1, dtype=np.int64)
    has = np.zeros(emitters.size, dtype=bool)
    has[cp[:, 0]] = True
    sel = sel[has[sel]]
    row_of[sel] = np.arange(sel.size)
    cp = cp[row_of[cp[:, 0]] >= 0]
    t2 = time.perf_counter()
    tuples, start, pieces, rep = two_bounce_bounds_points(chain, x0_of[sel], P, N, eta_e[sel], loc[sel], rec_p, rec_uv,
                                                          mask=np.column_stack([row_of[cp[:, 0]], cp[:, 1]]), settings=s)
    tuples = tuples.copy()
    tuples[:, 0] = sel[tuples[:, 0]]
    rep = dict(rep, emitters=int(emitters.size), bvh_pairs=int(bp.shape[0]), emitters_in_bvh_pairs=int(in_bvh.sum()),
               emitters_bounded=int(sel.size))
    rep["seconds"] = dict(rep["seconds"], pairs=t1 - t0, cone=t2 - t1, all=time.perf_counter() - t0)
    return tuples, start, pieces, rep


class TwoBounceBoundsCull(PieceCull):
    """Candidate (emitter, sample) tuples of a two-bounce chain (RR, RT, TR, TT) from the
    two-bounce Bernstein position bounds (module doc; Fan et al. 2025 §4.3, eq 3–13, §6.1),
    with the interface of :class:`addon.bake.cull.TupleCull` / :class:`addon.bake.cull.BoundsCull`:
    ``upper_bound`` and ``batches(max_tuples)`` -> (emitter index, sample index, 1/P or None).

    ``emitters``: the chain's :class:`addon.bake.cull.Emitters` (``two_bounce_emitters``; their
    cones are the per-sample test as well); ``tri_of`` (n, 2) their global (t1, t2) ids;
    ``x0_of`` (n, 3) their light points (one point, or the sun's far point per t1);
    ``scene_p/scene_n/scene_ior`` the scene's triangles; ``rec_tri`` (r,) the receiver's global
    triangle ids, ``rec_uv`` (r,3,2); ``band`` a :class:`addon.bake.raster.SampleBand` of a
    ``width`` x ``height`` texture.  ``gamma`` < inf: P = min(γ Ẽ, 1) with Ẽ from the
    irradiance pass (eq 21, 28; needs ``settings["prune"]``, else Ē = inf and P = 1).  ``cache``:
    a dict keeping the bounds of this (light point, receiver) across bands.
    ``parallel``: the light points stand for the sun (:func:`parallel_scale`).
    Where the bounds do not apply path-points falls back to the cone cull (module doc).
    """

    def __init__(self, chain, emitters, tri_of, x0_of, scene_p, scene_n, scene_ior, rec_tri, rec_uv, band, width, height,
                 gamma=math.inf, intensity=1.0, rng=None, cache=None, settings=None, parallel=False):
        t0 = time.perf_counter()
        key = "bounds2"
        if cache is not None and key in cache:
            tuples, start, pieces, report = cache[key]
        else:
            tuples, start, pieces, report = emitter_bounds_two(chain, emitters, tri_of, x0_of, scene_p, scene_n, scene_ior,
                                                                scene_p[rec_tri], rec_uv, settings=settings)
            if parallel:
                parallel_scale(pieces, start, scene_p[tri_of[tuples[:, 0], 0]], x0_of[tuples[:, 0]])
            if cache is not None:
                cache[key] = (tuples, start, pieces, report)
        self.report = report
        self.bounds_seconds = time.perf_counter() - t0
        self._prepare(tuples, start, pieces, emitters, rec_tri, band, width, height, gamma, intensity, rng)


def bounds_cull(scene, settings, chain, ls, m, em, tri_of, x0_of, band, W, rec):
    """The bounds-driven selection of one chain, light sample and band for path-points
    (``BakeSettings.cull == "bounds"``): :class:`addon.bake.cull.BoundsCull` for R and T (one
    light point, or a point per caster: the sun), :class:`TwoBounceBoundsCull` for RR, RT, TR,
    TT; None (path-points' cone cull) where they do not apply.  The bounds are cached per
    receiver on the chain's emitters (shared by every band)."""

    if rec is None or em.size == 0 or chain not in ("R", "T", "RR", "RT", "TR", "TT"):
        return None
    cache = em.extra.setdefault(("bounds", rec.name, rec.resolution), {})
    H = rec.resolution[1]
    kinds = ("R", "T", "RR", "RT", "TR", "TT")
    rng = np.random.default_rng([int(settings.seed) & 0x7FFFFFFF, m, kinds.index(chain), band.row0])
    intensity = float(np.max(ls.rgb[m]))
    sun = ls.kind == "sun"
    if len(chain) == 1:
        tri = tri_of[:, 0]
        return BoundsCull(chain, em, x0_of, scene.tri_p[tri], scene.tri_n[tri], scene.tri_ior[tri], scene.tri_p[rec.tri_index],
                          rec.tri_index, rec.uv, band, W, H, gamma=settings.gamma, intensity=intensity, rng=rng, cache=cache,
                          parallel=sun)
    return TwoBounceBoundsCull(chain, em, tri_of, x0_of, scene.tri_p, scene.tri_n, scene.tri_ior, rec.tri_index, rec.uv, band, W,
                               H, gamma=settings.gamma, intensity=intensity, rng=rng, cache=cache, parallel=sun)


# ---------------------------------------------------------------------------------------
# forward flux: which first-vertex casters can light a receiver at all


def reachable_first(chain, x0, tri_p1, tri_n1, eta1, rec_p, tri_p2=None, tri_n2=None, eta2=None, ids1=None, ids2=None,
                    use_bounds=True, settings=None):
    """Mask (T1,) of the first-vertex caster triangles from which light of ``x0`` can reach a
    receiver triangle through ``chain`` (conservative: a triangle with a path is never dropped).

    ``x0`` (3,) or (T1, 3) (the sun's far point per triangle); ``tri_p1, tri_n1, eta1`` the
    first-vertex casters (corners, corner normals, IOR behind the surface: (T1,) or scalar);
    ``rec_p`` (r, 3, 3) the receivers' triangles; for two-vertex chains ``tri_p2, tri_n2, eta2``
    the second-vertex casters and ``ids1`` / ``ids2`` global ids of both sets (a triangle is
    never its own second vertex; default: the sets are disjoint; ids1 must be distinct).  Pure:
    numpy in, numpy out.

    One bounce: the cone caps of ``cull.py`` per (triangle, receiver triangle) (its sphere as a
    tile), then the Bernstein position bound of ``one_bounce`` (Fan et al. 2025 §4.2–4.3, eq 3–13; the
    quadtree of §6.1 to ``max_depth`` 2 with σ = 0: a triangle stays when some piece's bound
    meets a receiver triangle).  Two bounces: the BVH pairs of §6.1 "Tuple construction"
    (bounds of x1 and d̃1, eq 9–10 in affine arithmetic), the reach grid of
    ``two_bounce_irradiance.receivers_reached`` per (pair, receiver triangle) and the position quadtree
    of §4.3 (eq 3–13, ``max_depth`` 1): a triangle stays when one of its pairs has a piece (no
    cone pairs: ``two_bounce_emitters`` costs O(T1 T2)).  ``use_bounds=False``: the cone tests
    of ``cull.py`` alone (one bounce: caps per (triangle, receiver triangle); two: the pairs of
    ``two_bounce_emitters`` with their parts, then the same per receiver triangle), the
    equivalent conservative test where the bound engines do not apply."""
    T1 = tri_p1.shape[0]
    keep = np.zeros(T1, dtype=bool)
    if T1 == 0 or rec_p.shape[0] == 0:
        return keep
    tri_p1 = np.ascontiguousarray(tri_p1, dtype=np.float64)
    tri_n1 = np.ascontiguousarray(tri_n1, dtype=np.float64)
    rec_p = np.ascontiguousarray(rec_p, dtype=np.float64)
    x0 = _points(x0, T1)
    eta1 = np.array(np.broadcast_to(np.asarray(eta1, dtype=np.float64), (T1,)))
    rec_uv = np.zeros((rec_p.shape[0], 3, 2))
    rec_uv[:, 1, 0] = 1.0
    rec_uv[:, 2, 1] = 1.0  # UV = barycentrics: only the receiver-barycentric bound matters here
    if len(chain) == 1:
        em = one_bounce_emitters(chain, x0, tri_p1, tri_n1, eta1)
        cp = _cone_pairs(em, rec_p)
        if not use_bounds or cp.shape[0] == 0:
            keep[cp[:, 0]] = True
            return keep
        s = {"max_depth": 2, "sigma": 0.0, "alpha": 2.0, **(settings or {})}
        tuples, _, _, _ = one_bounce_bounds_points(chain, x0, tri_p1, tri_n1, eta1, rec_p, rec_uv, pairs=cp, settings=s)
        keep[tuples[:, 0]] = True
        return keep
    T2 = tri_p2.shape[0]
    tri_p2 = np.ascontiguousarray(tri_p2, dtype=np.float64)
    tri_n2 = np.ascontiguousarray(tri_n2, dtype=np.float64)
    eta2 = np.array(np.broadcast_to(np.asarray(eta2 if eta2 is not None else eta1[:1], dtype=np.float64), (T2,)))
    if ids1 is None:
        ids1, ids2 = np.arange(T1), T1 + np.arange(T2)
    ids1, ids2 = np.asarray(ids1), np.asarray(ids2)
    if not use_bounds:
        em = two_bounce_emitters(chain, x0, tri_p1, tri_n1, eta1, tri_p2, tri_n2, eta2, ids1=ids1, ids2=ids2)
        if em.size:
            cp = _cone_pairs(em, rec_p)
            keep[em.index[cp[:, 0], 0]] = True
        return keep
    # one array over both sets (global ids -> rows): the BVH pair search of §6.1 over it, then the
    # pairs whose second triangle is a second-vertex caster with the first's IOR
    ids, first_row = np.unique(np.concatenate([ids1, ids2]), return_index=True)
    allP = np.ascontiguousarray(np.concatenate([tri_p1, tri_p2])[first_row])
    allN = np.ascontiguousarray(np.concatenate([tri_n1, tri_n2])[first_row])
    allE = np.concatenate([eta1, eta2])[first_row]
    row1 = np.searchsorted(ids, ids1)
    second = np.zeros(ids.size, dtype=bool)
    second[np.searchsorted(ids, ids2)] = True
    pairs = bvh_pairs(chain, x0, allP, allN, eta1, row1, levels=TWO_BOUNCE_SETTINGS["levels"], refine=TWO_BOUNCE_SETTINGS["refine"])
    pairs = pairs[second[pairs[:, 1]] & (allE[pairs[:, 1]] == allE[pairs[:, 0]])]
    if pairs.shape[0] == 0:
        return keep
    first_of = np.full(ids.size, -1, dtype=np.int64)
    first_of[row1] = np.arange(T1)
    t1 = first_of[pairs[:, 0]]
    s = {**TWO_BOUNCE_SETTINGS, "max_depth": 1, "sigma": 0.0, "prune": False, "image_split": 1, **(settings or {})}
    tuples, _, _, _ = two_bounce_bounds_points(chain, x0[t1], allP, allN, eta1[t1], pairs, rec_p, rec_uv, settings=s)
    keep[t1[tuples[:, 0]]] = True
    return keep
