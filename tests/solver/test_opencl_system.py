"""The OpenCL bivariate algebra and system construction of the two-bounce solver
(addon/solver/opencl/system.cl) compute what the Numba functions compute, bit for bit:
build_system (spoly/two_bounce/system.py: a and b of Fan et al. 2024 §3.4, Table 3, and the
hit-test copies of the map of eq 14-17), beta_poly (sqrt.py: β of eq 22) and _prepare_system
(staged.py: normalisation, the Bernstein early exit, the u-degrees), and through them the
bivariate operations of polynomials/bivariate.py.

system.cl is a library of static functions (no kernel); this test builds it with biv.cl and the
two-bounce tables and defines into a test-only program with kernels of its own (one work-item per
system).  The systems are real ones: the loop of staged._stage_a_oriented is replayed in Python
on the Numba kernels (fixtures/stage_a_replay.py) for tuples of
bench/workloads.py (planted and random, all four chains, both orientations; a few with flat
shading normals), and every build_system call's inputs are recorded.  Each system is then built
on the host (Numba) and on the device from the same starting scratch (random finite values: what
either side reads without writing first, or copies, shows up) and the whole scratch compared bit
for bit (int64 views), then normalised by _prepare_system on both.  PoCL on the CPU in CI;
skipped without a device.
"""

import collections
import functools

import numpy as np
import pytest

from addon.solver.polynomials import bivariate
from addon.solver.spoly.two_bounce import sqrt, staged, system
from addon.solver.spoly.two_bounce.params import BETA_SLOT, HIT_SLOT, MAXD, N_SLOTS, N_STATS, STAT_SKIPPED
from fixtures.opencl import library_program, opencl_device_or_skip
from fixtures.stage_a_replay import oriented_systems
from workloads import planted_two_bounce, random_two_bounce

CHAINS = ("RR", "RT", "TR", "TT")
ETA = 1.5
N_PLANTED = 64  # planted tuples drawn per chain (those breaking a side rule are dropped)
N_RANDOM = 24  # random tuples per chain
N_FLAT = 8  # random tuples per chain with flat shading normals (flat2)
BATCH = 64  # systems per launch (1 MB of scratch each)
BIV_SHAPE = (N_SLOTS, MAXD + 1, MAXD + 1)

# per system: ints (refract1, refract2, piece, flat2); doubles (s_in1, r1, S, eta_in2, eta_out2,
# heron[6], c2[3], geo_l[45])
N_IN_D = 5 + 6 + 3 + 45

TEST_KERNELS = r"""
__kernel void bv_test_build(__global const int *iin, __global const double *din, __global double *biv_all,
                            __global int *dab) {
    int g = get_global_id(0);
    __global const int *fi = iin + 4 * g;
    __global const double *fd = din + @N_IN_D@ * g;
    double heron[6], c2[3], geo_l[45];
    for (int k = 0; k < 6; ++k) heron[k] = fd[5 + k];
    for (int k = 0; k < 3; ++k) c2[k] = fd[11 + k];
    for (int k = 0; k < 45; ++k) geo_l[k] = fd[14 + k];
    __global double *biv = biv_all + (long)g * N_SLOTS * BIV_SLOT_SIZE;
    int da = -7, db = -7;
    bv_build_system(fi[0] != 0, fi[1] != 0, fd[0], fd[1], fi[2], fd[2], heron, fd[3], fd[4], fi[3] != 0, c2, geo_l, biv,
                    &da, &db);
    dab[2 * g] = da;
    dab[2 * g + 1] = db;
}

__kernel void bv_test_prepare(__global const int *iin, __global const int *dab, __global double *biv_all,
                              __global int *out, __global long *stats) {
    int g = get_global_id(0);
    __global double *biv = biv_all + (long)g * N_SLOTS * BIV_SLOT_SIZE;
    int na = -7, nb = -7, n = -7;
    __global long *st = stats + (long)g * N_STATS;
    out[4 * g] = bv_prepare_system(biv, dab[2 * g], dab[2 * g + 1], iin[4 * g] != 0, st, &na, &nb, &n);
    out[4 * g + 1] = na;
    out[4 * g + 2] = nb;
    out[4 * g + 3] = n;
}

__kernel void bv_test_beta(__global const double *din, __global double *biv_all) {
    int g = get_global_id(0);
    __global const double *fd = din + @N_IN_D@ * g;
    double geo_l[45];
    for (int k = 0; k < 45; ++k) geo_l[k] = fd[14 + k];
    bv_beta_poly(geo_l, fd[1], biv_all + (long)g * N_SLOTS * BIV_SLOT_SIZE);
}

__kernel void bv_test_bernstein(__global const double *polys, __global const int *deg, __global const double *margins,
                                const int n_m, __global int *out) {
    int g = get_global_id(0);
    __global const double *p = polys + (long)g * BIV_SLOT_SIZE;
    for (int k = 0; k < n_m; ++k) out[g * n_m + k] = bv_bernstein_has_zero(p, deg[g], margins[g * n_m + k]) ? 1 : 0;
}
"""


