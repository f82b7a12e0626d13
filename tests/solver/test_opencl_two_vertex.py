"""The OpenCL two-vertex path-space code (addon/solver/opencl/two_vertex.cl) computes what the
Numba functions of addon/solver/paths/two_vertex.py (and one_vertex.line_crossing_barycentrics)
compute, to the last bit or nearly.

two_vertex.cl is a library of static functions (no kernel); this test builds it into a
test-only program with kernels of its own (one work-item per case) and compares, case by case,
pack_geometry, two_vertex_residual (residual and Jacobian, eq (3) of Fan et al. 2024 per
vertex), polish_and_validate2 (Gauss-Newton, acceptance, sigma estimate), trace_to_second and
line_crossing_barycentrics.  Geometry: bench/workloads.py (planted_two_bounce, random_two_bounce)
for the four chains; polish starts near the planted paths (mostly accepted) and at random points
of the triangles (mostly rejected).  PoCL on the CPU in CI; skipped without a device.
"""

import numpy as np
import pytest

from addon.solver.paths.one_vertex import line_crossing_barycentrics
from addon.solver.paths.two_vertex import (pack_geometry, polish_and_validate2, trace_to_second,
                                           two_vertex_residual)
from addon.solver.spoly.two_bounce.params import ACCEPT_RESIDUAL, POLISH_STEPS
from fixtures.opencl import library_program, opencl_device_or_skip
from workloads import planted_two_bounce, random_two_bounce

CHAINS = ("RR", "RT", "TR", "TT")
ETA = 1.5
N_PLANTED = 40  # planted tuples per chain (of more drawn: those breaking a side rule are dropped)
N_RANDOM = 24  # random tuples per chain
N_DEGENERATE = 2  # per chain: a planted tuple with a zero-area triangle

# Output layout per case (doubles): 45 geo | 6 res | 24 jac | 4 th | err, sigma | u2, v2 | 2 x (u, v)
D_GEO, D_RES, D_JAC, D_TH, D_ERR, D_TRACE, D_LINE, N_D = 0, 45, 51, 75, 79, 81, 83, 87
# ints per case: pack ok, residual ok, accepted, trace ok, line ok (triangle 1), line ok (triangle 2)
N_I = 6

TEST_KERNELS = r"""
static void tv_test_row(const double *geo, int i, double *out) {
    out[0] = geo[3 * i]; out[1] = geo[3 * i + 1]; out[2] = geo[3 * i + 2];
}

__kernel void two_vertex_cases(__global const double *x0, __global const double *x3, __global const double *P,
                               __global const double *N, __global const int *chain, __global const double *eta,
                               __global const double *th0, __global const double *uv1, int max_steps,
                               double tolerance, __global double *dout, __global int *iout) {
    int g = get_global_id(0);
    double geo[45], res[6], jac[24], th[4];
    bool refract1 = chain[2 * g] != 0, refract2 = chain[2 * g + 1] != 0;
    double e = eta[g];
    __global double *d = dout + g * @N_D@;
    __global int *o = iout + g * @N_I@;
    o[0] = tv_pack_geometry(x0 + 3 * g, x3 + 3 * g, P + 18 * g, N + 18 * g, P + 18 * g + 9, N + 18 * g + 9, geo);
    for (int q = 0; q < 45; ++q) d[q] = geo[q];
    for (int q = 0; q < 4; ++q) th[q] = th0[4 * g + q];
    for (int q = 0; q < 6; ++q) res[q] = 0.0;
    for (int q = 0; q < 24; ++q) jac[q] = 0.0;
    o[1] = tv_residual(th, geo, refract1, refract2, e, res, jac);
    for (int q = 0; q < 6; ++q) d[45 + q] = res[q];
    for (int q = 0; q < 24; ++q) d[51 + q] = jac[q];
    double err, sigma;
    o[2] = tv_polish_and_validate(th, geo, refract1, refract2, e, max_steps, tolerance, &err, &sigma);
    for (int q = 0; q < 4; ++q) d[75 + q] = th[q];
    d[79] = err;
    d[80] = sigma;
    double u2, v2;
    o[3] = tv_trace_to_second(uv1[2 * g], uv1[2 * g + 1], geo, refract1, e, &u2, &v2);
    d[81] = u2;
    d[82] = v2;
    double a[3], b[3], p0[3] = {0.0, 0.0, 0.0}, e1[3], e2[3], ng[3], u, v;
    tv_test_row(geo, 0, a);
    tv_test_row(geo, 1, b);
    tv_test_row(geo, 2, e1);
    tv_test_row(geo, 3, e2);
    tv_test_row(geo, 13, ng);
    o[4] = tv_line_crossing_barycentrics(a, b, p0, e1, e2, ng, &u, &v);
    d[83] = u;
    d[84] = v;
    tv_test_row(geo, 7, p0);
    tv_test_row(geo, 8, e1);
    tv_test_row(geo, 9, e2);
    tv_test_row(geo, 14, ng);
    o[5] = tv_line_crossing_barycentrics(a, b, p0, e1, e2, ng, &u, &v);
    d[85] = u;
    d[86] = v;
}
"""


