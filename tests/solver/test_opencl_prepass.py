"""The OpenCL live pre-pass (addon/solver/opencl/prepass.cl) computes what the Numba functions of
addon/solver/spoly/two_bounce/prepass.py (and sqrt.beta_mask) compute, bit for bit.

prepass.cl is a library of static functions (no kernel); this test builds it, with the
two-bounce tables, build options and biv.cl, into a test-only program with a kernel of its own
(one work-item per system) and compares, system by system, on real systems: stage A of
two_bounce/staged.py (``_stage_a_oriented``'s loop, replayed here in Python with the Numba
kernels: ``tuple_frame``, ``sqrt_pieces_to_solve``, ``build_system``, ``_prepare_system``,
``sqrt_band``) for planted and random tuples of the four chains, forward and reversed.  For each
system to solve (status 1) its bivariate scratch is snapshot (every slot: a, b, the map to
triangle 2, β and the leftovers of the construction) and both back ends run on their own copy:
``live_pieces_band`` (the live pieces and their count), ``box_range`` on random boxes of a, b,
β and the hit polynomials (the small-degree register path of Numba against the general path of
the port), ``beta_mask`` (systems refracting at vertex 1) and ``tensor_bernstein_box``.  PoCL on
the CPU in CI; skipped without a device.
"""

import math

import numpy as np
import pytest

from addon.solver.polynomials.bivariate import bmax
from addon.solver.spoly.two_bounce import params, prepass, sqrt, staged, system
from fixtures.opencl import library_program, opencl_device_or_skip
from fixtures.stage_a_replay import oriented_systems
from workloads import planted_two_bounce, random_two_bounce

CHAINS = ("RR", "RT", "TR", "TT")
ETA = 1.5
N_PLANTED = 20  # planted tuples per chain
N_RANDOM = 150  # random tuples per chain (many have no system: the side tests)
MAX_SYSTEMS = 60  # status-1 systems kept per chain and kind (planted / random)
PIECES = 100
N_BOX = 8  # random boxes per system for box_range
BATCH = 32  # systems per launch (1 MB of scratch each)
NB = params.MAXD + 1

TEST_KERNELS = r"""
// per system g: its biv (a copy of the snapshot), then
//   live pieces and their count (pp_live_pieces_band), biv right after it (after_all),
//   box_range on N_BOX boxes (src, d, u0, v0, w) -> (lo, hi),
//   beta_mask (when refract1),
//   tensor_bernstein_box of slot tb_src (degree tb_d) on (tb_u0, tb_v0, tb_w) -> its square
__kernel void pp_test_systems(__global double *biv_all, __global const int *ipar, __global const double *dpar,
                              __global const int *box_i, __global const double *box_d, __global char *live_all,
                              __global int *iout, __global double *box_out, __global double *tb_out,
                              __global double *after_all) {
    int g = get_global_id(0);
    __global double *biv = biv_all + (long)g * N_SLOTS * BIV_SLOT_SIZE;
    __global const int *ip = ipar + 8 * g;
    __global const double *dp = dpar + 8 * g;
    int da = ip[0], db = ip[1], pieces = ip[2], refract1 = ip[3], tb_src = ip[4], tb_d = ip[5];
    double margin = dp[0], blo = dp[1], bhi = dp[2], S2 = dp[3];
    __global char *live = live_all + (long)g * pieces;
    iout[2 * g] = pp_live_pieces_band(SLOT(biv, 0), da, SLOT(biv, 1), db, margin, pieces, biv, live, blo, bhi);
    __global double *after = after_all + (long)g * N_SLOTS * BIV_SLOT_SIZE;
    for (long q = 0; q < (long)N_SLOTS * BIV_SLOT_SIZE; ++q) after[q] = biv[q];
    for (int q = 0; q < @N_BOX@; ++q) {
        double lo, hi;
        int c = g * @N_BOX@ + q;
        pp_box_range(biv, box_i[2 * c], box_i[2 * c + 1], box_d[3 * c], box_d[3 * c + 1], box_d[3 * c + 2], &lo, &hi);
        box_out[2 * c] = lo;
        box_out[2 * c + 1] = hi;
    }
    iout[2 * g + 1] = refract1 ? pp_beta_mask(biv, V_MARGIN_APPROX, S2) : 0;
    __global double *R = SLOT(biv, 40), *out = SLOT(biv, 41);
    pp_binomial_ratios(tb_d, R);
    pp_tensor_bernstein_box(SLOT(biv, tb_src), tb_d, dp[4], dp[5], dp[6], R, out, SLOT(biv, 42), SLOT(biv, 43));
    __global double *tb = tb_out + (long)g * BIV_SLOT_SIZE;
    for (int i = 0; i < BIV_N; ++i)
        for (int j = 0; j < BIV_N; ++j) AT(tb, i, j) = i <= tb_d && j <= tb_d ? AT(out, i, j) : 0.0;
}
"""