@functools.lru_cache(maxsize=None)
def _program(index):
    """(the _Device, {name: kernel}) of the test program (built once per device)."""
    d, prg = library_program(index, ("biv.cl", "system.cl"), TEST_KERNELS.replace("@N_IN_D@", str(N_IN_D)))
    names = ("bv_test_build", "bv_test_prepare", "bv_test_beta", "bv_test_bernstein")
    return d, {name: d.cl.Kernel(prg, name) for name in names}


# --- the systems: staged._stage_a_oriented's loop replayed on the Numba kernels ---------------


def _replay(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, biv, geo_o, geo_l, stats, kind, out):
    """Record the inputs of every build_system call of ``_stage_a_oriented``
    (fixtures.stage_a_replay)."""
    for q in oriented_systems(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, biv, geo_o, geo_l, stats):
        ints = (int(q.refract1), int(q.refract2), q.piece, int(q.flat2))
        doubles = np.concatenate([[q.s_in1, q.r1, q.S, q.eta_in2, q.eta_out2], q.heron, q.c2, q.geo_l.ravel()])
        out.append((kind, ints, doubles))


def _flat(x0, x3, P, N):
    """The tuples with every shading normal the geometric one (flat2, no normal interpolation)."""
    ng = np.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0])
    ng /= np.linalg.norm(ng, axis=-1, keepdims=True)
    return x0, x3, P, np.ascontiguousarray(np.repeat(ng[:, :, None, :], 3, axis=2))


@functools.lru_cache(maxsize=None)
def _systems():
    """(kinds, ints (S, 4) int32, doubles (S, N_IN_D)): kind = (chain, source, rev)."""
    biv = np.zeros(BIV_SHAPE)
    geo = np.zeros((3, 15, 3))
    stats = np.zeros(N_STATS, np.int64)
    out = []
    for k, chain in enumerate(CHAINS):
        refract1, refract2 = chain[0] == "T", chain[1] == "T"
        x0, x3, P, N, _ = planted_two_bounce(N_PLANTED, chain, eta=ETA, seed=70 + k)
        sources = (("planted", (x0, x3, P, N)), ("random", random_two_bounce(N_RANDOM, seed=80 + k)),
                   ("flat", _flat(*random_two_bounce(N_FLAT, seed=90 + k))))
        for source, (X0, X3, PP, NN) in sources:
            PP = np.ascontiguousarray(PP)
            NN = np.ascontiguousarray(NN)
            for t in range(X0.shape[0]):
                a = tuple(float(v) for v in X0[t])
                b = tuple(float(v) for v in X3[t])
                # forward (triangle 0 first), then reversed (x3 first, triangle 1 first)
                _replay(refract1, refract2, a, b, PP[t, 0], NN[t, 0], PP[t, 1], NN[t, 1], ETA, biv, geo[0], geo[1],
                        stats, (chain, source, 0), out)
                _replay(refract2, refract1, b, a, PP[t, 1], NN[t, 1], PP[t, 0], NN[t, 0], ETA, biv, geo[2], geo[1],
                        stats, (chain, source, 1), out)
    kinds = [o[0] for o in out]
    ints = np.array([o[1] for o in out], dtype=np.int32)
    doubles = np.ascontiguousarray(np.array([o[2] for o in out], dtype=np.float64))
    return kinds, ints, doubles


# --- the host side: the Numba kernels on the same inputs ---------------------------------------