def _program(index):
    kernels = TEST_KERNELS.replace("@N_D@", str(N_D)).replace("@N_I@", str(N_I))
    return library_program(index, ("two_vertex.cl",), kernels)


def _random_in_triangles(rng, n):
    """(n, 4): a uniform point in each of the two triangles' barycentric domains."""
    b = rng.dirichlet([1.0, 1.0, 1.0], size=(n, 2))
    return b[:, :, 1:].reshape(n, 4)


def _cases():
    """Per case: x0, x3, P (2, 3, 3), N, (refract1, refract2), eta, polish start th0, trace start
    (u1, v1), and whether the start is near a planted path."""
    rng = np.random.default_rng(20260519)
    parts = []
    for k, chain in enumerate(CHAINS):
        flags = (chain[0] == "T", chain[1] == "T")
        x0, x3, P, N, uv = (a[:N_PLANTED] for a in planted_two_bounce(8 * N_PLANTED, chain, eta=ETA, seed=40 + k))
        m = x0.shape[0]
        assert m == N_PLANTED
        # near the planted path: perturbed by 1e-3 .. 1e-2 (the polish converges)
        scale = 10.0 ** rng.uniform(-3.0, -2.0, size=(m, 1))
        near = uv + scale * rng.choice([-1.0, 1.0], size=(m, 4)) * rng.uniform(0.5, 1.0, size=(m, 4))
        trace_uv = np.where(rng.random((m, 1)) < 0.5, uv[:, :2], rng.uniform(-0.1, 1.1, size=(m, 2)))
        parts.append((x0, x3, P, N, flags, near, trace_uv, np.ones(m, bool)))
        # the same tuples from random points of the triangles (many rejected)
        parts.append((x0, x3, P, N, flags, _random_in_triangles(rng, m), rng.uniform(-0.1, 1.1, size=(m, 2)),
                      np.zeros(m, bool)))
        r0, r3, rP, rN = random_two_bounce(N_RANDOM, seed=50 + k)
        parts.append((r0, r3, rP, rN, flags, _random_in_triangles(rng, N_RANDOM),
                      rng.uniform(-0.1, 1.1, size=(N_RANDOM, 2)), np.zeros(N_RANDOM, bool)))
        # zero-area triangle 1 / triangle 2 (pack_geometry reports it; the rest runs on the unnormalised normal)
        dP = P[:N_DEGENERATE].copy()
        dP[0, 0, 2] = dP[0, 0, 1]
        dP[1 % N_DEGENERATE, 1, 2] = dP[1 % N_DEGENERATE, 1, 1]
        parts.append((x0[:N_DEGENERATE], x3[:N_DEGENERATE], dP, N[:N_DEGENERATE], flags, uv[:N_DEGENERATE] + 1e-3,
                      uv[:N_DEGENERATE, :2], np.zeros(N_DEGENERATE, bool)))
    cat = lambda i: np.ascontiguousarray(np.concatenate([p[i] for p in parts]), dtype=np.float64)  # noqa: E731
    flags = np.concatenate([np.tile(np.array(p[4], dtype=np.int32), (p[0].shape[0], 1)) for p in parts])
    planted = np.concatenate([p[7] for p in parts])
    n = planted.size
    return (cat(0), cat(1), cat(2), cat(3), np.ascontiguousarray(flags, dtype=np.int32), np.full(n, ETA), cat(5),
            cat(6), planted)


