"""The OpenCL per-tuple set-up of the two-bounce solver (addon/solver/opencl/frame.cl) computes
what the Numba functions of addon/solver/spoly/two_bounce/frame.py and sqrt.py compute, bit for
bit.

frame.cl is a library of static functions (no kernel); this test builds it (fixtures.opencl
library_program: after the two-bounce tables and two_vertex.cl) into a test-only program with
its own kernels (one work-item per case) and compares, case by case: tuple_frame (every returned
value, geo, geo_l, the statistics row), sqrt_sampling (the β/S² samples: ok, mask without the
beta_mask bits, fallback piece, xlo, xhi), heron_sqrt_cut (ok, cut, six coefficients) for r1 =
1/eta and eta, sqrt_band for every piece, and sqrt_piece / centroid_piece on a list of x values.
Geometry: bench/workloads.py (planted_two_bounce, random_two_bounce) for the four chains, both
orientations of each tuple, and degenerate tuples (zero-area triangles, an endpoint on a
triangle's plane, zero and constant shading normals, the plane-of-incidence fallback).  PoCL on
the CPU in CI; skipped without a device.
"""

import math

import numpy as np
import pytest

from addon.solver.spoly.two_bounce import frame, params, sqrt
from fixtures.opencl import library_program, opencl_device_or_skip
from workloads import planted_two_bounce, random_two_bounce

CHAINS = ("RR", "RT", "TR", "TT")
ETA = 1.5
R_VALUES = (1.0 / ETA, ETA)  # r1: entering / leaving the medium at vertex 1
MARGIN = params.V_MARGIN_APPROX
N_PLANTED = 40  # planted tuples per chain
N_RANDOM = 30  # random tuples per chain
N_DEGEN = 3  # per chain and kind of degenerate tuple
PIECES = range(-1, params.SQRT_PIECES.shape[0])  # sqrt_band's pieces (-1: Heron)
N_STATS = params.N_STATS

# doubles per case: geo 45 | geo_l 45 | side0, side3, inv, S, cx 3, c2 3 | per r1: xlo, xhi, cut,
# 6 coefficients | sqrt_band (blo, bhi) for refract1 = False / True and each piece
D_GEO, D_GEOL, D_FRAME, D_R = 0, 45, 90, 100
D_BAND = D_R + 9 * len(R_VALUES)
N_D = D_BAND + 2 * 2 * len(PIECES)
# ints per case: ok, any_front1, any_back1, any_front2, any_back2, flat2 | per r1: sampling ok, mask,
# fallback piece, Heron ok
I_R = 6
N_I = I_R + 4 * len(R_VALUES)