def _build_args(i, d):
    """build_system's arguments but biv from a recorded system's ints and doubles rows."""
    return (bool(i[0]), bool(i[1]), float(d[0]), float(d[1]), int(i[2]), float(d[2]), tuple(float(x) for x in d[5:11]),
            float(d[3]), float(d[4]), bool(i[3]), tuple(float(x) for x in d[11:14]), d[14:].reshape(15, 3).copy())


def _host(ints, doubles, background):
    """Per system: (biv after build_system, da, db), (biv after _prepare_system, status, na, nb,
    n, stats), biv after beta_poly: each from a copy of background."""
    S = ints.shape[0]
    built = np.empty((S,) + BIV_SHAPE)
    prepared = np.empty((S,) + BIV_SHAPE)
    beta = np.empty((S,) + BIV_SHAPE)
    dab = np.zeros((S, 2), np.int32)
    prep = np.zeros((S, 4), np.int32)
    stats = np.zeros((S, N_STATS), np.int64)
    for s in range(S):
        args = _build_args(ints[s], doubles[s])
        biv = background.copy()
        dab[s] = system.build_system(*args, biv)
        built[s] = biv
        prep[s] = staged._prepare_system(biv, int(dab[s, 0]), int(dab[s, 1]), args[0], stats[s])
        prepared[s] = biv
        biv = background.copy()
        sqrt.beta_poly(args[11], args[3], biv)
        beta[s] = biv
    return built, dab, prepared, prep, stats, beta


def _device(d, prg, ints, doubles, background):
    cl = d.cl
    S = ints.shape[0]
    mf = cl.mem_flags
    queue = d.queue
    tiled = np.ascontiguousarray(np.broadcast_to(background, (S,) + BIV_SHAPE))
    iin = cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=ints)
    din = cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=doubles)
    biv = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=tiled)
    dab = np.zeros((S, 2), np.int32)
    prep = np.zeros((S, 4), np.int32)
    stats = np.zeros((S, N_STATS), np.int64)
    dab_buf = cl.Buffer(d.ctx, mf.READ_WRITE, dab.nbytes)
    prep_buf = cl.Buffer(d.ctx, mf.WRITE_ONLY, prep.nbytes)
    stats_buf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=stats)
    built = np.empty_like(tiled)
    prepared = np.empty_like(tiled)
    beta = np.empty_like(tiled)
    prg["bv_test_build"](queue, (S,), None, iin, din, biv, dab_buf)
    cl.enqueue_copy(queue, built, biv)
    cl.enqueue_copy(queue, dab, dab_buf)
    prg["bv_test_prepare"](queue, (S,), None, iin, dab_buf, biv, prep_buf, stats_buf)
    cl.enqueue_copy(queue, prepared, biv)
    cl.enqueue_copy(queue, prep, prep_buf)
    cl.enqueue_copy(queue, stats, stats_buf)
    cl.enqueue_copy(queue, biv, tiled)
    prg["bv_test_beta"](queue, (S,), None, din, biv)
    cl.enqueue_copy(queue, beta, biv)
    queue.finish()
    return built, dab, prepared, prep, stats, beta


def _bits(x):
    return np.ascontiguousarray(x).view(np.int64)


def _first_difference(got, exp, what, s0):
    """A message naming the first system and slots where got and exp differ (bit for bit)."""
    bad = np.nonzero(np.any((_bits(got) != _bits(exp)).reshape(got.shape[0], -1), axis=1))[0]
    if bad.size == 0:
        return None
    s = bad[0]
    slots = np.nonzero(np.any((_bits(got[s]) != _bits(exp[s])).reshape(N_SLOTS, -1), axis=1))[0]
    return f"{what}: {bad.size} systems differ, first {s0 + s}, slots {slots.tolist()}"


