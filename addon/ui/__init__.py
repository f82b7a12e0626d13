"""Blender UI layer: properties, operators, panels.  Thin: no maths here.

:func:`register` first points numba's on-disk kernel cache at the extension's user directory
(``bpy.utils.extension_path_user(<extension>, path="numba_cache")``) and only then registers
the classes; nothing here imports numba or the solver, so registration stays fast and works
even where numba is missing (the operators report that instead).
"""

from . import numba_cache, operators, panels, properties, state

#: Registered in this order, unregistered in reverse.
classes = properties.classes + (
    operators.CAUSTICS_OT_prepare_solver,
    operators.CAUSTICS_OT_bake,
    operators.CAUSTICS_OT_clear,
) + panels.classes


def register():
    import bpy

    numba_cache.configure()
    state.forget_numba_check()
    state.STATE.reset()
    for cls in classes:
        bpy.utils.register_class(cls)
    properties.register_properties()


def unregister():
    import bpy

    properties.unregister_properties()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
    state.STATE.reset()
    numba_cache.restore()
