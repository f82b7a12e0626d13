"""The optional OpenCL back end (PoCL on the CPU in CI) returns the Numba back end's paths."""

import os
import sys

import numpy as np
import pytest

from addon.solver import opencl_backend, solve_tuples
from addon.solver.api import SpecularPolynomialSolver

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "bench"))
from workloads import planted_tuples, random_tuples  # noqa: E402


def _opencl_device_or_skip():
    try:
        devices = opencl_backend.list_devices()
    except opencl_backend.OpenCLUnavailable as ex:
        pytest.skip(f"no OpenCL here: {ex}")
    usable = [d for d in devices if d[3]]
    if not usable:
        pytest.skip("no OpenCL device with double precision")
    return usable[0][0]


@pytest.mark.opencl
@pytest.mark.parametrize("chain", ["R", "T"])
def test_opencl_returns_the_numba_paths(chain):
    index = _opencl_device_or_skip()
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


def test_bad_device_names_are_value_errors():
    P = np.zeros((1, 1, 3, 3))
    for bad in ("cuda", "opencl:", "opencl:x", "opencl:-1", 3):
        with pytest.raises(ValueError, match="device must be"):
            solve_tuples("R", np.zeros((1, 3)), np.ones((1, 3)), P, P, 1.5, device=bad)


@pytest.mark.opencl
def test_missing_device_warns_and_uses_numba():
    _opencl_device_or_skip()
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