TEST_KERNELS = r"""
__kernel void frame_cases(__global const double *x0, __global const double *x3, __global const double *P,
                          __global const double *N, __global const int *flags, double r_a, double r_b, double margin,
                          __global double *dout, __global int *iout, __global long *stats) {
    int g = get_global_id(0);
    double geo[45], geo_l[45];
    for (int q = 0; q < 45; ++q) { geo[q] = 0.0; geo_l[q] = 0.0; }
    bool refract1 = flags[2 * g] != 0, refract2 = flags[2 * g + 1] != 0;
    __global double *d = dout + g * @N_D@;
    __global int *o = iout + g * @N_I@;
    fr_frame F = fr_tuple_frame(refract1, refract2, x0 + 3 * g, x3 + 3 * g, P + 18 * g, N + 18 * g, P + 18 * g + 9,
                                N + 18 * g + 9, geo, geo_l, stats + g * @N_STATS@);
    for (int q = 0; q < 45; ++q) { d[@D_GEO@ + q] = geo[q]; d[@D_GEOL@ + q] = geo_l[q]; }
    d[@D_FRAME@ + 0] = F.side0;
    d[@D_FRAME@ + 1] = F.side3;
    d[@D_FRAME@ + 2] = F.inv;
    d[@D_FRAME@ + 3] = F.S;
    for (int a = 0; a < 3; ++a) { d[@D_FRAME@ + 4 + a] = F.cx[a]; d[@D_FRAME@ + 7 + a] = F.c2[a]; }
    o[0] = F.ok; o[1] = F.any_front1; o[2] = F.any_back1; o[3] = F.any_front2; o[4] = F.any_back2; o[5] = F.flat2;
    if (F.ok) {
        for (int t = 0; t < 2; ++t) {
            double r = t == 0 ? r_a : r_b;
            int mask, fb;
            double xlo, xhi, cut, c[6];
            o[@I_R@ + 4 * t] = fr_sqrt_sampling(refract1, geo, F.inv, F.S, F.cx, r, &mask, &fb, &xlo, &xhi);
            o[@I_R@ + 4 * t + 1] = mask;
            o[@I_R@ + 4 * t + 2] = fb;
            o[@I_R@ + 4 * t + 3] = fr_heron_sqrt_cut(geo_l, r, margin, F.S * F.S, &cut, c);
            d[@D_R@ + 9 * t] = xlo;
            d[@D_R@ + 9 * t + 1] = xhi;
            d[@D_R@ + 9 * t + 2] = cut;
            for (int k = 0; k < 6; ++k) d[@D_R@ + 9 * t + 3 + k] = c[k];
        }
    }
    for (int rf = 0; rf < 2; ++rf) {
        for (int piece = -1; piece < N_SQRT_PIECES; ++piece) {
            double blo, bhi;
            fr_sqrt_band(piece, F.S * F.S, rf != 0, &blo, &bhi);
            d[@D_BAND@ + 2 * ((N_SQRT_PIECES + 1) * rf + piece + 1)] = blo;
            d[@D_BAND@ + 2 * ((N_SQRT_PIECES + 1) * rf + piece + 1) + 1] = bhi;
        }
    }
}

__kernel void piece_cases(__global const double *x, __global const int *mask, __global int *out) {
    int g = get_global_id(0);
    int fb;
    out[3 * g] = fr_sqrt_piece(x[g]);
    out[3 * g + 1] = fr_centroid_piece(x[g], mask[g], &fb);
    out[3 * g + 2] = fb;
}
"""


def _program(index):
    kernels = TEST_KERNELS
    for key, value in dict(N_D=N_D, N_I=N_I, N_STATS=N_STATS, D_GEO=D_GEO, D_GEOL=D_GEOL, D_FRAME=D_FRAME, D_R=D_R,
                           D_BAND=D_BAND, I_R=I_R).items():
        kernels = kernels.replace(f"@{key}@", str(value))
    return library_program(index, ("two_vertex.cl", "frame.cl"), kernels)


def _degenerate(x0, x3, P, N, rng):
    """Degenerate variants of planted tuples: (name, x0, x3, P, N) each N_DEGEN tuples."""
    k = N_DEGEN
    out = []
    dP = P[:k].copy()  # zero-area triangle 1 (pack_geometry fails: no statistics)
    dP[:, 0, 2] = dP[:, 0, 1]
    out.append(("zero-area 1", x0[:k], x3[:k], dP, N[:k]))
    dP = P[k:2 * k].copy()  # zero-area triangle 2
    dP[:, 1, 2] = dP[:, 1, 1]
    out.append(("zero-area 2", x0[k:2 * k], x3[k:2 * k], dP, N[k:2 * k]))
    T = P[2 * k:3 * k, 0]  # x0 on plane 1 (reversed: x3 on plane 2)
    a, b = rng.uniform(-0.5, 1.0, size=(2, k, 1))
    dx0 = T[:, 0] + a * (T[:, 1] - T[:, 0]) + b * (T[:, 2] - T[:, 0])
    out.append(("x0 on plane 1", dx0, x3[2 * k:3 * k], P[2 * k:3 * k], N[2 * k:3 * k]))
    # x0 off plane 1 by about the skip threshold 1e-12 L1 (either side of it)
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    L1 = np.maximum(np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1))[:, None]
    ng = np.cross(e1, e2)
    ng /= np.linalg.norm(ng, axis=1)[:, None]
    for f in (0.7, 1.4):
        out.append((f"x0 near plane 1 x{f}", dx0 + ng * (f * 1e-12) * L1, x3[2 * k:3 * k], P[2 * k:3 * k],
                    N[2 * k:3 * k]))
    dN = N[3 * k:4 * k].copy()  # zero shading normals on triangle 1 (reversed: on triangle 2)
    dN[:, 0] = 0.0
    out.append(("zero normals 1", x0[3 * k:4 * k], x3[3 * k:4 * k], P[3 * k:4 * k], dN))
    dN = N[4 * k:5 * k].copy()  # constant shading normals on triangle 2: flat2 (reversed: on triangle 1)
    dN[:, 1, 1:] = dN[:, 1, :1]
    out.append(("flat normals 2", x0[4 * k:5 * k], x3[4 * k:5 * k], P[4 * k:5 * k], dN))
    # x3 on the line through triangle 1's centroid along triangle 2's summed normals: the
    # plane-of-incidence normal falls back to e21 x nb (both sides of triangle 2)
    for s in (3.0, -3.0):
        sl = slice(5 * k, 6 * k)
        cen = P[sl, 0].mean(axis=1)
        dx3 = cen + s * N[sl, 1].sum(axis=1)
        out.append((f"c2 fallback {s:+}", x0[sl], dx3, P[sl], N[sl]))
    return out


