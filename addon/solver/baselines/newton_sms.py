"""Baseline one-bounce solvers behind the same interface as the Specular Polynomials.

* ``NewtonSolver`` ("newton"): Manifold Next Event Estimation (Hanika et al. 2015) with the
  deterministic seeds of Path Cuts (Wang et al. 2020): the triangle's centroid, and for a
  refraction also the point where the straight line x0 -> x2 crosses the triangle.  Newton
  from each seed on the path-space constraint; a seed far from the path, or a tuple with two
  paths, loses paths — which is what the comparison is meant to show.
* ``SMSSolver`` ("sms"): Specular Manifold Sampling, biased variant (Zeltner et al. 2020):
  k uniformly random seeds per tuple, each solved by Newton, distinct solutions kept.  The
  seeds come from a counter-based hash of (seed, tuple, k), so the result does not depend on
  the number of threads.

Both use the same Newton (``one_vertex.polish_and_validate``) and the same rule for "one
physical path" (``one_bounce.store_path``) as the polynomial solver, so differences in the
comparison come from the seeding alone.
"""

import time

import numpy as np

from ..spoly.api import ONE_BOUNCE_CHAINS, SolveReport, SolveResult, compact_paths, validate_inputs
from ..runtime.jit import kernel, parallel_range
from ..spoly.one_bounce import ACCEPT_RESIDUAL, CHUNK, MAX_PATHS_ONE_BOUNCE, store_path
from ..paths.one_vertex import geometric_normal, polish_and_validate, triangle_frame
from ..geometry.vec3 import dot, madd, row, sub

NEWTON_STEPS = 20  # MNEE's usual iteration budget


@kernel(inline="always")
def _splitmix64(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    z = x
    z = ((z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    z = ((z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    return z ^ (z >> np.uint64(31))


@kernel(inline="always")
def _uniform(seed, t, k, j):
    """A uniform number in [0, 1) from (seed, tuple, sample, coordinate), thread-independent."""
    h = _splitmix64(np.uint64(seed) * np.uint64(0x100000001B3) + np.uint64(t) * np.uint64(64) + np.uint64(2 * k + j))
    return float(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@parallel_range("x_start", CHUNK)
def _seeded_newton_batch(refract, mode, n_seeds, seed, x_start, x_end, P, N, eta, out_uv, out_count, stats, first, last):
    """mode 0: Path Cuts seeds (centroid, + line crossing for T); mode 1: n_seeds random seeds."""
    n = x_start.shape[0]
    for c in range(first, last):
        buf = np.zeros((5, MAX_PATHS_ONE_BOUNCE + 1))
        for t in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            x0 = row(x_start, t)
            x2 = row(x_end, t)
            p0, e1, e2, n0, m1, m2 = triangle_frame(P[t, 0], N[t, 0])
            ng, area2 = geometric_normal(e1, e2)
            count = 0
            tried = 0
            if area2 > 0.0:
                total = n_seeds if mode == 1 else (2 if refract else 1)
                for k in range(total):
                    if mode == 1:
                        a = _uniform(seed, t, k, 0)
                        b = _uniform(seed, t, k, 1)
                        if a + b > 1.0:  # uniform on the triangle by folding the square
                            a = 1.0 - a
                            b = 1.0 - b
                        u, v = a, b
                    elif k == 0:
                        u, v = 1.0 / 3.0, 1.0 / 3.0
                    else:
                        # Where the straight line x0 -> x2 crosses the triangle's plane.
                        w = sub(x2, x0)
                        denom = dot(w, ng)
                        if denom == 0.0:
                            continue
                        xc = madd(x0, w, dot(sub(p0, x0), ng) / denom)
                        rel = sub(xc, p0)
                        d11 = dot(e1, e1)
                        d12 = dot(e1, e2)
                        d22 = dot(e2, e2)
                        det = d11 * d22 - d12 * d12
                        u = (dot(rel, e1) * d22 - dot(rel, e2) * d12) / det
                        v = (d11 * dot(rel, e2) - d12 * dot(rel, e1)) / det
                    tried += 1
                    ok, uu, vv, err, sig = polish_and_validate(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta[t],
                                                               NEWTON_STEPS, ACCEPT_RESIDUAL)
                    if ok:
                        count = store_path(uu, vv, err, sig, buf, out_uv[t], count)
            out_count[t] = count
            stats[t, 0] = tried
            stats[t, 1] = count


class _SeededNewton:
    mode = 0
    n_seeds = 1
    seed = 0

    def solve(self, chain, x_start, x_end, P, N, eta, **_ignored):
        """Same contract as ``SpecularPolynomialSolver.solve`` (R and T)."""
        t0 = time.perf_counter()
        x_start, x_end, P, N, eta = validate_inputs(chain, x_start, x_end, P, N, eta)
        if chain not in ONE_BOUNCE_CHAINS:
            raise ValueError(f"the {self.name} baseline solves {ONE_BOUNCE_CHAINS} only, not {chain!r}")
        report = SolveReport(solver=self.name, chain=chain, tuples=x_start.shape[0])
        n = x_start.shape[0]
        out_uv = np.zeros((n, MAX_PATHS_ONE_BOUNCE, 2))
        out_count = np.zeros(n, dtype=np.int64)
        stats = np.zeros((n, 2), dtype=np.int64)
        t1 = time.perf_counter()
        if n:
            _seeded_newton_batch(chain == "T", self.mode, self.n_seeds, self.seed, x_start, x_end, P, N, eta, out_uv, out_count, stats)
        t2 = time.perf_counter()
        tuple_index, uv = compact_paths(out_uv, out_count)
        report.candidates = int(stats[:, 0].sum())
        report.paths = int(tuple_index.shape[0])
        report.overflow = int(np.count_nonzero(out_count > MAX_PATHS_ONE_BOUNCE))
        report.seconds = {"prepare": t1 - t0, "solve": t2 - t1, "compact": time.perf_counter() - t2}
        return SolveResult(tuple_index, uv, report)


class NewtonSolver(_SeededNewton):
    """MNEE / Newton from Path Cuts' deterministic seeds (centroid; line crossing for T)."""

    name = "newton"


class SMSSolver(_SeededNewton):
    """Biased Specular Manifold Sampling: ``seeds`` random Newton seeds per tuple."""

    name = "sms"
    mode = 1

    def __init__(self, seeds=16, seed=0):
        if not 1 <= int(seeds) <= 4096:
            raise ValueError("seeds must be in [1, 4096]")
        self.n_seeds = int(seeds)
        self.seed = int(seed) & 0x7FFFFFFF