def _program(index):
    return library_program(index, ("biv.cl", "prepass.cl"), TEST_KERNELS.replace("@N_BOX@", str(N_BOX)))


def _oriented_systems(refract1, refract2, x0, x3, PA, NA, PB, NB_, eta, rng):
    """``staged._stage_a_oriented``'s loop for one orientation: yields one record per system
    with status 1 (the biv snapshot right before the pre-pass and its arguments)."""
    biv = np.zeros((params.N_SLOTS, NB, NB))
    geo = np.zeros((15, 3))
    geo_l = np.zeros((15, 3))
    stats = np.zeros(params.N_STATS, np.int64)
    x0 = (float(x0[0]), float(x0[1]), float(x0[2]))
    x3 = (float(x3[0]), float(x3[1]), float(x3[2]))
    for q in oriented_systems(refract1, refract2, x0, x3, PA, NA, PB, NB_, eta, biv, geo, geo_l, stats):
        da, db = system.build_system(refract1, refract2, q.s_in1, q.r1, q.piece, q.S, q.heron, q.eta_in2, q.eta_out2,
                                     q.flat2, q.c2, geo_l, biv)
        status, na, nb, n = staged._prepare_system(biv, da, db, refract1, stats)
        if status != 1:
            continue
        blo, bhi = sqrt.sqrt_band(q.piece, q.S * q.S, refract1)
        yield _record(biv, int(da), int(db), bool(refract1), float(blo), float(bhi), float(q.S * q.S), rng)


def _record(biv, da, db, refract1, blo, bhi, S2, rng):
    """The system's snapshot and the cases run on it: the pre-pass's arguments, N_BOX random
    boxes for box_range (a, b, β, the hit polynomials: degrees up to 46 and the small ones of
    Numba's register path) and one tensor_bernstein_box."""
    dk = int(biv[params.HIT_SLOT, params.MAXD, 0])
    srcs = [(0, da), (1, db), (params.BETA_SLOT, 4), (0, int(rng.integers(0, min(da, 7) + 1))),
            (1, int(rng.integers(0, min(db, 12) + 1)))]
    if dk > 0:
        srcs += [(params.HIT_SLOT, dk), (params.HIT_SLOT + 1, dk + 1), (params.HIT_SLOT + 3, 1)]
    box_i = np.zeros((N_BOX, 2), np.int32)
    box_d = np.zeros((N_BOX, 3))
    for q in range(N_BOX):
        box_i[q] = srcs[q % len(srcs)]
        w = 10.0 ** rng.uniform(-3.0, 0.1)
        box_d[q] = rng.uniform(-0.05, 1.0, size=2).tolist() + [w]
    tb_src = int(rng.integers(0, 2))  # a or b
    tb_d = da if tb_src == 0 else db
    tb_box = (float(rng.uniform(-0.1, 0.9)), float(rng.uniform(-0.1, 0.9)), float(10.0 ** rng.uniform(-2.0, 0.0)))
    margin = params.V_MARGIN_APPROX if refract1 else params.V_MARGIN_EXACT
    return dict(biv=biv.copy(), da=da, db=db, refract1=refract1, blo=blo, bhi=bhi, S2=S2, margin=margin, box_i=box_i,
                box_d=box_d, tb_src=tb_src, tb_d=tb_d, tb_box=tb_box)


