"""Install a built extension zip into a throw-away Blender user profile and exercise it.

Run by tests/packaging/test_packaging.py in a subprocess (never imported by pytest: the name does not
start with ``test_``), because the user profile is chosen by environment variables that the
``bpy`` module reads once, at import::

    BLENDER_USER_RESOURCES=<tmp> python tests/packaging/_install_check.py <zip> <result.json> --numba=MODE

The development venv has its own numba, and on a fresh install Blender *appends* the
extensions' wheel site-packages to ``sys.path``, so the venv's numba would be found first and
hide the bundled one.  ``--numba`` decides where numba/llvmlite may come from:

- ``bundle``: only from the temporary profile (the wheels Blender extracted from the zip),
  as in a real Blender that has no numba of its own;
- ``none``: nowhere (numba missing: the operator must fail cleanly);
- ``any``: no restriction (whatever ``sys.path`` finds first).

``--reuse``: the zip was installed into this profile by an earlier run; only enable it (a new
Blender session), so the kernels should now load from the cache in the extension user dir.

``--bake=BLEND``: after the solver step, the headless bake as a TD runs it,
``blender -b BLEND --python-expr "import bpy; bpy.ops.caustics.bake()"``: open BLEND, call
``bpy.ops.caustics.bake()`` (background mode: synchronous, then saves BLEND), and record what
it made; then open the saved file again and record what is in it.

Writes a JSON report; the test makes the assertions.  Exits 3 if the profile is not the
temporary one (so that a real user profile is never touched).
"""

import json
import os
import sys
import time
import traceback

PKG = "bl_ext.user_default.caustic_bake"
UI_TYPES = ("CAUSTICS_OT_bake", "CAUSTICS_OT_clear", "RENDER_PT_caustic_bake", "OBJECT_PT_caustic_bake")


class _RestrictNumba:
    """Meta-path finder: numba/llvmlite only from folders under ``allowed`` (None: nowhere)."""

    def __init__(self, allowed):
        self.allowed = allowed

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in ("numba", "llvmlite"):
            return None  # submodules follow their package's __path__
        if self.allowed is not None:
            from importlib.machinery import PathFinder

            dirs = [p for p in sys.path if os.path.realpath(p or ".").startswith(self.allowed + os.sep)]
            spec = PathFinder.find_spec(fullname, dirs)
            if spec is not None:
                return spec
        raise ModuleNotFoundError("No module named {!r} (hidden by the test)".format(fullname), name=fullname)


def bake_step(bpy, blend, step):
    """The headless bake: open, bpy.ops.caustics.bake(), then what the saved file holds."""
    bpy.ops.wm.open_mainfile(filepath=blend)
    mtime = os.stat(blend).st_mtime_ns
    t0 = time.perf_counter()
    try:
        bake_result, bake_error = sorted(bpy.ops.caustics.bake()), None
    except RuntimeError as ex:
        bake_result, bake_error = None, str(ex)
    seconds = time.perf_counter() - t0
    images = {img.name: [os.path.realpath(bpy.path.abspath(img.filepath)), list(img.size)] for img in bpy.data.images}
    folder = os.path.join(os.path.dirname(blend), "caustics")
    step(
        "bake",
        bake_result=bake_result,
        bake_error=bake_error,
        bake_seconds=seconds,
        bake_images=images,
        bake_node_groups=sorted(g.name for g in bpy.data.node_groups),
        bake_files=sorted(os.path.relpath(os.path.join(d, f), folder)
                          for d, _, fs in os.walk(folder) for f in fs) if os.path.isdir(folder) else None,
        bake_blend_saved=os.stat(blend).st_mtime_ns != mtime,
    )
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=blend)
    floor_mat = None
    for ob in bpy.data.objects:
        for slot in ob.material_slots:
            if slot.material is not None and slot.material.node_tree is not None and any(
                    n.type == "GROUP" and n.node_tree is not None and n.node_tree.name == "CausticBake"
                    for n in slot.material.node_tree.nodes):
                floor_mat = [ob.name, slot.material.name]
    step(
        "reopen",
        reopened_images=sorted(img.name for img in bpy.data.images),
        reopened_node_groups=sorted(g.name for g in bpy.data.node_groups),
        reopened_material_with_group=floor_mat,
    )