def _run_opencl(index, x0, x3, P, N, flags, eta, th0, uv1):
    d, prg = _program(index)
    cl = d.cl
    n = x0.shape[0]
    mf = cl.mem_flags
    inputs = [cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
              for a in (x0, x3, P, N, flags, eta, th0, uv1)]
    dout = np.zeros((n, N_D))
    iout = np.zeros((n, N_I), dtype=np.int32)
    dbuf = cl.Buffer(d.ctx, mf.WRITE_ONLY, dout.nbytes)
    ibuf = cl.Buffer(d.ctx, mf.WRITE_ONLY, iout.nbytes)
    queue = cl.CommandQueue(d.ctx)
    prg.two_vertex_cases(queue, (n,), None, *inputs, np.int32(POLISH_STEPS), np.float64(ACCEPT_RESIDUAL), dbuf, ibuf)
    cl.enqueue_copy(queue, dout, dbuf)
    cl.enqueue_copy(queue, iout, ibuf)
    queue.finish()
    return dout, iout


def _run_numba(x0, x3, P, N, flags, eta, th0, uv1):
    n = x0.shape[0]
    dout = np.zeros((n, N_D))
    iout = np.zeros((n, N_I), dtype=np.int32)
    geo = np.zeros((15, 3))
    res = np.zeros(6)
    jac = np.zeros((6, 4))
    work = np.zeros((25, 6))
    zero3 = np.zeros(3)
    for g in range(n):
        r1, r2 = bool(flags[g, 0]), bool(flags[g, 1])
        geo[:] = 0.0
        iout[g, 0] = pack_geometry(x0[g], x3[g], P[g, 0], N[g, 0], P[g, 1], N[g, 1], geo)
        dout[g, D_GEO:D_RES] = geo.ravel()
        res[:] = 0.0
        jac[:] = 0.0
        th = th0[g].copy()
        iout[g, 1] = two_vertex_residual(th, geo, r1, r2, eta[g], res, jac)
        dout[g, D_RES:D_JAC] = res
        dout[g, D_JAC:D_TH] = jac.ravel()
        work[:] = 0.0
        acc, err, sig = polish_and_validate2(th, geo, r1, r2, eta[g], POLISH_STEPS, ACCEPT_RESIDUAL, work)
        iout[g, 2] = acc
        dout[g, D_TH:D_ERR] = th
        dout[g, D_ERR:D_TRACE] = err, sig
        ok, u2, v2 = trace_to_second(uv1[g, 0], uv1[g, 1], geo, r1, eta[g])
        iout[g, 3] = ok
        dout[g, D_TRACE:D_LINE] = u2, v2
        for t, (p0, e1, e2, ng) in enumerate(((zero3, geo[2], geo[3], geo[13]), (geo[7], geo[8], geo[9], geo[14]))):
            ok, u, v = line_crossing_barycentrics(geo[0], geo[1], p0, e1, e2, ng)
            iout[g, 4 + t] = ok
            dout[g, D_LINE + 2 * t:D_LINE + 2 * t + 2] = u, v
    return dout, iout


def _max_rel(got, expected, floor=1.0):
    """max |got - expected| / max(floor, |expected|) over finite entries (0 for none)."""
    both = np.isfinite(expected) & np.isfinite(got)
    if not both.any():
        return 0.0
    return float(np.max(np.abs(got[both] - expected[both]) / np.maximum(floor, np.abs(expected[both]))))