def _systems():
    """(chain, kind, record) for planted and random tuples of each chain, both orientations
    (forward, and reversed as _stage_a_tuple's BOTH_DIRECTIONS), at most MAX_SYSTEMS per chain
    and kind."""
    rng = np.random.default_rng(20260529)
    for k, chain in enumerate(CHAINS):
        r1, r2 = chain[0] == "T", chain[1] == "T"
        planted = planted_two_bounce(8 * N_PLANTED, chain, eta=ETA, seed=70 + k)[:4]
        randoms = random_two_bounce(N_RANDOM, seed=80 + k)
        for kind, (x0, x3, P, N) in (("planted", planted), ("random", randoms)):
            count = 0
            m = N_PLANTED if kind == "planted" else N_RANDOM
            for t in range(min(m, x0.shape[0])):
                if count >= MAX_SYSTEMS:
                    break
                for rev in (False, True):
                    if not rev:
                        args = (r1, r2, x0[t], x3[t], P[t, 0], N[t, 0], P[t, 1], N[t, 1])
                    else:
                        args = (r2, r1, x3[t], x0[t], P[t, 1], N[t, 1], P[t, 0], N[t, 0])
                    for rec in _oriented_systems(*args, ETA, rng):
                        if count >= MAX_SYSTEMS:
                            break
                        rec["rev"] = rev
                        count += 1
                        yield chain, kind, rec


def _whole_square_miss(rec):
    """Whether the pre-pass's first test (``misses_second`` on the whole square, its tolerances)
    drops the system (Numba; for the counts only)."""
    biv = rec["biv"].copy()
    dk = int(biv[params.HIT_SLOT, params.MAXD, 0])
    if not (params.HIT_TEST and dk > 0):
        return False
    mk = bmax(biv[params.HIT_SLOT], dk)
    mu = bmax(biv[params.HIT_SLOT + 1], dk + 1) + bmax(biv[params.HIT_SLOT + 2], dk + 1)
    mt = bmax(biv[params.HIT_SLOT + 3], 1)
    tol = np.array([1e-11 * mk, 1e-11 * (mu + mk), 1e-11 * (mu + 2.0 * mk), 1e-11 * mt])
    m = rec["margin"]
    return bool(prepass.misses_second(biv, -m, -m, 1.0 + 2.0 * m, tol))


def _run_numba(rec):
    """live (PIECES,), n_live, biv after the pre-pass, box ranges (N_BOX, 2), beta mask,
    tensor Bernstein square."""
    biv = rec["biv"].copy()
    boxes = np.zeros((params.LIVE_STACK, 4))
    live = np.zeros(PIECES)
    n_live = prepass.live_pieces_band(biv[0], rec["da"], biv[1], rec["db"], rec["margin"], PIECES, biv, boxes, live,
                                      rec["blo"], rec["bhi"])
    after = biv.copy()
    ranges = np.zeros((N_BOX, 2))
    for q in range(N_BOX):
        src, d = (int(x) for x in rec["box_i"][q])
        ranges[q] = prepass.box_range(biv, src, d, *(float(x) for x in rec["box_d"][q]))
    mask = int(sqrt.beta_mask(biv, params.V_MARGIN_APPROX, rec["S2"])) if rec["refract1"] else 0
    R = np.zeros((NB, NB))
    out = np.zeros((NB, NB))
    d = rec["tb_d"]
    prepass.binomial_ratios(d, R)
    prepass.tensor_bernstein_box(biv[rec["tb_src"]], d, *rec["tb_box"], R, out, np.zeros((NB, NB)), np.zeros((NB, NB)))
    tb = np.zeros((NB, NB))
    tb[:d + 1, :d + 1] = out[:d + 1, :d + 1]
    return live.astype(np.int8), int(n_live), after, ranges, mask, tb


