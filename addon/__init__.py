"""Caustic Bake: the add-on package (ui -> bake -> solver).

Importing this package is cheap and never imports bpy or numba: the solver core is usable
without Blender, and Blender registration goes through :func:`register`.
"""


def register():
    """Register the Blender classes (called by the extension root ``__init__``)."""
    from . import ui

    ui.register()


def unregister():
    """Unregister everything :func:`register` added."""
    from . import ui

    ui.unregister()
