"""Numba set-up shared by every kernel module of the solver.

The on-disk cache of compiled kernels (``cache=True``) must be configured before numba is
imported: numba reads ``NUMBA_CACHE_DIR`` once, at import.  In Blender the UI layer calls
:func:`configure_cache` with the extension's user directory before the solver is imported;
in development the cache lives in ``<repo>/.numba_cache``.
"""

import os

_SOLVER = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # addon/solver
_PROJECT_CACHE = os.path.join(os.path.dirname(os.path.dirname(_SOLVER)), ".numba_cache")


def source_fingerprint():
    """Hash of every solver source file, subpackages included (sorted relative paths).

    Numba's on-disk cache is keyed per file: when a kernel inlines a function from another
    module and only that module changes, the caller's stale machine code is still loaded.
    Caching under a folder named by this fingerprint makes any source change (an edit, an
    extension update) a clean recompile.
    """
    import hashlib

    digest = hashlib.sha1()
    folder = _SOLVER
    files = []
    for root, dirs, names in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        files.extend(os.path.relpath(os.path.join(root, n), folder).replace(os.sep, "/") for n in names if n.endswith(".py"))
    for name in sorted(files):  # relative paths: subpackages (bounds/) count too
        digest.update(name.encode())
        with open(os.path.join(folder, name), "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()[:16]


_FINGERPRINT = source_fingerprint()
_base_directory = None


def configure_cache(directory=None):
    """Point numba's kernel cache at ``directory``/<source fingerprint>.

    ``directory`` defaults to the one configured before, then ``NUMBA_CACHE_DIR`` (set by the
    Blender UI layer to the extension's user directory), then ``<repo>/.numba_cache``.  Cache
    folders of other fingerprints (older sources) in it are removed.  Takes full effect if
    called before numba is first imported; afterwards it re-points ``numba.config`` for
    kernels not yet compiled.
    """
    import shutil
    import sys

    global _base_directory
    if directory is None:
        directory = _base_directory or os.environ.get("NUMBA_CACHE_DIR") or _PROJECT_CACHE
        if os.path.basename(os.path.normpath(directory)) == _FINGERPRINT:
            directory = os.path.dirname(os.path.normpath(directory))
    _base_directory = directory
    os.makedirs(directory, exist_ok=True)
    for name in os.listdir(directory):
        stale = os.path.join(directory, name)
        if name != _FINGERPRINT and len(name) == 16 and all(c in "0123456789abcdef" for c in name) and os.path.isdir(stale):
            shutil.rmtree(stale, ignore_errors=True)
    actual = os.path.join(directory, _FINGERPRINT)
    os.makedirs(actual, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = actual
    if "numba" in sys.modules:
        import numba

        numba.config.CACHE_DIR = actual
    return actual


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


def run_chunks(chunk_kernel, args, n, chunks=256):
    """Call ``chunk_kernel(*args, a, b)`` over [0, n) cut into about ``chunks`` ranges [a, b),
    on as many Python threads as numba's thread count.  The kernel must release the GIL
    (``kernel`` sets nogil): a thread pool costs no compilation, where a ``parallel=True``
    wrapper takes seconds to compile."""
    from concurrent.futures import ThreadPoolExecutor

    size = max(1, -(-n // max(1, int(chunks))))
    ranges = [(a, min(n, a + size)) for a in range(0, n, size)]
    threads = get_num_threads()
    if threads <= 1 or len(ranges) <= 1:
        for a, b in ranges:
            chunk_kernel(*args, a, b)
        return
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for f in [pool.submit(chunk_kernel, *args, a, b) for a, b in ranges]:
            f.result()
