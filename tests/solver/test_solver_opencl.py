"""The optional OpenCL back end (PoCL on the CPU in CI) returns the Numba back end's paths."""

import os

import numpy as np
import pytest

from addon.solver.opencl import backend as opencl_backend
from fixtures.opencl import opencl_device_or_skip
from addon.solver import solve_tuples
from addon.solver.spoly.api import SpecularPolynomialSolver

from workloads import planted_tuples, random_tuples


@pytest.mark.opencl
@pytest.mark.parametrize("stages", ["1", "2"])
@pytest.mark.parametrize("chain", ["R", "T"])
def test_opencl_returns_the_numba_paths(chain, stages, monkeypatch):
    """In one stage (CPUs) and as a filter stage then a solve stage over the survivors (GPUs)."""
    monkeypatch.setenv("CAUSTIC_OPENCL_STAGES", stages)
    index = opencl_device_or_skip()
    x0, x2, P, N, _ = planted_tuples(6000, chain, seed=21)
    r0, r2, rP, rN = random_tuples(6000, seed=22)
    x0, x2, P, N = np.vstack([x0, r0]), np.vstack([x2, r2]), np.vstack([P, rP]), np.vstack([N, rN])
    solver = SpecularPolynomialSolver()
    numba = solver.solve(chain, x0, x2, P, N, 1.5)
    ocl = solver.solve(chain, x0, x2, P, N, 1.5, device=f"opencl:{index}")
    assert ocl.report.device.startswith("opencl: ")
    assert numba.report.paths > 3000
    np.testing.assert_array_equal(ocl.tuple_index, numba.tuple_index)
    np.testing.assert_allclose(ocl.uv, numba.uv, rtol=0, atol=1e-9)
    assert ocl.report.paths == numba.report.paths and ocl.report.skipped == numba.report.skipped
    # Root and candidate counts may differ by a few touch candidates at rounding thresholds
    # (two compilers); the paths may not.
    assert abs(ocl.report.roots - numba.report.roots) <= 0.01 * numba.report.roots
    assert abs(ocl.report.candidates - numba.report.candidates) <= 0.01 * numba.report.candidates


def test_program_sources_paste_their_includes_once_nested(tmp_path):
    """backend._assemble: an included file's own includes are pasted too, each file once per
    program whichever file asks first; the shipped programs hold every Python-semantics max /
    min helper exactly once (numba_math.cl, included by several of their files)."""
    (tmp_path / "a.cl").write_text("A1\n// @INCLUDE c.cl@ (c)\nA2")
    (tmp_path / "b.cl").write_text("// @INCLUDE c.cl@\nB")
    (tmp_path / "c.cl").write_text("C")
    out = opencl_backend._assemble("top\n// @INCLUDE a.cl@\n// @INCLUDE b.cl@\n// @INCLUDE a.cl@\nend", str(tmp_path))
    assert out.split("\n") == ["top", "A1", "C", "A2", "B", "end"]
    folder = os.path.dirname(opencl_backend._KERNEL_FILE_2)
    for program in ("two_bounce.cl", "refine.cl", "splat.cl"):
        with open(os.path.join(folder, program)) as f:
            text = opencl_backend._assemble(f.read(), folder)
        assert text.count("#define NB_MAX(") == 1, program
        assert not any(line.startswith("// @INCLUDE ") for line in text.split("\n")), program


def test_bad_device_names_are_value_errors():
    P = np.zeros((1, 1, 3, 3))
    for bad in ("cuda", "opencl:", "opencl:x", "opencl:-1", 3):
        with pytest.raises(ValueError, match="device must be"):
            solve_tuples("R", np.zeros((1, 3)), np.ones((1, 3)), P, P, 1.5, device=bad)