@pytest.mark.opencl
def test_opencl_system_matches_numba():
    index = opencl_device_or_skip()
    kinds, ints, doubles = _systems()
    S = ints.shape[0]
    d, prg = _program(index)
    background = np.random.default_rng(20260601).uniform(-1.0, 1.0, size=BIV_SHAPE)

    status = np.zeros(S, np.int32)
    errors = []
    for s0 in range(0, S, BATCH):
        sl = slice(s0, min(S, s0 + BATCH))
        h_built, h_dab, h_prepared, h_prep, h_stats, h_beta = _host(ints[sl], doubles[sl], background)
        g_built, g_dab, g_prepared, g_prep, g_stats, g_beta = _device(d, prg, ints[sl], doubles[sl], background)
        status[sl] = h_prep[:, 0]
        # degrees, then the parts named: a and b up to their degrees, the hit-test slots and corner
        np.testing.assert_array_equal(g_dab, h_dab, err_msg=f"da, db from system {s0}")
        for k in range(h_dab.shape[0]):
            da, db = h_dab[k]
            for slot, deg in ((0, da), (1, db)):
                tri = np.add.outer(np.arange(MAXD + 1), np.arange(MAXD + 1)) <= deg
                assert np.array_equal(_bits(g_built[k, slot][tri]), _bits(h_built[k, slot][tri])), \
                    f"system {s0 + k} ({kinds[s0 + k]}): slot {slot} differs"
            assert np.array_equal(_bits(g_built[k, HIT_SLOT:HIT_SLOT + 4]), _bits(h_built[k, HIT_SLOT:HIT_SLOT + 4])), \
                f"system {s0 + k} ({kinds[s0 + k]}): hit-test slots differ"
            assert g_built[k, HIT_SLOT, MAXD, 0] == h_built[k, HIT_SLOT, MAXD, 0] in (3.0, 5.0, 7.0)
            assert g_built[k, HIT_SLOT, MAXD, 1] == h_built[k, HIT_SLOT, MAXD, 1]
            beta_tri = np.add.outer(np.arange(MAXD + 1), np.arange(MAXD + 1)) <= 4
            assert np.array_equal(_bits(g_beta[k, BETA_SLOT][beta_tri]), _bits(h_beta[k, BETA_SLOT][beta_tri])), \
                f"system {s0 + k} ({kinds[s0 + k]}): beta_poly differs"
        # the whole scratch, bit for bit (intermediates, and nothing written that should not be)
        for what, got, exp in (("build_system", g_built, h_built), ("_prepare_system", g_prepared, h_prepared),
                               ("beta_poly", g_beta, h_beta)):
            msg = _first_difference(got, exp, what, s0)
            if msg:
                errors.append(msg)
        np.testing.assert_array_equal(g_prep, h_prep, err_msg=f"status, na, nb, n from system {s0}")
        np.testing.assert_array_equal(g_stats, h_stats, err_msg=f"stats from system {s0}")
        assert np.array_equal(g_stats[:, STAT_SKIPPED], (h_prep[:, 0] == 0).astype(np.int64))
    assert not errors, errors

    # not vacuous: every chain and orientation, reflection and refraction at each vertex, the
    # Heron √ and eq (23)'s pieces, flat and interpolated normals, systems solved and rejected
    r1, r2, piece, flat2 = ints[:, 0] == 1, ints[:, 1] == 1, ints[:, 2], ints[:, 3] == 1
    counts = {
        "systems": S,
        "reflect at 1": int((~r1).sum()), "refract at 1": int(r1.sum()),
        "reflect at 2": int((~r2).sum()), "refract at 2": int(r2.sum()),
        "Heron": int((r1 & (piece < 0)).sum()), "eq 23 pieces": int((r1 & (piece >= 0)).sum()),
        "distinct pieces": len(set(piece[r1 & (piece >= 0)].tolist())),
        "flat2": int(flat2.sum()),
        "status 1": int((status == 1).sum()), "status 0": int((status == 0).sum()),
        "status -1": int((status == -1).sum()),
    }
    per_chain = collections.Counter((k[0], k[2]) for k in kinds)
    print(f"\n{counts}\nper (chain, reversed): {dict(sorted(per_chain.items()))}")
    assert S >= 300
    for key in ("reflect at 1", "refract at 1", "reflect at 2", "refract at 2", "Heron", "eq 23 pieces", "status 1"):
        assert counts[key] >= 40, (key, counts[key])
    assert counts["distinct pieces"] >= 5 and counts["flat2"] >= 10 and counts["status 0"] >= 10, counts
    for chain in CHAINS:
        for rev in (0, 1):
            assert per_chain[(chain, rev)] >= 20, (chain, rev, per_chain[(chain, rev)])
    for r1_, r2_ in ((0, 0), (0, 1), (1, 0), (1, 1)):
        assert ((ints[:, 0] == r1_) & (ints[:, 1] == r2_)).sum() >= 40


