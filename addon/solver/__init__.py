"""Caustic Bake solver core: plain numpy + Numba, never imports bpy.

Public API (see CONTRACT.md):
- :func:`solve_tuples` — all specular paths through triangle tuples (Specular Polynomials,
  Fan et al. 2024), chains "R" and "T".
- :func:`path_irradiance` — irradiance per unit light intensity of each solved path.
- :class:`SpecularPolynomialSolver`, :class:`SolveResult`, :class:`SolveReport` — the solver
  interface shared with the baselines.
- :func:`warm_up` — compile (or load from the cache) every kernel ahead of the first bake.
"""

from .runtime import jit  # noqa: F401  (configures the Numba cache before any kernel module loads)
from .spoly.api import SolveReport, SolveResult, SpecularPolynomialSolver, solve_tuples, validate_inputs  # noqa: F401
from .geometry.optics import fresnel_conductor, fresnel_dielectric  # noqa: F401
from .paths.irradiance import PathIrradiance, path_irradiance  # noqa: F401


def warm_up(bounces=2):
    """Compile (or load from Numba's cache) the solver kernels; returns the seconds taken.

    Called ahead of the first bake (the Blender operator "Prepare Caustic Solver", the CLI)
    so that compile latency is not paid in the middle of a bake.  ``bounces=1`` compiles the
    one-bounce chains only (R, T: ~30 s cold); 2 also the two-bounce ones (RR, RT, TR, TT
    share one kernel: ~90 s more cold, well under a second from the cache).
    """
    import time

    import numpy as np

    t0 = time.perf_counter()
    P = np.array([[[[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]]]])
    N = np.array([[[[0.0, 1.0, 0.0]] * 3]])
    x0 = np.array([[0.1, 1.0, 0.0]])
    for chain, x2 in (("R", [[0.3, 2.0, 0.1]]), ("T", [[0.3, -2.0, 0.1]])):
        ti, uv = solve_tuples(chain, x0, np.array(x2), P, N, 1.5)
        path_irradiance(chain, x0, np.array(x2), P, N, 1.5, ti, uv)
    if bounces >= 2:
        # a floor mirror under a ceiling mirror: one RR path (x0 -> floor -> ceiling -> x3)
        ceiling = P[0, 0] * np.array([1.0, 0.0, 1.0]) + np.array([0.0, 3.0, 0.0])
        P2 = np.stack([P[0, 0], ceiling[::-1]])[None]
        N2 = np.stack([N[0, 0], -N[0, 0]])[None]
        x3 = np.array([[0.4, 1.5, 0.2]])
        for chain in ("RR", "TT"):
            ti, uv = solve_tuples(chain, x0, x3, P2, N2, 1.5)
            path_irradiance(chain, x0, x3, P2, N2, 1.5, ti, uv)
    return time.perf_counter() - t0
