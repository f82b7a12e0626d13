"""Numba set-up shared by every kernel module of the solver.

The on-disk cache of compiled kernels (``cache=True``) must be configured before numba is
imported: numba reads ``NUMBA_CACHE_DIR`` once, at import.  In Blender the UI layer calls
:func:`configure_cache` with the extension's user directory before the solver is imported;
in development the cache lives in ``<repo>/.numba_cache``.
"""

import os

_PROJECT_CACHE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), ".numba_cache")


def configure_cache(directory=None):
    """Point numba's kernel cache at ``directory`` (default: the project-local folder).

    Has an effect only if called before numba is first imported, or to re-point it
    afterwards through ``numba.config`` for kernels not yet compiled.
    """
    directory = directory or os.environ.get("NUMBA_CACHE_DIR") or _PROJECT_CACHE
    os.makedirs(directory, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = directory
    import sys

    if "numba" in sys.modules:
        import numba

        numba.config.CACHE_DIR = directory
    return directory


configure_cache()

import numba  # noqa: E402  (after the cache directory is set)
from numba import njit, prange  # noqa: E402,F401


def kernel(*args, **kwargs):
    """``numba.njit`` with the project defaults: cached, no Python fallback, fastmath off.

    fastmath stays off on purpose: the root finder and the path validation rely on IEEE
    semantics (NaN checks, exact zero tests, signed comparisons).
    """
    kwargs.setdefault("cache", True)
    kwargs.setdefault("nogil", True)
    if args and callable(args[0]):
        return njit(**kwargs)(args[0])
    return njit(*args, **kwargs)


def set_num_threads(n):
    """Set the number of threads the parallel kernels use (1 = single core)."""
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


def get_num_threads():
    return numba.get_num_threads()