def _run_opencl(d, prg, recs):
    cl = d.cl
    n = len(recs)
    mf = cl.mem_flags
    biv_all = np.ascontiguousarray(np.stack([r["biv"] for r in recs]))
    ipar = np.zeros((n, 8), np.int32)
    dpar = np.zeros((n, 8))
    for g, r in enumerate(recs):
        ipar[g, :6] = (r["da"], r["db"], PIECES, int(r["refract1"]), r["tb_src"], r["tb_d"])
        dpar[g, :7] = (r["margin"], r["blo"], r["bhi"], r["S2"]) + r["tb_box"]
    box_i = np.ascontiguousarray(np.stack([r["box_i"] for r in recs]), dtype=np.int32)
    box_d = np.ascontiguousarray(np.stack([r["box_d"] for r in recs]))
    live = np.zeros((n, PIECES), np.int8)
    iout = np.zeros((n, 2), np.int32)
    box_out = np.zeros((n, N_BOX, 2))
    tb_out = np.zeros((n, NB, NB))
    after = np.zeros_like(biv_all)
    biv_buf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=biv_all)
    inputs = [cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in (ipar, dpar, box_i, box_d)]
    outs = [cl.Buffer(d.ctx, mf.WRITE_ONLY, a.nbytes) for a in (live, iout, box_out, tb_out, after)]
    queue = cl.CommandQueue(d.ctx)
    d.cl.Kernel(prg, "pp_test_systems")(queue, (n,), None, biv_buf, *inputs, *outs)
    for a, buf in zip((live, iout, box_out, tb_out, after), outs):
        cl.enqueue_copy(queue, a, buf)
    queue.finish()
    return live, iout, box_out, tb_out, after


def _bits(x):
    return np.ascontiguousarray(x, dtype=np.float64).view(np.int64)


def _scratch_regions(rec):
    """(slot, degree, triangle) of the pre-pass's scratch whose bits are determined by its
    path through the quadtree (the same on both back ends when the path is): the box stack
    (a's and b's tensor Bernstein forms of the last boxes there, degree da / db), the u halves
    of the last splits (41, 42: a; 43, 44: b), the weights of degree db (40) and the hit test's
    last polynomial (HIT_SLOT + 4, the triangle of total degree dk + 1); the square of the
    degree [0, d]^2 otherwise.  Elsewhere (columns beyond the degree,
    the transposes' scratch) Numba's whole-vector operations leave values that are never read."""
    da, db = rec["da"], rec["db"]
    out = []
    for t in range(params.LIVE_STACK):
        out.append((params.LIVE_SLOT0 + 2 * t, da, False))
        out.append((params.LIVE_SLOT0 + 2 * t + 1, db, False))
    out += [(41, da, False), (42, da, False), (43, db, False), (44, db, False), (40, db, False)]
    dk = int(rec["biv"][params.HIT_SLOT, params.MAXD, 0])
    if dk > 0:
        out.append((params.HIT_SLOT + 4, dk + 1, True))
    return out


def _scratch_differs(after_g, after_e, rec):
    bad = []
    for slot, d, triangle in _scratch_regions(rec):
        g = _bits(after_g[slot, :d + 1, :d + 1])
        e = _bits(after_e[slot, :d + 1, :d + 1])
        if triangle:
            keep = np.add.outer(np.arange(d + 1), np.arange(d + 1)) <= d
            g, e = g[keep], e[keep]
        if not np.array_equal(g, e):
            bad.append(slot)
    return bad