def _cases():
    """Per case: x0, x3, P (2, 3, 3), N (triangle A first), (refract1, refract2) int32, and a
    label; each tuple forward and reversed (x0 <-> x3, triangles swapped, flags swapped)."""
    rng = np.random.default_rng(20260601)
    parts = []
    for k, chain in enumerate(CHAINS):
        flags = (chain[0] == "T", chain[1] == "T")
        x0, x3, P, N, _ = planted_two_bounce(8 * N_PLANTED, chain, eta=ETA, seed=60 + k)
        assert x0.shape[0] >= N_PLANTED + 6 * N_DEGEN
        parts.append(("planted", x0[:N_PLANTED], x3[:N_PLANTED], P[:N_PLANTED], N[:N_PLANTED], flags))
        r0, r3, rP, rN = random_two_bounce(N_RANDOM, seed=70 + k)
        parts.append(("random", r0, r3, rP, rN, flags))
        for name, a, b, c, d in _degenerate(x0[N_PLANTED:], x3[N_PLANTED:], P[N_PLANTED:], N[N_PLANTED:], rng):
            parts.append((name, a, b, c, d, flags))
    cols = [[] for _ in range(6)]
    for name, x0, x3, P, N, (f1, f2) in parts:
        m = x0.shape[0]
        for rev in (False, True):
            if rev:
                cols[0].append(x3)
                cols[1].append(x0)
                cols[2].append(P[:, ::-1])
                cols[3].append(N[:, ::-1])
                cols[4].append(np.tile(np.array([f2, f1], dtype=np.int32), (m, 1)))
            else:
                cols[0].append(x0)
                cols[1].append(x3)
                cols[2].append(P)
                cols[3].append(N)
                cols[4].append(np.tile(np.array([f1, f2], dtype=np.int32), (m, 1)))
            cols[5].extend([name + (" reversed" if rev else "")] * m)
    arrays = [np.ascontiguousarray(np.concatenate(c), dtype=np.float64) for c in cols[:4]]
    flags = np.ascontiguousarray(np.concatenate(cols[4]), dtype=np.int32)
    return (*arrays, flags, np.array(cols[5]))


def _run_opencl(d, prg, x0, x3, P, N, flags):
    cl = d.cl
    n = x0.shape[0]
    mf = cl.mem_flags
    inputs = [cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in (x0, x3, P, N, flags)]
    dout = np.zeros((n, N_D))
    iout = np.zeros((n, N_I), dtype=np.int32)
    stats = np.zeros((n, N_STATS), dtype=np.int64)
    dbuf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=dout)
    ibuf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=iout)
    sbuf = cl.Buffer(d.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=stats)
    queue = cl.CommandQueue(d.ctx)
    prg.frame_cases(queue, (n,), None, *inputs, np.float64(R_VALUES[0]), np.float64(R_VALUES[1]), np.float64(MARGIN),
                    dbuf, ibuf, sbuf)
    cl.enqueue_copy(queue, dout, dbuf)
    cl.enqueue_copy(queue, iout, ibuf)
    cl.enqueue_copy(queue, stats, sbuf)
    queue.finish()
    return dout, iout, stats