@pytest.mark.opencl
def test_opencl_two_vertex_matches_numba():
    index = opencl_device_or_skip()
    x0, x3, P, N, flags, eta, th0, uv1, planted = _cases()
    n = x0.shape[0]
    assert n >= 200
    got, got_i = _run_opencl(index, x0, x3, P, N, flags, eta, th0, uv1)
    exp, exp_i = _run_numba(x0, x3, P, N, flags, eta, th0, uv1)

    # ok / accepted flags
    names = ("pack ok", "residual ok", "accepted", "trace ok", "line ok 1", "line ok 2")
    for k, name in enumerate(names):
        bad = np.nonzero(got_i[:, k] != exp_i[:, k])[0]
        assert bad.size == 0, f"{name} differs in cases {bad[:10]}"
    assert (exp_i[:, 0] == 0).sum() == len(CHAINS) * N_DEGENERATE  # the degenerate ones, and only they

    # pack_geometry: bit for bit
    np.testing.assert_array_equal(got[:, D_GEO:D_RES], exp[:, D_GEO:D_RES])

    # residual and Jacobian where defined
    ok = exp_i[:, 1] == 1
    assert ok.sum() >= 0.3 * n
    dev_res = _max_rel(got[ok, D_RES:D_JAC], exp[ok, D_RES:D_JAC])
    dev_jac = _max_rel(got[ok, D_JAC:D_TH], exp[ok, D_JAC:D_TH])
    assert dev_res <= 1e-12 and dev_jac <= 1e-12, (dev_res, dev_jac)

    # polish: th, err, sigma
    dev_th = _max_rel(got[:, D_TH:D_ERR], exp[:, D_TH:D_ERR])
    assert dev_th <= 1e-12, dev_th
    assert np.array_equal(np.isfinite(got[:, D_TH:D_ERR]), np.isfinite(exp[:, D_TH:D_ERR]))
    err_g, err_e = got[:, D_ERR], exp[:, D_ERR]
    assert np.array_equal(np.isinf(err_g), np.isinf(err_e)) and not np.isnan(err_e).any()
    fin = np.isfinite(err_e)
    err_dev = np.abs(err_g[fin] - err_e[fin])
    assert np.all((err_dev <= 1e-9 * np.abs(err_e[fin])) | (err_dev <= 1e-20)), \
        float(np.max(err_dev / np.maximum(np.abs(err_e[fin]), 1e-300)))
    sig_g, sig_e = got[:, D_ERR + 1], exp[:, D_ERR + 1]
    assert np.all(np.abs(sig_g - sig_e) <= 1e-9 * np.abs(sig_e)), float(np.max(np.abs(sig_g - sig_e)))
    dev_err = _max_rel(err_g, err_e, floor=1e-300)
    dev_sig = _max_rel(sig_g, sig_e, floor=1e-300)

    # not vacuous: near the planted paths most polishes are accepted, from random starts most rejected
    acc = exp_i[:, 2] == 1
    assert acc[planted].mean() >= 0.8, acc[planted].mean()
    # (from a random point of a planted tuple's triangles Gauss-Newton often still finds its path)
    assert (~acc[~planted]).mean() >= 0.4, (~acc[~planted]).mean()
    assert (~acc).sum() >= 0.25 * n and acc.sum() >= 0.25 * n

    # trace_to_second and line crossings
    tr = exp_i[:, 3] == 1
    assert 0.2 * n <= tr.sum() < n
    dev_trace = _max_rel(got[:, D_TRACE:D_LINE], exp[:, D_TRACE:D_LINE])
    dev_line = _max_rel(got[:, D_LINE:], exp[:, D_LINE:])
    assert dev_trace <= 1e-12 and dev_line <= 1e-12, (dev_trace, dev_line)

    identical = np.all((got == exp) | (np.isnan(got) & np.isnan(exp)), axis=1)
    bitwise = np.all(got.view(np.int64) == exp.view(np.int64), axis=1)
    print(f"\n{n} cases ({planted.sum()} started near a planted path, {acc.sum()} accepted: "
          f"{acc[planted].sum()} of those, "
          f"{acc[~planted].sum()} of the others; {tr.sum()} traced): "
          f"{identical.sum()} identical in every output ({bitwise.sum()} bit for bit, signed zeros included); "
          f"max deviation res {dev_res:.3g}, jac {dev_jac:.3g}, th {dev_th:.3g}, err {dev_err:.3g}, "
          f"sigma {dev_sig:.3g}, trace {dev_trace:.3g}, line {dev_line:.3g}")
    assert identical.mean() >= 0.9