@pytest.mark.opencl
def test_missing_device_warns_and_uses_numba():
    opencl_device_or_skip()
    x0, x2, P, N, _ = planted_tuples(200, "R", seed=23)
    expected = solve_tuples("R", x0, x2, P, N, 1.5)
    with pytest.warns(RuntimeWarning, match="OpenCL unavailable.*does not exist"):
        got = solve_tuples("R", x0, x2, P, N, 1.5, device="opencl:99")
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


def test_without_pyopencl_warns_and_uses_numba(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_pyopencl(name, *args, **kwargs):
        if name == "pyopencl" or name.startswith("pyopencl."):
            raise ImportError("No module named 'pyopencl'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pyopencl)
    monkeypatch.setattr(opencl_backend, "_cache", {})
    x0, x2, P, N, _ = planted_tuples(100, "T", seed=24)
    with pytest.warns(RuntimeWarning, match="pyopencl is not installed"):
        ti, uv = solve_tuples("T", x0, x2, P, N, 1.5, device="opencl")
    assert ti.size >= x0.shape[0] * 0.99


def test_device_without_double_precision_is_refused(monkeypatch):
    """The refusal path, with the device list replaced by one fp32-only device."""
    monkeypatch.setattr(opencl_backend, "_cache", {})
    monkeypatch.setattr(opencl_backend, "list_devices", lambda: [(0, "Fake", "fp32-only GPU", False, None)])
    x0, x2, P, N, _ = planted_tuples(10, "R", seed=25)
    with pytest.raises(opencl_backend.OpenCLNoDoublePrecision, match="fp32-only GPU.*cl_khr_fp64"):
        solve_tuples("R", x0, x2, P, N, 1.5, device="opencl")


def _lexsort_reference(tuple_index, uv):
    order = np.lexsort(tuple(uv[:, k] for k in range(uv.shape[1] - 1, -1, -1)) + (tuple_index,))
    return tuple_index[order], uv[order]


@pytest.mark.parametrize("width", [2, 4])
def test_canonical_order_is_the_lexicographic_order(width):
    """compact_paths (per-tuple slots) and canonical_order (paths in any order, as a device
    writes them) both give the order of a lexsort by (tuple, u, v, ...), ties included."""
    from addon.solver.spoly.api import canonical_order, compact_paths

    rng = np.random.default_rng(5)
    n, cap = 3000, 8
    counts = rng.choice([0, 0, 0, 1, 1, 2, 3, 8, 11], size=n)  # 11: more than the slots hold
    out_uv = rng.integers(0, 4, size=(n, cap, width)) / 4.0  # coarse values: many ties in u
    ti, uv = compact_paths(out_uv, counts)
    stored = np.minimum(counts, cap)
    ref_ti = np.repeat(np.arange(n), stored)
    ref_uv = np.concatenate([out_uv[t, :c] for t, c in enumerate(stored)])
    ref_ti, ref_uv = _lexsort_reference(ref_ti, ref_uv)
    np.testing.assert_array_equal(ti, ref_ti)
    np.testing.assert_array_equal(uv, ref_uv)
    shuffle = rng.permutation(ref_ti.size)
    ti2, uv2 = canonical_order(ref_ti[shuffle], ref_uv[shuffle], n)
    np.testing.assert_array_equal(ti2, ref_ti)
    np.testing.assert_array_equal(uv2, ref_uv)


def _mixed_batch(n_random, n_planted, chain, seed):
    """Random tuples (mostly without a path) with planted ones (a path each) spread among them."""
    x0, x2, P, N = random_tuples(n_random, seed=seed)
    p0, p2, pP, pN, _ = planted_tuples(2 * n_planted, chain, seed=seed + 1)
    at = np.sort(np.random.default_rng(seed).choice(n_random, size=n_planted, replace=False))
    for a, b in ((x0, p0), (x2, p2), (P, pP), (N, pN)):
        a[at] = b[:n_planted]
    return x0, x2, P, N


@pytest.mark.opencl
def test_device_buffers_by_role_and_inputs_read_in_place(monkeypatch):
    """_Device.buffer keeps a role's buffer while it is large enough and replaces it by one at
    least 1.5 times as large; read_only gives the kernels the array's own memory on a CPU device
    (and a written role buffer elsewhere): either way the device reads the array's values."""
    index = opencl_device_or_skip()
    d = opencl_backend._context(index)
    monkeypatch.setattr(d, "buffers", {})
    a = d.buffer("t", 4000)
    assert d.buffer("t", 1000) is a
    b = d.buffer("t", 5000)
    assert b is not a and b.size >= 6000
    values = np.random.default_rng(2).normal(size=1000)
    for cpu in (True, False):
        monkeypatch.setattr(d, "is_cpu", cpu)
        buf = d.read_only("t_in", values)
        assert ("t_in" in d.buffers) is not cpu
        back = np.empty_like(values)
        d.read(back, buf)
        np.testing.assert_array_equal(back, values)


@pytest.mark.parametrize("stages", ["1", "2"])
@pytest.mark.parametrize("chain", ["R", "T"])
def test_opencl_compaction_and_buffer_reuse(chain, stages, monkeypatch):
    """Paths compacted on the device equal Numba's over consecutive calls of different sizes
    (the device buffers kept from a larger call serve a smaller one and are replaced for a
    larger one), and when the path records overflow the device buffers (they grow and the
    kernel runs again)."""
    monkeypatch.setenv("CAUSTIC_OPENCL_STAGES", stages)
    index = opencl_device_or_skip()
    solver = SpecularPolynomialSolver()
    dev = opencl_backend._context(index)
    monkeypatch.setattr(dev, "buffers", {})  # as on a device's first call
    monkeypatch.setattr(dev, "path_capacity", 0)
    sizes = (6000, 1500, 9000)
    held = None
    for i, n in enumerate(sizes):
        x0, x2, P, N = _mixed_batch(n, n // 20, chain, seed=40 + i)
        numba = solver.solve(chain, x0, x2, P, N, 1.5)
        ocl = solver.solve(chain, x0, x2, P, N, 1.5, device=f"opencl:{index}")
        with_paths = np.unique(numba.tuple_index).size
        assert n // 40 < with_paths < n // 4  # some tuples have paths, most do not
        np.testing.assert_array_equal(ocl.tuple_index, numba.tuple_index)
        np.testing.assert_allclose(ocl.uv, numba.uv, rtol=0, atol=1e-9)
        assert (ocl.report.paths, ocl.report.skipped, ocl.report.overflow) == \
            (numba.report.paths, numba.report.skipped, numba.report.overflow)
        if dev.is_cpu:  # a CPU device reads the tuples where they are (_Device.read_only): no copy
            assert "x_start" not in dev.buffers
            continue
        buf = dev.buffers["x_start"]
        assert buf.size >= 24 * n
        if i == 1:
            assert buf is held  # the smaller call wrote into the larger call's buffer
        if i == 2:
            assert buf is not held  # a larger call replaced it
        held = buf
    # path records past the device buffers' capacity: the buffers grow and the kernel runs again
    monkeypatch.setattr(opencl_backend, "PATH_RECORDS_PER_TUPLE", 0)
    monkeypatch.setattr(opencl_backend, "PATH_RECORDS_MIN", 16)
    monkeypatch.setattr(dev, "path_capacity", 0)
    monkeypatch.setattr(dev, "buffers", {})
    x0, x2, P, N, _ = planted_tuples(400, chain, seed=47)
    numba = solver.solve(chain, x0, x2, P, N, 1.5)
    prof = opencl_backend.Profiler()
    opencl_backend.set_profiling(index, prof)
    try:
        ocl = solver.solve(chain, x0, x2, P, N, 1.5, device=f"opencl:{index}")
    finally:
        opencl_backend.set_profiling(index, None)
    launches = [stage for stage, _ in prof.events if stage.startswith("kernel")]
    assert numba.uv.shape[0] > 16
    if stages == "1":
        assert launches == ["kernel solve_one_bounce"] * 2  # run again after the overflow
    else:
        assert launches.count("kernel one_bounce solve") == 1 and launches.count("kernel gather") == 2  # gathered again
    assert dev.path_capacity >= numba.uv.shape[0]
    np.testing.assert_array_equal(ocl.tuple_index, numba.tuple_index)
    np.testing.assert_allclose(ocl.uv, numba.uv, rtol=0, atol=1e-9)
    assert ocl.report.paths == numba.report.paths


@pytest.mark.parametrize("chain", ["R", "T"])
def test_opencl_launches_in_batches_and_empty_calls(chain, monkeypatch):
    """A call larger than ONE_BOUNCE_BATCH runs in several launches (tuple offsets, summed
    statistics) with Numba's paths; a call without tuples returns nothing."""
    index = opencl_device_or_skip()
    solver = SpecularPolynomialSolver()
    x0, x2, P, N = _mixed_batch(7000, 700, chain, seed=60)
    numba = solver.solve(chain, x0, x2, P, N, 1.5)
    monkeypatch.setattr(opencl_backend, "ONE_BOUNCE_BATCH", 2500)
    prof = opencl_backend.Profiler()
    opencl_backend.set_profiling(index, prof)
    try:
        ocl = solver.solve(chain, x0, x2, P, N, 1.5, device=f"opencl:{index}")
    finally:
        opencl_backend.set_profiling(index, None)
    solves = [stage for stage, _ in prof.events if stage in ("kernel solve_one_bounce", "kernel one_bounce solve")]
    assert len(solves) == 3
    assert numba.uv.shape[0] > 700
    np.testing.assert_array_equal(ocl.tuple_index, numba.tuple_index)
    np.testing.assert_allclose(ocl.uv, numba.uv, rtol=0, atol=1e-9)
    assert (ocl.report.paths, ocl.report.skipped, ocl.report.overflow) == \
        (numba.report.paths, numba.report.skipped, numba.report.overflow)
    empty = solver.solve(chain, x0[:0], x2[:0], P[:0], N[:0], 1.5, device=f"opencl:{index}")
    assert empty.tuple_index.shape == (0,) and empty.uv.shape == (0, 2) and empty.report.paths == 0


@pytest.mark.opencl
@pytest.mark.parametrize("stages", ["1", "2"])
@pytest.mark.parametrize("chain", ["R", "T"])
def test_pair_table_on_the_device_returns_the_numba_paths(chain, stages, monkeypatch):
    """Tuples as (emitter, point) index pairs over tables uploaded once: the paths of the
    gathered tuples on Numba, over several solves of one table; bad pairs are refused."""
    from addon.solver.spoly.api import TupleTable

    monkeypatch.setenv("CAUSTIC_OPENCL_STAGES", stages)
    index = opencl_device_or_skip()
    x0, x2, P, N, _ = planted_tuples(3000, chain, seed=71)
    n = x0.shape[0]
    r0, r2, rP, rN = random_tuples(2000, seed=72)
    x0, P, N = np.vstack([x0, r0]), np.vstack([P, rP]), np.vstack([N, rN])
    points = np.vstack([x2, r2])
    eta = np.linspace(1.3, 1.6, x0.shape[0])
    rng = np.random.default_rng(73)
    device = TupleTable(chain, x0, P, N, eta, points, device=f"opencl:{index}")
    numba = TupleTable(chain, x0, P, N, eta, points)
    seen = 0
    for e, s in ((np.arange(n), np.arange(n)),  # the planted tuples: a path each
                 (rng.integers(0, x0.shape[0], 20000), rng.integers(0, points.shape[0], 20000))):
        got, want = device.solve(e, s), numba.solve(e, s)
        direct = SpecularPolynomialSolver().solve(chain, x0[e], points[s], P[e], N[e], eta[e])
        np.testing.assert_array_equal(want.tuple_index, direct.tuple_index)
        np.testing.assert_array_equal(want.uv, direct.uv)
        np.testing.assert_array_equal(got.tuple_index, want.tuple_index)
        np.testing.assert_allclose(got.uv, want.uv, rtol=0, atol=1e-9)
        assert (got.report.paths, got.report.skipped) == (want.report.paths, want.report.skipped)
        seen += want.report.paths
    assert device.device_name.startswith("opencl: ") and numba.device_name == "numba"
    assert seen > 0.9 * n
    for ints in (np.int64, np.int32):  # int32 pairs are checked by the kernel, wider ones on the host
        with pytest.raises(IndexError, match="outside the table"):
            device.solve(np.array([0, 1], dtype=ints), np.array([1, points.shape[0]], dtype=ints))
        with pytest.raises(IndexError, match="outside the table"):
            device.solve(np.array([-1, 1], dtype=ints), np.array([1, 2], dtype=ints))
    ok = device.solve(np.arange(n, dtype=np.int32), np.arange(n, dtype=np.int32))  # the device still serves
    assert ok.report.paths == numba.solve(np.arange(n), np.arange(n)).report.paths
    with pytest.raises(IndexError, match="outside the table"):
        numba.solve(np.array([0, 1]), np.array([1, -1]))  # on the host: a negative index must not wrap
    for bad in ((np.array([0, 1]), np.array([0])), (np.array([0.0]), np.array([0.0]))):
        with pytest.raises(ValueError, match="integer index arrays of one shape"):
            device.solve(*bad)


@pytest.mark.opencl
@pytest.mark.parametrize("stages", ["1", "2"])
def test_opencl_grazing_refractions_match_numba(stages, monkeypatch):
    """T at grazing incidence and near the critical angle, endpoints close to large triangles
    (tests/reference/grazing.py): the kernel interpolates the resultant at Chebyshev nodes as
    the Numba solver does (the symbolic expansion cancels there), so it returns the same
    paths, every planted one among them."""
    from reference.grazing import make_grazing
    from reference.truth import match_paths

    monkeypatch.setenv("CAUSTIC_OPENCL_STAGES", stages)
    index = opencl_device_or_skip()
    d = make_grazing(12_000)
    n = len(d["x0"])
    args = (d["x0"], d["x2"], d["P"], d["N"], d["eta"])
    numba = SpecularPolynomialSolver().solve("T", *args)
    ocl = SpecularPolynomialSolver().solve("T", *args, device=f"opencl:{index}")
    np.testing.assert_array_equal(ocl.tuple_index, numba.tuple_index)
    np.testing.assert_allclose(ocl.uv, numba.uv, rtol=0, atol=1e-9)
    found = match_paths(np.arange(n), d["uv"], ocl.tuple_index, ocl.uv) >= 0
    assert found.mean() >= 0.9999, f"{int((~found).sum())} planted paths missed of {n}"


@pytest.mark.opencl
def test_pair_table_without_the_device_warns_once_and_uses_numba():
    from addon.solver.spoly.api import TupleTable

    opencl_device_or_skip()
    x0, x2, P, N, _ = planted_tuples(300, "R", seed=81)
    n = x0.shape[0]
    table = TupleTable("R", x0, P, N, 1.5, x2, device="opencl:99")
    with pytest.warns(RuntimeWarning, match="OpenCL unavailable.*does not exist"):
        got = table.solve(np.arange(n), np.arange(n))
    again = table.solve(np.arange(n), np.arange(n))  # no second warning: the table stays on Numba
    want = solve_tuples("R", x0, x2, P, N, 1.5)
    assert table.device_name == "numba" and got.report.paths == want[0].size
    np.testing.assert_array_equal(got.tuple_index, want[0])
    np.testing.assert_array_equal(again.uv, want[1])
