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
from numba import njit  # noqa: E402
import numpy as np  # noqa: E402


def _compile_without_literals(dispatcher):
    """Make calls from other kernels compile ``dispatcher`` for the plain types of their
    arguments.  Numba types a constant argument in jitted code as a literal (``0`` as
    ``Literal[int](0)``, ``True`` as ``Literal[bool](True)``) and compiles a separate
    specialisation for each literal value; every specialisation re-optimises the callee's
    whole call tree.  The kernels never branch on a literal's type, so one specialisation per
    plain signature gives the same machine arithmetic for a fraction of the compile time."""
    from numba.core import types

    resolve = getattr(dispatcher, "get_call_template", None)
    if resolve is None:  # NUMBA_DISABLE_JIT=1 (debugging in plain Python): a plain function
        return dispatcher

    def get_call_template(args, kws):
        return resolve(tuple(types.unliteral(a) for a in args), {k: types.unliteral(v) for k, v in kws.items()})

    dispatcher.get_call_template = get_call_template
    return dispatcher


def kernel(*args, refcounted=True, **kwargs):
    """``numba.njit`` with the project defaults: cached, no Python fallback, fastmath off,
    one specialisation per plain signature (:func:`_compile_without_literals`).

    fastmath stays off on purpose: the root finder and the path validation rely on IEEE
    semantics (NaN checks, exact zero tests, signed comparisons).

    ``refcounted=False`` compiles without numba's reference counting (NRT): array arguments
    and row views are borrowed, so a call or a view costs no atomic NRT_incref / NRT_decref
    pair.  In the per-tuple solver kernels those pairs were a quarter of the time.  Only for
    kernels that neither allocate arrays nor return them (a returned array would be freed
    by the caller's decref while still in use).
    """
    kwargs.setdefault("cache", True)
    kwargs.setdefault("nogil", True)
    if not refcounted:
        kwargs["_nrt"] = False
    if args and callable(args[0]):
        return _compile_without_literals(njit(**kwargs)(args[0]))
    decorate = njit(*args, **kwargs)
    return lambda function: _compile_without_literals(decorate(function))


def set_num_threads(n):
    """Set the number of threads the parallel kernels use (1 = single core)."""
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


def get_num_threads():
    return numba.get_num_threads()


_POOL = None
_POOL_SIZE = 0


def _pool(threads):
    """The process's worker threads for :func:`run_chunks`, grown on demand, reused so a call
    costs microseconds rather than a thread start-up."""
    from concurrent.futures import ThreadPoolExecutor

    global _POOL, _POOL_SIZE
    if _POOL is None or _POOL_SIZE < threads:
        _POOL = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="caustic-kernel")
        _POOL_SIZE = threads
    return _POOL


def run_chunks(chunk_kernel, args, n, chunks=256, serial_below=2):
    """Call ``chunk_kernel(*args, a, b)`` over [0, n) cut into about ``chunks`` ranges [a, b),
    on as many threads as numba's thread count (:func:`set_num_threads`).

    This is how the solver runs independent work in parallel instead of ``prange``: the kernel
    must release the GIL (``kernel`` sets nogil) and write disjoint outputs per index, so the
    result does not depend on the thread count.  A ``parallel=True`` wrapper compiles its
    body as a gufunc and re-optimises the whole call tree below it two more times (about 4x
    the compile time of the serial kernel, ~20 s for the big solvers); a thread pool costs no
    compilation.  Arrays reach the kernel C-contiguous and writeable (:func:`_writeable_c_arrays`).
    Fewer than ``serial_below`` indices run on the calling thread (handing a small range to
    the pool costs more than it saves).  Must not be called from inside a chunk kernel."""
    args, written_back = _writeable_c_arrays(args)
    size = max(1, -(-n // max(1, int(chunks))))
    ranges = [(a, min(n, a + size)) for a in range(0, n, size)]
    threads = get_num_threads()
    if threads <= 1 or len(ranges) <= 1 or n < serial_below:
        for a, b in ranges:
            chunk_kernel(*args, a, b)
    else:
        work = iter(ranges)  # shared: each worker takes the next range (next() holds the GIL)
        futures = [_pool(threads).submit(_drain, chunk_kernel, args, work) for _ in range(min(threads, len(ranges)))]
        for f in futures:
            f.result()
    for original, copy in written_back:
        original[...] = copy


def run_calls(call, items):
    """[call(item) for item in items], the calls spread over numba's thread count (each must
    release the GIL: a ``kernel`` call); the results in the order of ``items``, whatever thread
    ran them.  For kernels that return their own variable-sized output per call (:func:`run_chunks`
    is for kernels writing disjoint parts of given arrays)."""
    items = list(items)
    threads = get_num_threads()
    if threads <= 1 or len(items) <= 1:
        return [call(item) for item in items]
    return list(_pool(threads).map(call, items))


def _drain(chunk_kernel, args, work):
    for a, b in work:
        chunk_kernel(*args, a, b)


def _writeable_c_arrays(args):
    """``args`` with every array C-contiguous and writeable, so that a kernel has one
    signature per argument dtype and rank (numba compiles a kernel and its whole call tree
    again for an F-ordered, strided or read-only array); an array copied for that which the
    caller can write is listed with its copy, to be written back after the kernel."""
    out = list(args)
    written_back = []
    for i, a in enumerate(args):
        if isinstance(a, np.ndarray) and a.ndim and not (a.flags.c_contiguous and a.flags.writeable):
            out[i] = np.array(a, order="C")
            if a.flags.writeable:
                written_back.append((a, out[i]))
    return out, written_back


def parallel_range(count, per=1, serial_below=2):
    """Decorator for a function ``f(*args, first, last)`` that does the independent work items
    [first, last) of a range: it is compiled as a kernel, and ``f(*args)`` becomes a Python
    function running it over the whole range with :func:`run_chunks` (the compiled kernel is
    ``f.chunk_kernel``).

    ``count`` names the argument whose length (first dimension) gives the range, one index per
    ``per`` of its rows; or it is a function of the arguments by name returning the number of
    indices; fewer than ``serial_below`` indices run on the calling thread.  The kernel is compiled with ``error_model="numpy"``: x / 0 gives inf or NaN, not
    an exception, as in numba's own parallel loops."""
    import functools
    import inspect

    def wrap(function):
        chunk_kernel = kernel(error_model="numpy")(function)
        names = list(inspect.signature(function).parameters)[:-2]
        position = names.index(count) if isinstance(count, str) else None

        @functools.wraps(function)
        def run(*args):
            if position is not None:
                n = -(-len(args[position]) // per)
            else:
                n = int(count(dict(zip(names, args))))
            run_chunks(chunk_kernel, args, n, serial_below=serial_below)

        run.chunk_kernel = chunk_kernel
        return run

    return wrap