# --- bernstein_has_zero at its thresholds, _prepare_system's other branches -------------------


def _key(x):
    """The doubles in order as integers (-0.0 and 0.0 alike)."""
    i = int(np.float64(x).view(np.int64))
    return i if i >= 0 else -(i & 0x7FFFFFFFFFFFFFFF)


def _unkey(k):
    return float(np.int64(k).view(np.float64)) if k >= 0 else -float(np.int64(-k).view(np.float64))


def _threshold(p, d):
    """(m, m_below): adjacent doubles in [-4, 4] with bernstein_has_zero(p, d, m) True and at
    m_below False (it is monotone in the margin: False far below, True far above)."""
    has_zero = lambda m: bivariate.bernstein_has_zero(p, d, m, 0.0)  # noqa: E731
    lo, hi = _key(-4.0), _key(4.0)
    assert not has_zero(-4.0) and has_zero(4.0)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if has_zero(_unkey(mid)):
            hi = mid
        else:
            lo = mid
    return _unkey(hi), _unkey(lo)


def _normalised_a(ints, doubles):
    """Every system's a after _prepare_system (host, built from zeros): (S, MAXD + 1, MAXD + 1), da."""
    S = ints.shape[0]
    polys = np.zeros((S, MAXD + 1, MAXD + 1))
    da = np.zeros(S, np.int32)
    biv = np.zeros(BIV_SHAPE)
    stats = np.zeros(N_STATS, np.int64)
    for s in range(S):
        biv[:] = 0.0
        da[s], db = system.build_system(*_build_args(ints[s], doubles[s]), biv)
        staged._prepare_system(biv, int(da[s]), db, bool(ints[s, 0]), stats)
        polys[s] = biv[0]
    return polys, da


def _edge_cases(built, dab, r1):
    """Scratches of built systems with a and b altered to reach _prepare_system's other
    branches: (biv stack, (da, db), refract1, labels)."""
    out, degs, flags, labels = [], [], [], []
    tri = np.add.outer(np.arange(MAXD + 1), np.arange(MAXD + 1))

    def add(label, biv, k):
        out.append(biv)
        degs.append(dab[k])
        flags.append(r1[k])
        labels.append(label)

    for k in range(built.shape[0]):
        da, db = dab[k]
        in_a, in_b = tri <= da, tri <= db
        b = built[k].copy()
        b[0][in_a] = 0.0
        add("a = 0", b, k)
        b = built[k].copy()
        b[1, 2, 3] = np.inf
        add("inf in b", b, k)
        b = built[k].copy()
        b[0, 1, 0] = np.nan
        add("NaN in a", b, k)
        b = built[k].copy()
        b[1, 0, 1] = np.nan
        add("NaN in b", b, k)
        b = built[k].copy()
        b[0][in_a] = 0.0
        b[0, 0, 0], b[0, 0, 1] = -0.5, 1.0  # a = v - 1/2: a zero on the triangle, u-degree 0
        b[1][in_b & (np.arange(MAXD + 1)[:, None] > 0)] = 0.0
        add("u-degree 0", b, k)
        b = built[k].copy()
        b[0][in_a] *= 1e-300  # coefficients near and below the subnormal range
        b[1][in_b] *= 1e-305
        add("subnormal", b, k)
        b = built[k].copy()
        b[0][in_a] *= -1.0
        b[0][in_a & (tri >= 2)] *= 1e-13  # the 1e-14 cut-off and u_degree's zeroed rows
        b[1][in_b & (tri >= 2)] *= 1e-14
        add("near the cut-offs", b, k)
    return np.ascontiguousarray(np.array(out)), np.array(degs, np.int32), np.array(flags, bool), labels


def _same(got, exp):
    """Bit for bit, or both NaN (a NaN's payload may differ between devices)."""
    return (_bits(got) == _bits(exp)) | (np.isnan(got) & np.isnan(exp))


