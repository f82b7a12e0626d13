"""The one interface every chain solver sits behind, and the Specular Polynomials solver.

``solve_tuples`` is the public entry point (contract in CONTRACT.md).  A solver object
(``SpecularPolynomialSolver``, later the baselines) exposes ``name`` and
``solve(chain, x_start, x_end, P, N, eta) -> SolveResult`` whose ``report`` says what it
did (tuples tried, tuples skipped early, resultant roots, candidates, paths, seconds per
stage), so the benchmarks can chart speed against accuracy for all of them.
"""

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

ONE_BOUNCE_CHAINS = ("R", "T")
TWO_BOUNCE_CHAINS = ("RR", "RT", "TR", "TT")
CHAIN_LENGTH = {c: len(c) for c in ONE_BOUNCE_CHAINS + TWO_BOUNCE_CHAINS}


@dataclass
class SolveReport:
    """What one solve call did.  Counts are summed over the batch."""

    solver: str
    chain: str
    tuples: int = 0
    skipped: int = 0  # rejected before solving (sides, degenerate triangle or normals)
    roots: int = 0  # real resultant roots in range
    candidates: int = 0  # (u, v) candidates polished and validated
    paths: int = 0
    overflow: int = 0  # tuples whose paths did not all fit the per-tuple capacity
    determinants: int = 0  # two bounces: Bézout determinant evaluations
    device: str = "numba"  # where the solve ran
    seconds: dict = field(default_factory=dict)  # stage -> wall seconds

    def as_dict(self):
        return dict(self.__dict__)


@dataclass
class SolveResult:
    tuple_index: np.ndarray  # (m,) int64
    uv: np.ndarray  # (m, 2k) float64
    report: SolveReport


