"""Caustic Bake solver core: plain numpy + Numba, never imports bpy.

Public API (see CONTRACT.md):
- :func:`solve_tuples` — all specular paths through triangle tuples (Specular Polynomials,
  Fan et al. 2024), chains "R" and "T".
- :func:`path_irradiance` — irradiance per unit light intensity of each solved path.
- :class:`SpecularPolynomialSolver`, :class:`SolveResult`, :class:`SolveReport` — the solver
  interface shared with the baselines.
- :func:`warm_up` — compile (or load from the cache) every kernel ahead of the first bake.
"""

from . import jit  # noqa: F401  (configures the Numba cache before any kernel module loads)
from .api import SolveReport, SolveResult, SpecularPolynomialSolver, solve_tuples, validate_inputs  # noqa: F401
from .irradiance import PathIrradiance, fresnel_conductor, fresnel_dielectric, path_irradiance  # noqa: F401


def warm_up():
    """Compile (or load from Numba's cache) every solver kernel; returns the seconds taken.

    Called ahead of the first bake (the Blender operator "Prepare Caustic Solver", the CLI)
    so that compile latency is not paid in the middle of a bake.
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
    return time.perf_counter() - t0