def _run_numba(x0, x3, P, N, flags):
    """The Numba functions, case by case: (dout, iout, stats) laid out as the kernel's, plus per
    case and r1 the mask of sqrt_pieces_to_solve, the beta_mask bits it would add, and its Heron
    results (ok, cut, coefficients)."""
    n = x0.shape[0]
    dout = np.zeros((n, N_D))
    iout = np.zeros((n, N_I), dtype=np.int32)
    stats = np.zeros((n, N_STATS), dtype=np.int64)
    full_mask = np.zeros((n, len(R_VALUES)), dtype=np.int64)
    beta_bits = np.zeros((n, len(R_VALUES)), dtype=np.int64)
    full_heron = np.zeros((n, len(R_VALUES), 8))
    biv = np.zeros((params.N_SLOTS, params.MAXD + 1, params.MAXD + 1))
    M = np.zeros((6, 7))
    for g in range(n):
        r1, r2 = bool(flags[g, 0]), bool(flags[g, 1])
        geo = np.zeros((3, 15, 3))
        (ok, side0, side3, inv, S, af1, ab1, af2, ab2, flat2, cx, c2) = frame.tuple_frame(
            r1, r2, tuple(x0[g]), tuple(x3[g]), P[g, 0], N[g, 0], P[g, 1], N[g, 1], geo[0], geo[1], stats[g])
        dout[g, D_GEO:D_GEOL] = geo[0].ravel()
        dout[g, D_GEOL:D_FRAME] = geo[1].ravel()
        dout[g, D_FRAME:D_R] = (side0, side3, inv, S, *cx, *c2)
        iout[g, :I_R] = (ok, af1, ab1, af2, ab2, flat2)
        if ok:
            for t, r in enumerate(R_VALUES):
                biv[:] = 0.0
                ok_s, mask, fb, h_ok, h_cut, h = frame.sqrt_pieces_to_solve(r1, geo[0], geo[1], inv, S, cx, r,
                                                                          MARGIN, biv)
                full_mask[g, t] = mask
                full_heron[g, t] = (h_ok, h_cut, *h)
                if r1:
                    dout[g, D_R + 9 * t:D_R + 9 * t + 2] = frame.sqrt_sampling(True, geo[0], inv, S, cx, r)[3:5]
                else:
                    dout[g, D_R + 9 * t:D_R + 9 * t + 2] = (math.inf, -math.inf)
                if ok_s and r1 and params.SQRT_BANDS:
                    beta_bits[g, t] = sqrt.beta_mask(biv, MARGIN, S * S)
                M[:] = 0.0
                hok, cut, c = sqrt.heron_sqrt_cut(geo[1], r, MARGIN, S * S, M)
                iout[g, I_R + 4 * t:I_R + 4 * t + 4] = (ok_s, 0, fb, hok)
                dout[g, D_R + 9 * t + 2:D_R + 9 * t + 9] = (cut, *c)
        for rf in (0, 1):
            for piece in PIECES:
                j = D_BAND + 2 * ((len(PIECES)) * rf + piece + 1)
                dout[g, j:j + 2] = sqrt.sqrt_band(piece, S * S, bool(rf))
    return dout, iout, stats, full_mask, beta_bits, full_heron


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def _piece_inputs():
    """x values (piece boundaries exactly and next to them, signed zeros, beyond [0, 1], NaN)
    and masks for sqrt_piece / centroid_piece."""
    rng = np.random.default_rng(7)
    edges = np.unique(params.SQRT_PIECES[:, :2])
    xs = np.concatenate([edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf), [0.0, -0.0, -1e-300, -0.5,
                         1.0, 1.5, np.inf, -np.inf, np.nan], rng.uniform(0.0, 1.0, 40), 10.0 ** rng.uniform(-9, 0, 40)])
    masks = np.array([0, 1, 2, 6, 1 << 14, (1 << 15) - 1, 0b1010])
    x = np.repeat(xs, masks.size)
    m = np.tile(masks, xs.size).astype(np.int32)
    return np.ascontiguousarray(x), np.ascontiguousarray(m)


