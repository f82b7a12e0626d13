"""The two-bounce OpenCL path (RR, RT, TR, TT) returns the Numba back end's paths.

device="opencl" runs the staged pipeline of addon/solver/spoly/two_bounce/staged.py: the systems
(stage A: on the device on GPUs, on Numba beside CPU devices, both tested here); the resultant scan over the Bézout determinants (Fan et al. 2024, eq 29:
samples, Illinois pins, root lists), its refinement (§4.2) and the candidates' back-substitution
and path-space polish (§4.3) on the device (addon/solver/opencl/two_bounce.cl).  PoCL on the CPU
in CI; tests that need a device skip without one.  Tuples: bench/workloads.py (planted_two_bounce, random_two_bounce) and
tests/reference/two_bounce_data.py (the sets of test_solver_two_bounce.py, fewer of them).
"""

import warnings

import numpy as np
import pytest

from addon.solver.opencl import backend as opencl_backend
from fixtures.opencl import opencl_device_or_skip
from addon.solver import solve_tuples
from addon.solver.spoly.api import SpecularPolynomialSolver, compact_paths
from reference.two_bounce_data import plant_two_bounce, random_two_bounce as random_pairs
from workloads import planted_two_bounce, random_two_bounce

CHAINS = ("RR", "RT", "TR", "TT")
N_EACH = 24  # tuples per source: ~1 min for the file on a loaded 2-core PoCL machine (warm Numba cache)