def _as_float_array(name, value, shape_tail, check_finite=True):
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or tuple(arr.shape[1:]) != shape_tail:
        raise ValueError(f"{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    if check_finite:
        _check_finite(name, arr)
    return np.ascontiguousarray(arr)


def _check_finite(name, arr):
    """ValueError naming the first tuple of ``arr`` with a NaN or Inf."""
    # one pass over the values first: a NaN or Inf makes the sum non-finite (so does an
    # overflow of finite values, which the full test then lets through)
    if arr.size and not np.isfinite(arr.sum()) and not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise ValueError(f"{name} contains NaN or Inf (first at tuple {bad})")


def validate_inputs(chain, x_start, x_end, P, N, eta, check_finite=True):
    """Check and convert solver inputs; raise ValueError with a clear reason.  With
    ``check_finite`` False the positions and normals are not scanned for NaN or Inf (the caller
    does that where it reads them anyway: the one-bounce kernel flags such tuples)."""
    if chain not in CHAIN_LENGTH:
        raise ValueError(f"unknown chain {chain!r}; expected one of {', '.join(CHAIN_LENGTH)}")
    k = CHAIN_LENGTH[chain]
    x_start = _as_float_array("x_start", x_start, (3,), check_finite)
    n = x_start.shape[0]
    x_end = _as_float_array("x_end", x_end, (3,), check_finite)
    P = _as_float_array("P", P, (k, 3, 3), check_finite)
    N = _as_float_array("N", N, (k, 3, 3), check_finite)
    for name, arr in (("x_end", x_end), ("P", P), ("N", N)):
        if arr.shape[0] != n:
            raise ValueError(f"{name} has {arr.shape[0]} tuples but x_start has {n}")
    return x_start, x_end, P, N, _as_eta(eta, n)


def check_finite_inputs(x_start, x_end, P, N):
    """ValueError naming the first input array and tuple with a NaN or Inf (the check that
    ``validate_inputs(..., check_finite=False)`` left out)."""
    for name, arr in (("x_start", x_start), ("x_end", x_end), ("P", P), ("N", N)):
        _check_finite(name, arr)


def _as_eta(eta, n):
    """eta as a contiguous (n,) float64 array (a scalar is broadcast); ValueError unless every
    value is finite and positive."""
    eta_arr = np.asarray(eta, dtype=np.float64)
    if eta_arr.ndim == 0:
        eta_arr = np.full(n, float(eta_arr))
    elif eta_arr.shape != (n,):
        raise ValueError(f"eta must be a scalar or have shape ({n},), got {eta_arr.shape}")
    if not np.all(np.isfinite(eta_arr)) or np.any(eta_arr <= 0.0):
        raise ValueError("eta must be finite and positive")
    return np.ascontiguousarray(eta_arr)


class SpecularPolynomialSolver:
    """Deterministic solver of Fan et al. 2024 (one bounce: R, T; two bounces: RR, RT, TR, TT)."""

    name = "spoly"

    def solve(self, chain, x_start, x_end, P, N, eta, stop_after=0, pieces=None, device="numba"):
        """Solve a batch of tuples; see CONTRACT.md.  ``stop_after`` is for stage timing;
        ``pieces`` (two bounces only) the number of pieces of the resultant's sign scan;
        ``device``: "numba" (default), "opencl" or "opencl:N" (see :func:`solve_tuples`)."""
        t0 = time.perf_counter()
        # the one-bounce kernel scans its tuples for NaN and Inf itself (below)
        x_start, x_end, P, N, eta = validate_inputs(chain, x_start, x_end, P, N, eta, check_finite=False)
        report = SolveReport(solver=self.name, chain=chain, tuples=x_start.shape[0])
        device_index = self._opencl_device(device, chain, report)
        if chain not in ONE_BOUNCE_CHAINS or (device_index is not None and not stop_after):
            check_finite_inputs(x_start, x_end, P, N)
        if chain in TWO_BOUNCE_CHAINS:
            return self._solve_two_bounce(chain, x_start, x_end, P, N, eta, stop_after, pieces, report, t0, device_index)
        if chain not in ONE_BOUNCE_CHAINS:
            raise ValueError(f"chain {chain!r} is not supported yet by the {self.name} solver")
        from .one_bounce import (CHUNK, CHUNK_COLUMNS, CHUNK_NONFINITE, CHUNK_OVERFLOW, MAX_PATHS_ONE_BOUNCE,
                                 solve_one_bounce_batch)

        n = x_start.shape[0]
        t1 = time.perf_counter()
        if device_index is not None and not stop_after:
            # compacted on the device: only the paths come back, in no particular order
            from ..opencl.backend import solve_one_bounce_opencl

            tuple_index, uv, totals, ordered = solve_one_bounce_opencl(device_index, chain == "T", x_start, x_end, P, N, eta)
            t2 = time.perf_counter()
            if not ordered:
                tuple_index, uv = canonical_order(tuple_index, uv, n)
            report.overflow = int(totals[4])
        else:
            # each chunk of tuples writes its paths densely from its own first row: only the rows
            # written are touched, and only the paths are gathered
            chunks = -(-n // CHUNK)
            chunk_index = np.empty(n * MAX_PATHS_ONE_BOUNCE, dtype=np.int64)
            chunk_uv = np.empty((n * MAX_PATHS_ONE_BOUNCE, 2))
            chunk_paths = np.zeros(chunks, dtype=np.int64)
            chunk_stats = np.zeros((chunks, CHUNK_COLUMNS), dtype=np.int64)
            if n:
                solve_one_bounce_batch(chain == "T", x_start, x_end, P, N, eta, int(stop_after), chunk_index, chunk_uv,
                                       chunk_paths, chunk_stats)
            totals = chunk_stats.sum(axis=0)
            if totals[CHUNK_NONFINITE]:
                check_finite_inputs(x_start, x_end, P, N)  # raises, naming the first such tuple
            t2 = time.perf_counter()
            tuple_index, uv = gather_chunk_paths(chunk_index, chunk_uv, chunk_paths, CHUNK * MAX_PATHS_ONE_BOUNCE)
            report.overflow = int(totals[CHUNK_OVERFLOW])
        t3 = time.perf_counter()
        report.roots, report.candidates, report.paths, report.skipped = (int(v) for v in totals[:4])
        report.seconds = {"prepare": t1 - t0, "solve": t2 - t1, "compact": t3 - t2}
        return SolveResult(tuple_index, uv, report)

    @staticmethod
    def _opencl_device(device, chain, report):
        """The OpenCL device index to use, or None for Numba (with a warning saying why)."""
        from ..opencl.backend import OpenCLUnavailable, device_name, parse_device, two_bounce_device_name

        index = parse_device(device)
        if index is None:
            report.device = "numba"
            return None
        try:
            # builds the program; OpenCLNoDoublePrecision propagates
            report.device = "opencl: " + (two_bounce_device_name(index) if chain in TWO_BOUNCE_CHAINS else device_name(index))
        except OpenCLUnavailable as ex:
            warnings.warn(f"OpenCL unavailable ({ex}); solving on Numba instead", RuntimeWarning, stacklevel=4)
            report.device = "numba"
            return None
        return index

    def _solve_two_bounce(self, chain, x_start, x_end, P, N, eta, stop_after, pieces, report, t0, device_index=None):
        from .two_bounce.params import DEFAULT_PIECES, MAX_PATHS_TWO_BOUNCE, MAX_PIECES, N_STATS, STAT_PATHS
        from .two_bounce.solve import solve_two_bounce_batch

        pieces = DEFAULT_PIECES if pieces is None else int(pieces)
        if not 1 <= pieces <= MAX_PIECES:
            raise ValueError(f"pieces must be in [1, {MAX_PIECES}], got {pieces}")
        n = x_start.shape[0]
        out_uv = np.empty((n, MAX_PATHS_TWO_BOUNCE, 4))
        out_count = np.zeros(n, dtype=np.int64)
        stats = np.zeros((n, N_STATS), dtype=np.int64)
        t1 = time.perf_counter()
        if device_index is not None and not stop_after:
            # the staged pipeline: Bézout determinants and brackets on the device, systems and
            # path-space polish on Numba (two_bounce/staged.py); the same paths
            from ..opencl.backend import solve_two_bounce_opencl

            if n:
                solve_two_bounce_opencl(device_index, chain[0] == "T", chain[1] == "T", x_start, x_end, P, N, eta, pieces,
                                        out_uv, out_count, stats)
        elif n:
            solve_two_bounce_batch(chain[0] == "T", chain[1] == "T", x_start, x_end, P, N, eta, pieces, int(stop_after),
                                   out_uv, out_count, stats)
        t2 = time.perf_counter()
        tuple_index, uv = compact_paths(out_uv, out_count)
        t3 = time.perf_counter()
        totals, report.overflow = _stat_totals(stats, STAT_PATHS, MAX_PATHS_TWO_BOUNCE)
        report.roots, report.candidates, report.paths, report.skipped = (int(v) for v in totals[:4])
        report.seconds = {"prepare": t1 - t0, "solve": t2 - t1, "compact": t3 - t2}
        report.determinants = int(totals[4])
        return SolveResult(tuple_index, uv, report)


class TupleTable:
    """Tuples given as index pairs into two tables, the form a bake produces them in: emitter
    rows (x_start (E, 3), the chain's triangles P, N (E, k, 3, 3), eta (E,)) and receiver
    points (x_end (S, 3)); tuple i is (emitter e[i], point s[i]).  The tables are checked once
    (as :func:`validate_inputs`); on an OpenCL device a one-bounce table is uploaded once and
    each :meth:`solve` sends only the pairs (8 bytes a tuple), elsewhere the rows are gathered
    and solved as :meth:`SpecularPolynomialSolver.solve` does.  Same paths either way.
    ``solver``: the :class:`SpecularPolynomialSolver` to use (default: the shared one);
    ``pieces``: as its ``solve``'s (two bounces)."""

    def __init__(self, chain, x_start, P, N, eta, x_end, device="numba", solver=None, pieces=None):
        if chain not in CHAIN_LENGTH:
            raise ValueError(f"unknown chain {chain!r}; expected one of {', '.join(CHAIN_LENGTH)}")
        k = CHAIN_LENGTH[chain]
        self.chain = chain
        self.solver = solver or _DEFAULT_SOLVER
        self.pieces = pieces
        self.x_start = _as_float_array("x_start", x_start, (3,))
        n = self.x_start.shape[0]
        self.P = _as_float_array("P", P, (k, 3, 3))
        self.N = _as_float_array("N", N, (k, 3, 3))
        for name, arr in (("P", self.P), ("N", self.N)):
            if arr.shape[0] != n:
                raise ValueError(f"{name} has {arr.shape[0]} emitter rows but x_start has {n}")
        self.eta = _as_eta(eta, n)
        self.x_end = _as_float_array("x_end", x_end, (3,))
        self.device = device
        self.device_name = "numba"
        self._table = None  # the OpenCL upload (one bounce on a device), made on the first solve

    def _pairs(self, e, s, on_device):
        """The pairs as contiguous int32 (what the device reads; int32 input is not copied),
        checked against the tables: by the OpenCL kernel when they go to the device as int32
        (the host does not scan millions of pairs first), else here."""
        e, s = np.asarray(e), np.asarray(s)
        if e.ndim != 1 or s.shape != e.shape or not (e.size == 0 or np.issubdtype(e.dtype, np.integer)) \
                or not (s.size == 0 or np.issubdtype(s.dtype, np.integer)):
            raise ValueError(f"e and s must be integer index arrays of one shape, got {e.dtype}{e.shape} and {s.dtype}{s.shape}")
        host_check = not on_device or e.dtype != np.int32 or s.dtype != np.int32  # wider ints could wrap
        if host_check and e.size and (e.min() < 0 or e.max() >= self.x_start.shape[0] or s.min() < 0
                                      or s.max() >= self.x_end.shape[0]):
            raise IndexError(f"pair indices outside the tables ({self.x_start.shape[0]} emitters, {self.x_end.shape[0]} points)")
        return np.ascontiguousarray(e, dtype=np.int32), np.ascontiguousarray(s, dtype=np.int32)

    def solve(self, e, s):
        """Paths of the tuples (e[i], s[i]): a :class:`SolveResult` whose tuple_index counts
        pairs, in canonical order."""
        on_device = self.chain in ONE_BOUNCE_CHAINS and self.device not in (None, "numba")
        e, s = self._pairs(e, s, on_device)
        if on_device:
            t0 = time.perf_counter()
            report = SolveReport(solver=self.solver.name, chain=self.chain, tuples=e.size)
            index = self.solver._opencl_device(self.device, self.chain, report)
            if index is not None:
                from ..opencl.backend import one_bounce_table, solve_one_bounce_pairs

                if self._table is None:
                    self._table = one_bounce_table(index, self.x_start, self.P, self.N, self.eta, self.x_end)
                self.device_name = report.device
                t1 = time.perf_counter()
                tuple_index, uv, totals, ordered = solve_one_bounce_pairs(index, self.chain == "T", self._table, e, s)
                t2 = time.perf_counter()
                if not ordered:
                    tuple_index, uv = canonical_order(tuple_index, uv, e.size)
                report.roots, report.candidates, report.paths, report.skipped = (int(v) for v in totals[:4])
                report.overflow = int(totals[4])
                report.seconds = {"prepare": t1 - t0, "solve": t2 - t1, "compact": time.perf_counter() - t2}
                return SolveResult(tuple_index, uv, report)
            self.device = "numba"  # warned once by _opencl_device; the rest of the bake stays on Numba
        result = self.solver.solve(self.chain, self.x_start[e], self.x_end[s], self.P[e], self.N[e], self.eta[e],
                                   pieces=self.pieces, device=self.device)
        self.device_name = result.report.device
        return result


def _stat_totals(stats, paths_column, capacity):
    """(column sums of the per-tuple statistics, tuples whose column ``paths_column`` counts
    more paths than ``capacity``)."""
    from ..paths.order import stat_totals

    totals = np.zeros(stats.shape[1], dtype=np.int64)
    over = stat_totals(stats, paths_column, capacity, totals) if stats.shape[0] else 0
    return totals, int(over)


def compact_paths(out_uv, out_count):
    """(n, cap, 2k) per-tuple slots + counts -> (tuple_index (m,), uv (m, 2k)) in canonical
    order (by tuple, then u, then v: ``paths.order``)."""
    from ..paths.order import gather_sorted

    m = int(np.minimum(out_count, out_uv.shape[1]).sum())
    tuple_index = np.empty(m, dtype=np.int64)
    uv = np.empty((m, out_uv.shape[2]))
    if m:
        gather_sorted(np.ascontiguousarray(out_uv), np.ascontiguousarray(out_count, dtype=np.int64), tuple_index, uv)
    return tuple_index, uv


def gather_chunk_paths(chunk_index, chunk_uv, chunk_paths, stride):
    """Paths written densely per chunk (chunk c's chunk_paths[c] rows from row c * stride, in
    canonical order) -> (tuple_index (m,), uv (m, w)), the chunks one after the other."""
    from ..paths.order import gather_chunks

    m = int(chunk_paths.sum())
    tuple_index = np.empty(m, dtype=np.int64)
    uv = np.empty((m, chunk_uv.shape[1]))
    if m:
        gather_chunks(chunk_index, chunk_uv, chunk_paths, stride, tuple_index, uv)
    return tuple_index, uv


def canonical_order(tuple_index, uv, n):
    """Paths of tuples in [0, n) given in any order -> (tuple_index, uv) in canonical order
    (by tuple, then u, then v: ``paths.order``): the order a device writes them in is not part
    of the result."""
    from ..paths.order import order_by_tuple

    out_index = np.empty(tuple_index.shape[0], dtype=np.int64)
    out_uv = np.empty(uv.shape)
    if tuple_index.shape[0]:
        order_by_tuple(np.ascontiguousarray(tuple_index, dtype=np.int64), np.ascontiguousarray(uv), n, out_index, out_uv)
    return out_index, out_uv


_DEFAULT_SOLVER = SpecularPolynomialSolver()


def solve_tuples(chain, x_start, x_end, P, N, eta, device="numba"):
    """All admissible specular paths x_start → triangles → x_end (Fan et al. 2024).

    chain: "R", "T", "RR", "RT", "TR" or "TT"; x_start, x_end: (n,3); P, N: (n,k,3,3) vertex positions / normals of
    the k triangles in path order; eta: scalar or (n,), IOR behind each surface.
    Returns (tuple_index (m,) int64, uv (m,2k) float64) with x = p0 + u e1 + v e2.
    device: "numba" (default), "opencl" (first OpenCL device) or "opencl:N"; OpenCL needs
    pyopencl and a device with double precision (a device without cl_khr_fp64 raises
    OpenCLNoDoublePrecision); without pyopencl or a device it warns and uses Numba.
    """
    result = _DEFAULT_SOLVER.solve(chain, x_start, x_end, P, N, eta, device=device)
    return result.tuple_index, result.uv