@pytest.mark.opencl
def test_opencl_bernstein_threshold_and_prepare_branches():
    index = opencl_device_or_skip()
    kinds, ints, doubles = _systems()
    d, kernels = _program(index)
    cl = d.cl
    mf = cl.mem_flags
    queue = d.queue
    # a few systems of each chain and orientation (refraction at vertex 1 or not), built from zeros
    pick = []
    for chain in CHAINS:
        for rev in (0, 1):
            pick += [s for s, k in enumerate(kinds) if k[0] == chain and k[2] == rev][:3]
    built, dab, _, _, _, _ = _host(ints[pick], doubles[pick], np.zeros(BIV_SHAPE))

    # bernstein_has_zero on every normalised a (all systems), at its threshold margin and one
    # double below it: the device's Bernstein coefficients, their min, max and largest |.| decide
    # it at the same double
    polys, da = _normalised_a(ints, doubles)
    S = ints.shape[0]
    margins = np.zeros((S, 4))
    expected = np.zeros((S, 4), np.int32)
    for s in range(S):
        m, below = _threshold(polys[s], int(da[s]))
        margins[s] = m, below, 1e-2, 1e-9
        expected[s] = [bivariate.bernstein_has_zero(polys[s], int(da[s]), x, 0.0) for x in margins[s]]
    assert (expected[:, 0] == 1).all() and (expected[:, 1] == 0).all()
    got = np.zeros((S, 4), np.int32)
    bufs = [cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x) for x in (polys, da, margins)]
    out = cl.Buffer(d.ctx, mf.WRITE_ONLY, got.nbytes)
    kernels["bv_test_bernstein"](queue, (S,), None, *bufs, np.int32(4), out)
    cl.enqueue_copy(queue, got, out)
    queue.finish()
    bad = np.nonzero(np.any(got != expected, axis=1))[0]
    assert bad.size == 0, f"bernstein_has_zero differs for {bad.size} of {S} polynomials, first {bad[:5]}"
    positive = int((margins[:, 0] > 0.0).sum())

    # _prepare_system's other branches (degenerate scale, NaN, u-degree 0, subnormals, cut-offs)
    bivs, degs, flags, labels = _edge_cases(built, dab, ints[pick, 0] == 1)
    E = bivs.shape[0]
    h_prep = np.zeros((E, 4), np.int32)
    h_stats = np.zeros((E, N_STATS), np.int64)
    h_biv = bivs.copy()
    for e in range(E):
        h_prep[e] = staged._prepare_system(h_biv[e], int(degs[e, 0]), int(degs[e, 1]), bool(flags[e]), h_stats[e])
    iin = np.zeros((E, 4), np.int32)
    iin[:, 0] = flags
    g_prep = np.zeros((E, 4), np.int32)
    g_stats = np.zeros((E, N_STATS), np.int64)
    g_biv = np.empty_like(bivs)
    iin_buf = cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=iin)
    dab_buf = cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(degs))
    biv_buf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=bivs)
    prep_buf = cl.Buffer(d.ctx, mf.WRITE_ONLY, g_prep.nbytes)
    stats_buf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=g_stats)
    kernels["bv_test_prepare"](queue, (E,), None, iin_buf, dab_buf, biv_buf, prep_buf, stats_buf)
    cl.enqueue_copy(queue, g_prep, prep_buf)
    cl.enqueue_copy(queue, g_stats, stats_buf)
    cl.enqueue_copy(queue, g_biv, biv_buf)
    queue.finish()
    for e in range(E):
        assert np.array_equal(g_prep[e], h_prep[e]), (e, labels[e], g_prep[e], h_prep[e])
        assert np.array_equal(g_stats[e], h_stats[e]), (e, labels[e])
        assert _same(g_biv[e], h_biv[e]).all(), (e, labels[e])
    by_label = collections.defaultdict(collections.Counter)
    for e in range(E):
        by_label[labels[e]][int(h_prep[e, 0])] += 1
    print(f"\n{S} Bernstein thresholds ({positive} positive margins); {E} prepare edge cases, status per kind: "
          + "; ".join(f"{k}: {dict(v)}" for k, v in by_label.items()))
    statuses = collections.Counter(h_prep[:, 0].tolist())
    assert statuses[-1] >= 3 * len(pick) and statuses[1] >= 5 and statuses[0] >= 1, statuses
    assert by_label["u-degree 0"][-1] >= 1 and by_label["a = 0"][-1] == len(pick)