@pytest.mark.opencl
def test_opencl_frame_matches_numba():
    index = opencl_device_or_skip()
    d, prg = _program(index)
    x0, x3, P, N, flags, labels = _cases()
    n = x0.shape[0]
    assert n >= 500
    got_d, got_i, got_s = _run_opencl(d, prg, x0, x3, P, N, flags)
    exp_d, exp_i, exp_s, full_mask, beta_bits, full_heron = _run_numba(x0, x3, P, N, flags)

    # tuple_frame: flags, statistics, geo, geo_l, every returned double: bit for bit
    names = ("frame ok", "any_front1", "any_back1", "any_front2", "any_back2", "flat2")
    for k, name in enumerate(names):
        bad = np.nonzero(got_i[:, k] != exp_i[:, k])[0]
        assert bad.size == 0, f"{name} differs in cases {bad[:10]} ({labels[bad[:10]]})"
    np.testing.assert_array_equal(got_s, exp_s)
    for name, a, b in (("geo", D_GEO, D_GEOL), ("geo_l", D_GEOL, D_FRAME), ("frame values", D_FRAME, D_R),
                       ("sqrt_band", D_BAND, N_D)):
        bad = np.nonzero(np.any(_bits(got_d[:, a:b]) != _bits(exp_d[:, a:b]), axis=1))[0]
        assert bad.size == 0, f"{name} differs in cases {bad[:10]} ({labels[bad[:10]]})"

    ok = exp_i[:, 0] == 1
    refract1 = flags[:, 0] == 1
    counts = dict(cases=n, frames_ok=int(ok.sum()), rejected=int((~ok).sum()),
                  skipped=int(exp_s[:, params.STAT_SKIPPED].sum()), flat2=int((ok & (exp_i[:, 5] == 1)).sum()))
    c2 = exp_d[:, D_FRAME + 7:D_FRAME + 10]
    e21 = exp_d[:, D_GEO + 24:D_GEO + 27]
    fallback_c2 = ok & (np.abs(np.sum(c2 * e21, 1)) <= 1e-12 * np.linalg.norm(e21, axis=1))
    counts["c2_fallback"] = int(fallback_c2.sum())

    # sampling / centroid and Heron, per r1
    tir = heron_ok = heron_fail = beta_added = beta_extra = sampled = 0
    for t in range(len(R_VALUES)):
        io = I_R + 4 * t
        for k, name in enumerate(("sampling ok", None, "fallback piece", "heron ok")):
            if name is None:
                continue
            bad = np.nonzero(ok & (got_i[:, io + k] != exp_i[:, io + k]))[0]
            assert bad.size == 0, f"r1={R_VALUES[t]:.4g}: {name} differs in cases {bad[:10]} ({labels[bad[:10]]})"
        s_ok = ok & (exp_i[:, io] == 1)
        # mask: Numba's = the sampled pieces | beta_mask's bits where Python adds them (xlo > 0)
        xlo = exp_d[:, D_R + 9 * t]  # the reference's (equal to the device's: checked below)
        add = s_ok & refract1 & bool(params.SQRT_BANDS) & (xlo > 0.0)
        mask_ocl = got_i[:, io + 1].astype(np.int64)
        expected = full_mask[:, t]
        combined = np.where(add, mask_ocl | beta_bits[:, t], mask_ocl)
        bad = np.nonzero(ok & (combined != expected))[0]
        assert bad.size == 0, (f"r1={R_VALUES[t]:.4g}: mask differs in cases {bad[:10]} ({labels[bad[:10]]}): "
                               f"{mask_ocl[bad[:5]]} | {beta_bits[bad[:5], t]} vs {expected[bad[:5]]}")
        # without refract1 nothing is sampled; TIR everywhere: xhi <= 0 and mask 0
        assert np.all(mask_ocl[ok & ~refract1] == 0) and np.all(np.isinf(xlo[ok & ~refract1]))
        xhi = got_d[:, D_R + 9 * t + 1]
        assert np.array_equal(ok & refract1 & ~s_ok, ok & refract1 & (xhi <= 0.0))
        assert np.all(mask_ocl[ok & ~s_ok] == 0)
        tir += int((ok & refract1 & ~s_ok).sum())
        sampled += int((s_ok & refract1).sum())
        beta_added += int(add.sum())
        beta_extra += int((add & ((beta_bits[:, t] & ~mask_ocl) != 0)).sum())
        # Heron: ok, cut, coefficients bit for bit (direct call); and as sqrt_pieces_to_solve returns it
        dr = D_R + 9 * t
        bad = np.nonzero(ok & np.any(_bits(got_d[:, dr:dr + 2]) != _bits(exp_d[:, dr:dr + 2]), axis=1))[0]
        assert bad.size == 0, f"r1={R_VALUES[t]:.4g}: sampled range (xlo, xhi) differs in cases {bad[:10]}"
        bad = np.nonzero(ok & np.any(_bits(got_d[:, dr + 2:dr + 9]) != _bits(exp_d[:, dr + 2:dr + 9]), axis=1))[0]
        assert bad.size == 0, f"r1={R_VALUES[t]:.4g}: Heron cut / coefficients differ in cases {bad[:10]}"
        via = ok & refract1 & s_ok & bool(params.HERON_SQRT)
        assert np.array_equal(got_i[via, io + 3], full_heron[via, t, 0].astype(np.int32))
        assert np.array_equal(_bits(got_d[via, dr + 2:dr + 9]), _bits(full_heron[via, t, 1:]))
        heron_ok += int((ok & (exp_i[:, io + 3] == 1)).sum())
        heron_fail += int((ok & (exp_i[:, io + 3] == 0)).sum())
    counts.update(sampled=sampled, tir_everywhere=tir, heron_ok=heron_ok, heron_not_ok=heron_fail,
                  beta_mask_added=beta_added, beta_mask_new_bits=beta_extra)

    # sqrt_piece / centroid_piece on their own
    xs, ms = _piece_inputs()
    out = np.zeros((xs.size, 3), dtype=np.int32)
    cl = d.cl
    mf = cl.mem_flags
    queue = cl.CommandQueue(d.ctx)
    obuf = cl.Buffer(d.ctx, mf.WRITE_ONLY, out.nbytes)
    prg.piece_cases(queue, (xs.size,), None, cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=xs),
                    cl.Buffer(d.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=ms), obuf)
    cl.enqueue_copy(queue, out, obuf)
    queue.finish()
    exp_p = np.array([(sqrt.sqrt_piece(x), *sqrt.centroid_piece(x, int(m))) for x, m in zip(xs, ms)])
    np.testing.assert_array_equal(out, exp_p)

    print(f"\n{counts}; {xs.size} sqrt_piece / centroid_piece cases: all bit for bit")
    # not vacuous
    assert counts["frames_ok"] >= 0.3 * n and counts["rejected"] >= 0.2 * n
    assert counts["skipped"] >= 50 and counts["flat2"] >= 4 and counts["c2_fallback"] >= 1
    assert counts["sampled"] >= 200 and counts["tir_everywhere"] >= 1
    assert counts["heron_ok"] >= 100 and counts["heron_not_ok"] >= 50
    assert counts["beta_mask_added"] >= 50
    for name in ("zero-area 1", "zero-area 2", "x0 on plane 1", "zero normals 1"):
        assert not ok[labels == name].any(), name
    near = np.char.startswith(labels, "x0 near plane 1") & ~np.char.endswith(labels, "reversed")
    assert ok[near].any() and not ok[near].all()  # the skip threshold on side0 splits them