@pytest.mark.opencl
def test_opencl_prepass_matches_numba():
    index = opencl_device_or_skip()
    d, prg = _program(index)
    recs = list(_systems())
    n = len(recs)
    per = {}
    for chain, kind, rec in recs:
        per[(chain, kind, rec["rev"])] = per.get((chain, kind, rec["rev"]), 0) + 1
    counts = {"systems": n, "live": 0, "none": 0, "whole_square_miss": 0, "banded": 0, "hit": 0, "beta_masks": 0,
              "beta_bits": 0, "boxes": 0, "small_boxes": 0, "tb": 0}
    bad = []
    for start in range(0, n, BATCH):
        batch = [rec for _, _, rec in recs[start:start + BATCH]]
        live_g, iout_g, box_g, tb_g, after_g = _run_opencl(d, prg, batch)
        for g, rec in enumerate(batch):
            live_e, n_e, after_e, ranges_e, mask_e, tb_e = _run_numba(rec)
            where = f"system {start + g} ({recs[start + g][0]} {recs[start + g][1]}, da {rec['da']}, db {rec['db']})"
            if not np.array_equal(live_g[g], live_e) or iout_g[g, 0] != n_e:
                bad.append(f"{where}: live {iout_g[g, 0]} vs {n_e}, pieces differ at "
                           f"{np.nonzero(live_g[g] != live_e)[0][:10]}")
            slots = _scratch_differs(after_g[g], after_e, rec)
            if slots:
                bad.append(f"{where}: the pre-pass's scratch differs in slots {slots}")
            if not np.array_equal(_bits(box_g[g]), _bits(ranges_e)):
                q = np.nonzero(np.any(_bits(box_g[g]) != _bits(ranges_e), axis=1))[0]
                bad.append(f"{where}: box_range differs in boxes {q} {rec['box_i'][q].tolist()}: "
                           f"{box_g[g][q].tolist()} vs {ranges_e[q].tolist()}")
            if iout_g[g, 1] != mask_e:
                bad.append(f"{where}: beta_mask {iout_g[g, 1]:#x} vs {mask_e:#x}")
            if not np.array_equal(_bits(tb_g[g]), _bits(tb_e)):
                bad.append(f"{where}: tensor_bernstein_box (degree {rec['tb_d']}) differs in "
                           f"{int(np.sum(_bits(tb_g[g]) != _bits(tb_e)))} coefficients")
            counts["live" if n_e > 0 else "none"] += 1
            counts["whole_square_miss"] += _whole_square_miss(rec)
            counts["banded"] += rec["blo"] != -math.inf or rec["bhi"] != math.inf
            counts["hit"] += rec["biv"][params.HIT_SLOT, params.MAXD, 0] > 0
            counts["beta_masks"] += rec["refract1"]
            counts["beta_bits"] += bin(mask_e).count("1")
            counts["boxes"] += N_BOX
            counts["small_boxes"] += int(np.sum((rec["box_i"][:, 1] >= 1) & (rec["box_i"][:, 1] <= 7)))
            counts["tb"] += 1
    print(f"\n{counts}\nper (chain, kind, reversed): {per}")
    assert not bad, f"{len(bad)} differences:\n" + "\n".join(bad[:20])
    # not vacuous: several hundred systems of every chain, both orientations, planted and random
    assert n >= 300, n
    for chain in CHAINS:
        for kind in ("planted", "random"):
            assert per.get((chain, kind, False), 0) + per.get((chain, kind, True), 0) >= 10, (chain, kind, per)
        assert per.get((chain, "planted", True), 0) + per.get((chain, "random", True), 0) >= 5, (chain, per)
    assert counts["live"] >= 100 and counts["none"] >= 40, counts
    # systems with none dropped by the hit test on the whole square and by the quadtree
    assert counts["whole_square_miss"] >= 10 and counts["none"] - counts["whole_square_miss"] >= 20, counts
    assert counts["banded"] >= 50 and counts["hit"] >= 100, counts
    assert counts["beta_masks"] >= 100 and counts["beta_bits"] >= 50, counts
    assert counts["small_boxes"] >= 500, counts