def _tuples(chain, n=N_EACH):
    """bench/workloads planted + random, and the test set's planted (tilted, sphere) + random."""
    x0, x3, P, N, _ = planted_two_bounce(4 * n, chain, seed=31)
    assert x0.shape[0] >= n
    r0, r3, rP, rN = random_two_bounce(n, seed=32)
    rng = np.random.default_rng([33, ord(chain[0]), ord(chain[1])])
    parts = [plant_two_bounce(rng, chain, n, sphere_frac=0.0), plant_two_bounce(rng, chain, n // 2, sphere_frac=1.0),
             random_pairs(rng, chain, n // 2)]
    cat = lambda key: np.concatenate([p[key] for p in parts])  # noqa: E731
    X0 = np.concatenate([x0[:n], r0, cat("x0")])
    X3 = np.concatenate([x3[:n], r3, cat("x3")])
    PP = np.concatenate([P[:n], rP, cat("P")])
    NN = np.concatenate([N[:n], rN, cat("N")])
    eta = np.concatenate([np.full(2 * n, 1.5), cat("eta")])
    return X0, X3, PP, NN, eta


def _assert_same_paths(got, expected, n, what=""):
    np.testing.assert_array_equal(np.bincount(got.tuple_index, minlength=n), np.bincount(expected.tuple_index, minlength=n),
                                  err_msg=f"path count per tuple {what}")
    np.testing.assert_array_equal(got.tuple_index, expected.tuple_index)
    np.testing.assert_allclose(got.uv, expected.uv, rtol=0, atol=1e-9, err_msg=what)


@pytest.mark.opencl
@pytest.mark.slow  # the first builds the two-bounce OpenCL kernels: ~3 min on PoCL here
@pytest.mark.parametrize("chain", CHAINS)
def test_opencl_two_bounce_returns_the_numba_paths(chain):
    index = opencl_device_or_skip()
    x0, x3, P, N, eta = _tuples(chain)
    solver = SpecularPolynomialSolver()
    numba = solver.solve(chain, x0, x3, P, N, eta)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning: it runs on the device
        ocl = solver.solve(chain, x0, x3, P, N, eta, device=f"opencl:{index}")
    assert ocl.report.device.startswith("opencl: ") and numba.report.device == "numba"
    assert numba.report.paths >= N_EACH
    _assert_same_paths(ocl, numba, x0.shape[0], chain)
    assert ocl.report.paths == numba.report.paths and ocl.report.skipped == numba.report.skipped
    assert ocl.report.overflow == numba.report.overflow
    # Two compilers (log, exp to the last bit): an Illinois iteration may take another step
    # and a rounding-level sign another value, so the counts may differ a little; the
    # paths may not.
    for key in ("determinants", "roots", "candidates"):
        a, b = getattr(ocl.report, key), getattr(numba.report, key)
        assert abs(a - b) <= 0.02 * b + 5, (key, a, b)
    print(f"\n[{chain}] {x0.shape[0]} tuples, {ocl.report.paths} paths; determinants OpenCL {ocl.report.determinants:,} "
          f"Numba {numba.report.determinants:,}")


def _solve_staged(device, chain, x0, x3, P, N, eta, **kwargs):
    from addon.solver.spoly.two_bounce.params import MAX_PATHS_TWO_BOUNCE, N_STATS
    from addon.solver.spoly.two_bounce.staged import solve_staged

    n = x0.shape[0]
    out_uv = np.zeros((n, MAX_PATHS_TWO_BOUNCE, 4))
    count = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, N_STATS), dtype=np.int64)
    solve_staged(device, chain[0] == "T", chain[1] == "T", x0, x3, P, N, eta, 100, out_uv, count, stats, **kwargs)
    ti, uv = compact_paths(out_uv, count)
    return ti, uv, stats.sum(0)


@pytest.mark.slow  # compiles the staged pipeline, which no other everyday test uses: ~45 s on a fresh cache
@pytest.mark.parametrize("chain", ["RR", "TT"])
def test_staged_pipeline_on_numba_is_the_one_kernel_solver(chain, monkeypatch):
    """Stages A-E with the resultant scan on Numba (no OpenCL needed): the staging itself
    changes nothing — same paths, and the same counts, determinants included — also with
    small batches, with tuples pushed to the one-kernel path (sys_cap=1), and with the
    refinement's capacity so small that most refined systems overflow it and are refined
    again on the host."""
    from addon.solver.spoly.two_bounce import staged

    x0, x3, P, N, eta = _tuples(chain, 8)
    expected = SpecularPolynomialSolver().solve(chain, x0, x3, P, N, eta)
    rep = expected.report
    for kwargs, cap in (({}, staged.REFINE_CAP), ({"batch": 5, "sys_cap": 1}, staged.REFINE_CAP), ({}, 2)):
        monkeypatch.setattr(staged, "REFINE_CAP", cap)
        ti, uv, totals = _solve_staged(staged.NumbaSystemSolver(), chain, x0, x3, P, N, eta, **kwargs)
        np.testing.assert_array_equal(ti, expected.tuple_index)
        np.testing.assert_allclose(uv, expected.uv, rtol=0, atol=1e-9)
        assert (totals[0], totals[2], totals[3], totals[4]) == (rep.roots, rep.paths, rep.skipped, rep.determinants), \
            (kwargs, cap)


@pytest.mark.opencl
@pytest.mark.slow  # builds the two-bounce OpenCL kernels
@pytest.mark.parametrize("chain", CHAINS)
def test_opencl_stage_a_on_the_device_returns_the_numba_paths(chain, monkeypatch):
    """The whole pipeline on the device, the systems too (stage_a.cl: frame.cl, system.cl,
    prepass.cl; what GPUs run, CPUs build the systems on Numba by default): the one-kernel
    solver's paths and counts, also with small batches and tuples pushed to the host's
    one-kernel path (sys_cap=1)."""
    index = opencl_device_or_skip()
    from addon.solver.opencl.backend import OpenCLSystemSolver

    monkeypatch.setenv("CAUSTIC_OPENCL_STAGE_A", "device")
    x0, x3, P, N, eta = _tuples(chain, 12)
    expected = SpecularPolynomialSolver().solve(chain, x0, x3, P, N, eta)
    rep = expected.report
    assert rep.paths >= 12
    for kwargs in ({}, {"batch": 7, "sys_cap": 1}):
        ti, uv, totals = _solve_staged(OpenCLSystemSolver(index), chain, x0, x3, P, N, eta, **kwargs)
        np.testing.assert_array_equal(ti, expected.tuple_index)
        np.testing.assert_allclose(uv, expected.uv, rtol=0, atol=1e-9)
        assert (totals[2], totals[3]) == (rep.paths, rep.skipped), kwargs
        assert abs(int(totals[4]) - rep.determinants) <= 0.02 * rep.determinants + 5, kwargs


@pytest.mark.opencl
@pytest.mark.slow  # builds the two-bounce OpenCL kernels
def test_opencl_refinement_in_cuts_and_overflow_on_the_host(monkeypatch):
    """Stage A in launches of 5 tuples and the refinement over the batch's systems in cuts of
    3 (their scratch made that small), and a tuple with a system whose refined roots exceed
    the device's capacity (here 2 a system) left to the host's one-kernel path: the paths and
    counts stay the one-kernel solver's."""
    index = opencl_device_or_skip()
    from addon.solver.opencl.backend import OpenCLSystemSolver
    from addon.solver.spoly.two_bounce import staged

    x0, x3, P, N, eta = _tuples("RT", 8)
    expected = SpecularPolynomialSolver().solve("RT", x0, x3, P, N, eta)
    on_host = []
    solve_on_host = staged.solve_on_host
    monkeypatch.setattr(staged, "solve_on_host", lambda *a: on_host.extend(a[8]) or solve_on_host(*a))
    monkeypatch.setattr(staged, "REFINE_CAP", 2)
    monkeypatch.setattr(opencl_backend, "REFINE_SUB_BYTES", 3 * opencl_backend.refine_bytes_per_system(100))
    monkeypatch.setattr(opencl_backend, "STAGE_A_SCRATCH_BYTES", 5 << 20)  # stage A in launches of 5 tuples
    monkeypatch.setenv("CAUSTIC_OPENCL_STAGE_A", "device")
    ti, uv, totals = _solve_staged(OpenCLSystemSolver(index), "RT", x0, x3, P, N, eta)
    assert 0 < len(on_host) < x0.shape[0], "a capacity of 2 should overflow some tuples' refinement, not all"
    np.testing.assert_array_equal(ti, expected.tuple_index)
    np.testing.assert_allclose(uv, expected.uv, rtol=0, atol=1e-9)
    rep = expected.report
    assert (totals[2], totals[3]) == (rep.paths, rep.skipped)
    assert abs(int(totals[4]) - rep.determinants) <= 0.02 * rep.determinants + 5


@pytest.mark.opencl
@pytest.mark.slow  # builds the two-bounce OpenCL kernels
def test_opencl_determinant_equals_det_bezout():
    """sign and log|det R(v1)| (eq 29) of real TT systems: OpenCL against Numba's det_bezout."""
    index = opencl_device_or_skip()
    from addon.solver.opencl.backend import OpenCLSystemSolver
    from addon.solver.spoly.two_bounce.params import MAXD, N_STATS
    from addon.solver.spoly.two_bounce.resultant import det_bezout
    from addon.solver.spoly.two_bounce.staged import SYS_CAP, _unpack_v_major, layout, stage_a_on_host

    x0, x3, P, N, eta = _tuples("TT", 6)
    n = x0.shape[0]
    stride, b_offset = layout(True, True)
    _, systems = stage_a_on_host(True, True, x0, x3, P, N, eta, 100, stride, b_offset, SYS_CAP,
                                 np.zeros((n, N_STATS), dtype=np.int64))
    solvable = systems.sysint[:, 1] == 1
    assert solvable.sum() >= 20
    coef, sysint = np.ascontiguousarray(systems.coef[solvable]), systems.sysint[solvable]
    count = coef.shape[0]
    assert sysint[:, 6].max() > 30  # TT: Bézout matrices up to 46 x 46
    dev = OpenCLSystemSolver(index)
    dev.load(coef, np.ascontiguousarray(sysint[:, [2, 3, 6]], dtype=np.int32), b_offset, np.ones((count, 100), np.int8),
             np.full(count, 0.02), 100)
    rng = np.random.default_rng(7)
    job_sys = np.repeat(np.arange(count), 40).astype(np.int32)
    job_v = rng.uniform(-0.02, 1.02, job_sys.size)
    sign, log, _ = dev.dets(job_sys, job_v)
    a = np.zeros((MAXD + 1, MAXD + 1))
    scratch = np.zeros((MAXD + 1, MAXD + 1))
    b = np.zeros((MAXD + 1, MAXD + 1))
    cf = np.zeros((2, MAXD + 2))
    mat = np.zeros((MAXD + 1, MAXD + 1))
    compared = 0
    for j, (s, v) in enumerate(zip(job_sys, job_v)):
        da, db, nn = sysint[s, 2], sysint[s, 3], sysint[s, 6]
        _unpack_v_major(coef[s], 0, da, scratch, a)
        _unpack_v_major(coef[s], b_offset, db, scratch, b)
        s_nb, lg_nb = det_bezout(a, da, b, db, nn, v, cf, mat)
        if s_nb == 0:
            continue  # an exact zero is re-checked a hair away by both back ends
        assert sign[j] == s_nb, (j, s, v)
        assert abs(log[j] - lg_nb) <= 1e-9 * max(1.0, abs(lg_nb)), (j, log[j], lg_nb)
        compared += 1
    assert compared >= 0.99 * job_sys.size


@pytest.mark.opencl
@pytest.mark.slow  # builds the two-bounce OpenCL kernels
@pytest.mark.parametrize("chain", CHAINS)
def test_opencl_two_bounce_degenerate_tuples(chain):
    """Degenerate, grazing and near-TIR tuples (as test_solver_two_bounce.py): no NaN, no
    crash, the Numba back end's paths."""
    index = opencl_device_or_skip()
    rng = np.random.default_rng([20261121, 9, ord(chain[0]), ord(chain[1])])
    d = plant_two_bounce(rng, chain, 40, max_theta_deg=89.9)
    x0, x3, P, N, eta = d["x0"].copy(), d["x3"].copy(), d["P"].copy(), d["N"].copy(), d["eta"].copy()
    P[0:4, 0, 2] = P[0:4, 0, 0]  # zero-area triangle 1
    P[4:8, 1, 2] = P[4:8, 1, 1]  # zero-area triangle 2
    N[8:12] = 0.0  # zero normals
    x0[12:16] = P[12:16, 0].mean(1) + 2.0 * (P[12:16, 0, 1] - P[12:16, 0, 0])  # x0 in plane 1
    x3[16:20] = P[16:20, 1].mean(1) + 2.0 * (P[16:20, 1, 1] - P[16:20, 1, 0])  # x3 in plane 2
    P[20:24, 1] = P[20:24, 0]  # both triangles the same
    eta[24:28] = 1.0 + 1e-9  # index matched
    c = P[28:40, 0].mean(1)
    fn = np.cross(P[28:40, 0, 1] - P[28:40, 0, 0], P[28:40, 0, 2] - P[28:40, 0, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    rel = x0[28:40] - c
    h = np.sum(rel * fn, 1, keepdims=True)
    x0[28:40] = c + (rel - h * fn) + h * fn * 10.0 ** rng.uniform(-6, -2, (12, 1))  # grazing
    solver = SpecularPolynomialSolver()
    numba = solver.solve(chain, x0, x3, P, N, eta)
    ocl = solver.solve(chain, x0, x3, P, N, eta, device=f"opencl:{index}")
    assert np.isfinite(ocl.uv).all()
    assert not np.isin(ocl.tuple_index, np.r_[0:12]).any()
    _assert_same_paths(ocl, numba, x0.shape[0], chain)


@pytest.mark.opencl
def test_two_bounce_missing_device_warns_and_uses_numba():
    opencl_device_or_skip()
    x0, x3, P, N, _ = planted_two_bounce(12, "RR", seed=34)
    expected = solve_tuples("RR", x0, x3, P, N, 1.5)
    with pytest.warns(RuntimeWarning, match="OpenCL unavailable.*does not exist"):
        got = solve_tuples("RR", x0, x3, P, N, 1.5, device="opencl:99")
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


def test_two_bounce_device_without_double_precision_is_refused(monkeypatch):
    monkeypatch.setattr(opencl_backend, "_cache", {})
    monkeypatch.setattr(opencl_backend, "_cache2", {})
    monkeypatch.setattr(opencl_backend, "list_devices", lambda: [(0, "Fake", "fp32-only GPU", False, None)])
    x0, x3, P, N, _ = planted_two_bounce(6, "TT", seed=35)
    with pytest.raises(opencl_backend.OpenCLNoDoublePrecision, match="fp32-only GPU.*cl_khr_fp64"):
        solve_tuples("TT", x0, x3, P, N, 1.5, device="opencl")


@pytest.mark.opencl
def test_two_bounce_program_that_does_not_build_warns_and_uses_numba(monkeypatch, tmp_path):
    """A driver that rejects the two-bounce program (here a source with a syntax error) is no
    crash: the solve warns with the build log and runs on Numba (the same paths)."""
    index = opencl_device_or_skip()
    device = opencl_backend._context(index)
    broken = tmp_path / "two_bounce.cl"
    broken.write_text("__kernel void det_batch(__global double *x) { x[0] = ; }\n")
    monkeypatch.setattr(opencl_backend, "_KERNEL_FILE_2", str(broken))
    monkeypatch.setattr(device, "kernels_two", None)
    monkeypatch.setattr(opencl_backend, "_cache2", {})
    x0, x3, P, N, _ = planted_two_bounce(8, "RR", seed=36)
    expected = solve_tuples("RR", x0, x3, P, N, 1.5)
    with pytest.warns(RuntimeWarning, match="OpenCL unavailable.*does not build"):
        got = solve_tuples("RR", x0, x3, P, N, 1.5, device=f"opencl:{index}")
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