def main():
    zip_path, out_path = os.path.abspath(sys.argv[1]), os.path.abspath(sys.argv[2])
    modes = [a.partition("=")[2] for a in sys.argv[3:] if a.startswith("--numba=")]
    mode = modes[-1] if modes else "any"
    reuse = "--reuse" in sys.argv[3:]
    bakes = [a.partition("=")[2] for a in sys.argv[3:] if a.startswith("--bake=")]
    bake_blend = os.path.abspath(bakes[-1]) if bakes else None
    resources = os.environ.get("BLENDER_USER_RESOURCES")
    if not resources or not os.path.isdir(resources):
        print("BLENDER_USER_RESOURCES must name an existing (temporary) folder", file=sys.stderr)
        return 3
    resources = os.path.realpath(resources)
    site_packages = os.path.join(
        resources, "extensions", ".local", "lib",
        "python{}.{}".format(*sys.version_info[:2]), "site-packages",
    )
    if mode == "bundle":
        sys.meta_path.insert(0, _RestrictNumba(resources))
    elif mode == "none":
        sys.meta_path.insert(0, _RestrictNumba(None))
    elif mode != "any":
        print("unknown --numba mode {!r}".format(mode), file=sys.stderr)
        return 2

    report = {"steps": [], "numba_mode": mode, "reuse": reuse}

    def step(name, **values):
        report["steps"].append(name)
        report.update(values)

    import bpy  # after the environment is set up

    extensions_dir = os.path.realpath(bpy.utils.user_resource("EXTENSIONS"))
    if os.path.commonpath([extensions_dir, resources]) != resources:
        print("refusing: the extensions folder {} is not under {}".format(extensions_dir, resources), file=sys.stderr)
        return 3
    step("import_bpy", extensions_dir=extensions_dir, numba_imported_before=("numba" in sys.modules))

    try:
        if reuse:  # installed by an earlier run on this profile: only enable it
            result = bpy.ops.preferences.addon_enable(module=PKG)
        else:
            result = bpy.ops.extensions.package_install_files(
                filepath=zip_path, repo="user_default", enable_on_install=True,
            )
        step("install", install_result=sorted(result))
        addons = bpy.context.preferences.addons
        step(
            "installed",
            enabled_after_install=PKG in addons,
            package_dir=os.path.join(extensions_dir, "user_default", "caustic_bake"),
            package_dir_exists=os.path.isfile(
                os.path.join(extensions_dir, "user_default", "caustic_bake", "__init__.py")
            ),
            site_packages=site_packages,
            site_packages_content=sorted(os.listdir(site_packages)) if os.path.isdir(site_packages) else None,
            operator_registered=hasattr(bpy.types, "CAUSTICS_OT_prepare_solver"),
            operator_in_ops="prepare_solver" in dir(bpy.ops.caustics),
            ui_registered=[hasattr(bpy.types, n) for n in UI_TYPES] + [
                hasattr(bpy.types.Scene, "caustic_bake"), hasattr(bpy.types.Object, "caustic_bake")],
            cache_env=os.environ.get("NUMBA_CACHE_DIR"),
            expected_cache_dir=bpy.utils.extension_path_user(PKG, path="numba_cache"),
            numba_imported_after_enable=("numba" in sys.modules),
        )
        package_dir = report["package_dir"]

        t0 = time.perf_counter()
        try:
            op_result = sorted(bpy.ops.caustics.prepare_solver())
            op_error = None
        except RuntimeError as ex:  # an ERROR report from the operator
            op_result, op_error = None, str(ex)
        op_seconds = time.perf_counter() - t0
        cache_dir = report["expected_cache_dir"]
        cache_files = {}  # relative path -> modification time (ns)
        for dirpath, _dirs, files in os.walk(cache_dir):
            for f in files:
                path = os.path.join(dirpath, f)
                cache_files[os.path.relpath(path, cache_dir)] = os.stat(path).st_mtime_ns
        numba = sys.modules.get("numba")
        llvmlite = sys.modules.get("llvmlite")
        step(
            "prepare_solver",
            operator_result=op_result,
            operator_error=op_error,
            numba_file=os.path.realpath(numba.__file__) if numba else None,
            numba_version=getattr(numba, "__version__", None),
            llvmlite_file=os.path.realpath(llvmlite.__file__) if llvmlite else None,
            numba_cache_dir=numba.config.CACHE_DIR if numba else None,
            operator_seconds=op_seconds,
            cache_files=cache_files,
            # numba cache files inside the installed package (which must not be written to).
            package_caches=sorted(
                os.path.relpath(os.path.join(d, f), package_dir)
                for d, _dirs, files in os.walk(package_dir) for f in files
                if f.endswith((".nbi", ".nbc"))
            ) + (([".numba_cache"]) if os.path.exists(os.path.join(package_dir, ".numba_cache")) else []),
        )

        if mode == "none":  # the bake is greyed out, saying why
            try:
                bpy.ops.caustics.bake()
                step("bake_without_numba", bake_poll_error=None)
            except RuntimeError as ex:
                step("bake_without_numba", bake_poll_error=str(ex))
        if bake_blend:
            bake_step(bpy, bake_blend, step)

        result = bpy.ops.preferences.addon_disable(module=PKG)
        step(
            "disable",
            disable_result=sorted(result),
            enabled_after_disable=PKG in bpy.context.preferences.addons,
            operator_registered_after_disable=hasattr(bpy.types, "CAUSTICS_OT_prepare_solver"),
            operator_in_ops_after_disable="prepare_solver" in dir(bpy.ops.caustics),
            ui_registered_after_disable=[hasattr(bpy.types, n) for n in UI_TYPES] + [
                hasattr(bpy.types.Scene, "caustic_bake"), hasattr(bpy.types.Object, "caustic_bake")],
            cache_env_after_disable=os.environ.get("NUMBA_CACHE_DIR"),
        )
    except Exception:
        report["exception"] = traceback.format_exc()

    with open(out_path, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
