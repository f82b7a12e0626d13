"""Where numba keeps its compiled kernels when the add-on runs as an installed extension.

:func:`configure` (at registration) points ``NUMBA_CACHE_DIR`` at the extension's user
directory (``bpy.utils.extension_path_user(<extension>, path="numba_cache")``) before anything
imports numba; :func:`restore` (at unregistration) puts the previous value back.  A leaf module:
the operators read :func:`directory` without importing the UI package.
"""

import os
import sys

#: The numba cache directory chosen at registration (None in development: the solver then
#: uses ``<repo>/.numba_cache``, see ``addon.solver.runtime.jit``).
numba_cache_dir = None
_previous_cache_env = None


def extension_package():
    """The extension's root package (``bl_ext.<repo>.caustic_bake``), or None when this add-on
    is not running as an installed Blender extension (development, tests)."""
    parts = (__package__ or "").split(".")
    # __package__ is "<root>.addon.ui"; an extension root has exactly three components.
    if len(parts) == 5 and parts[0] == "bl_ext" and parts[3:] == ["addon", "ui"]:
        return ".".join(parts[:3])
    return None


def configure():
    """Send numba's kernel cache to the extension user directory.

    numba reads ``NUMBA_CACHE_DIR`` when it is first imported, and ``addon.solver.runtime.jit`` uses the
    same variable as its default; setting it here, before anything imports the solver, is what
    ``jit.configure_cache(directory)`` needs without importing numba at registration.  If
    numba was already imported (by another add-on), re-point it through ``configure_cache``.
    """
    global numba_cache_dir, _previous_cache_env
    package = extension_package()
    if package is None:
        return None
    import bpy

    directory = bpy.utils.extension_path_user(package, path="numba_cache", create=True)
    if not directory:
        return None
    _previous_cache_env = os.environ.get("NUMBA_CACHE_DIR")
    os.environ["NUMBA_CACHE_DIR"] = directory
    numba_cache_dir = directory
    if "numba" in sys.modules:
        try:
            from ..solver.runtime.jit import configure_cache

            configure_cache(directory)
        except Exception as ex:  # never block registration; the operator reports problems
            print("Caustic Bake: could not configure the numba cache: {}".format(ex))
    return directory


def directory():
    """The numba cache directory chosen at registration, or None."""
    return numba_cache_dir


def restore():
    """Undo :func:`configure`: NUMBA_CACHE_DIR as it was before, when it is still ours."""
    global numba_cache_dir, _previous_cache_env
    current = os.environ.get("NUMBA_CACHE_DIR")
    # addon.solver.runtime.jit caches under <our directory>/<source fingerprint>: that is ours too.
    ours = current is not None and numba_cache_dir is not None and (
        current == numba_cache_dir or os.path.dirname(os.path.normpath(current)) == os.path.normpath(numba_cache_dir))
    if ours:
        if _previous_cache_env is None:
            os.environ.pop("NUMBA_CACHE_DIR", None)
        else:
            os.environ["NUMBA_CACHE_DIR"] = _previous_cache_env
    numba_cache_dir = None
    _previous_cache_env = None
