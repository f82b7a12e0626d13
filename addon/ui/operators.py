"""Operators.  Thin: they call into addon.solver / addon.bake and report; no maths here."""

import bpy

_MISSING_NUMBA = (
    "Caustic Bake needs numba and llvmlite, which are bundled with the extension, "
    "but they could not be imported ({}). Reinstall the extension package built for "
    "this platform and Blender version"
)


def _is_numba_import_error(ex):
    """True if ``ex`` (an ImportError) is about numba/llvmlite themselves (missing or broken)."""
    name = (getattr(ex, "name", None) or "").split(".")[0]
    return name in ("numba", "llvmlite") or "numba" in str(ex).lower() or "llvmlite" in str(ex).lower()


class CAUSTICS_OT_prepare_solver(bpy.types.Operator):
    """Compile (or load from the cache) the solver kernels now, so that the first bake starts at once"""

    bl_idname = "caustics.prepare_solver"
    bl_label = "Prepare Caustic Solver"
    bl_options = {"REGISTER"}

    def execute(self, context):
        from . import numba_cache_dir

        try:
            # Lazy: numba is imported only when the solver is needed, after register()
            # pointed its kernel cache at the extension's user directory.
            import llvmlite  # noqa: F401
            import numba  # noqa: F401

            from .. import solver

            if numba_cache_dir:
                from ..solver.jit import configure_cache

                configure_cache(numba_cache_dir)
            seconds = solver.warm_up()
        except ImportError as ex:
            if _is_numba_import_error(ex):
                self.report({"ERROR"}, _MISSING_NUMBA.format(ex))
            else:
                import traceback

                traceback.print_exc()
                self.report({"ERROR"}, "Caustic Bake: could not load the solver: {}".format(ex))
            return {"CANCELLED"}
        except Exception as ex:  # a bug: say so in the UI, keep the details in the console
            import traceback

            traceback.print_exc()
            self.report({"ERROR"}, "Caustic Bake: preparing the solver failed: {}".format(ex))
            return {"CANCELLED"}

        self.report({"INFO"}, "Caustic solver ready ({:.1f} s)".format(seconds))
        return {"FINISHED"}
