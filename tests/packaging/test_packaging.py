"""The extension package: build with Blender's tool, validate, install into a throw-away
Blender profile, run the first operator, disable.

The zips are built once per session by tools/build_extension.py (the numba/llvmlite wheels,
~300 MB, are downloaded the first time into build/wheel_cache/ and reused afterwards).
Installing happens in subprocesses (tests/packaging/_install_check.py) whose BLENDER_USER_RESOURCES is
a temporary folder, so neither this process's bpy state nor the user's profile is touched.
"""

import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tools"))

import build_extension  # noqa: E402

pytestmark = pytest.mark.bpy  # Blender's extension tool ships inside the bpy package

PKG = "bl_ext.user_default.caustic_bake"
PLATFORM_WHEEL_TAG = {
    "linux-x64": re.compile(r"manylinux.*_x86_64\.whl$"),
    "windows-x64": re.compile(r"win_amd64\.whl$"),
    "macos-arm64": re.compile(r"macosx_\d+_\d+_arm64\.whl$"),
}
# every OpenCL source of the tree (the programs and the files they include): all must ship
OPENCL_SOURCES = sorted(os.path.relpath(p, ROOT).replace(os.sep, "/")
                        for p in glob.glob(os.path.join(ROOT, "addon", "solver", "opencl", "*.cl")))


@pytest.fixture(scope="session")
def zips():
    """``{platform: zip path}`` of a fresh build (one zip per platform)."""
    return build_extension.build()


def _names(path):
    with zipfile.ZipFile(path) as zf:
        return zf.namelist()


def _manifest(path):
    with zipfile.ZipFile(path) as zf:
        return tomllib.loads(zf.read("blender_manifest.toml").decode("utf-8"))


def test_committed_manifest_is_clean_and_valid():
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as fh:
        manifest = tomllib.load(fh)
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "caustic_bake"
    assert manifest["blender_version_min"] == "4.2.0"
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"]
    assert manifest["permissions"]["files"]
    # Generated at build time only.
    assert "wheels" not in manifest and "platforms" not in manifest
    tool, tags = build_extension.blender_ext_tool()
    proc = subprocess.run(
        [sys.executable, tool, "validate", "--valid-tags", tags, ROOT], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.network
@pytest.mark.slow  # the session's zip build takes ~20 s (and downloads the wheels once)
def test_one_zip_per_platform_each_valid(zips):
    assert set(zips) == set(build_extension.PLATFORMS)
    tool, tags = build_extension.blender_ext_tool()
    for platform, path in zips.items():
        assert os.path.getsize(path) > 1_000_000, path
        proc = subprocess.run(
            [sys.executable, tool, "validate", "--valid-tags", tags, path], capture_output=True, text=True
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "Success" in proc.stdout + proc.stderr


@pytest.mark.network
@pytest.mark.slow  # the session's zip build takes ~20 s (and downloads the wheels once)
def test_zip_contents(zips):
    versions = build_extension.pinned_versions()
    for platform, path in zips.items():
        names = _names(path)
        # The add-on itself.
        for required in ("__init__.py", "blender_manifest.toml", "addon/__init__.py",
                         "addon/ui/__init__.py", "addon/ui/operators.py", "addon/ui/panels.py",
                         "addon/ui/properties.py", "addon/ui/state.py", "addon/solver/runtime/jit.py", *OPENCL_SOURCES):
            assert required in names, (platform, required)
        # Nothing from development.
        for name in names:
            top = name.split("/")[0]
            assert top not in ("tests", "bench", "tools", "build", "dist", "sample_blends", "seeds"), name
            assert not any(part.startswith(".") for part in name.split("/")), name  # .venv, .ci, .git, ...
            assert "__pycache__" not in name and not name.endswith((".pyc", ".md", ".zip")), name
            assert not name.startswith("requirements"), name
        # Exactly the wheels of this platform: numba + llvmlite for cp311 and cp313, no numpy.
        wheels = sorted(n for n in names if n.endswith(".whl"))
        assert all(n.startswith("wheels/") for n in wheels)
        assert len(wheels) == 4, wheels
        for wheel in wheels:
            assert PLATFORM_WHEEL_TAG[platform].search(wheel), (platform, wheel)
        for name in ("numba", "llvmlite"):
            for cp in ("cp311", "cp313"):
                prefix = "wheels/{}-{}-{}-{}-".format(name, versions[name], cp, cp)
                assert sum(w.startswith(prefix) for w in wheels) == 1, (platform, prefix, wheels)
        assert not any("numpy" in w for w in wheels)
        # The packaged manifest lists them and the platform.
        manifest = _manifest(path)
        assert manifest["build"]["generated"]["platforms"] == [platform]
        listed = sorted(w.removeprefix("./") for w in manifest["build"]["generated"]["wheels"])
        assert listed == wheels


def _install_check(zip_path, tmp_path, numba_mode, reuse=False, bake=None):
    resources = tmp_path / "blender_user"
    resources.mkdir(exist_ok=reuse)
    out = tmp_path / ("report_reuse.json" if reuse else "report.json")
    env = dict(os.environ)
    for var in ("BLENDER_USER_CONFIG", "BLENDER_USER_SCRIPTS", "BLENDER_USER_DATAFILES",
                "BLENDER_USER_EXTENSIONS", "NUMBA_CACHE_DIR"):
        env.pop(var, None)
    env["BLENDER_USER_RESOURCES"] = str(resources)
    proc = subprocess.run(
        [sys.executable, os.path.join(ROOT, "tests", "packaging", "_install_check.py"), zip_path, str(out),
         "--numba=" + numba_mode] + (["--reuse"] if reuse else []) + (["--bake=" + str(bake)] if bake else []),
        env=env, capture_output=True, text=True, timeout=900, cwd=str(tmp_path),
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    report = json.loads(out.read_text())
    assert "exception" not in report, report["exception"] + "\n" + log
    return os.path.realpath(str(resources)), report, log


def _assert_installed_and_disabled(report, resources):
    assert report["install_result"] == ["FINISHED"]
    assert report["extensions_dir"] == os.path.join(resources, "extensions")
    assert report["package_dir_exists"]
    assert report["enabled_after_install"]
    assert report["operator_registered"] and report["operator_in_ops"]
    assert all(report["ui_registered"]), report["ui_registered"]  # bake, clear, panels, properties
    # Registration points numba's cache at the extension's user directory...
    cache_dir = os.path.join(resources, "extensions", ".user", "user_default", "caustic_bake", "numba_cache")
    assert report["expected_cache_dir"] == cache_dir
    assert report["cache_env"] == cache_dir
    # ... and disabling takes everything away again.
    assert report["disable_result"] == ["FINISHED"]
    assert not report["enabled_after_disable"]
    assert not report["operator_registered_after_disable"]
    assert not report["operator_in_ops_after_disable"]
    assert not any(report["ui_registered_after_disable"]), report["ui_registered_after_disable"]
    assert report["cache_env_after_disable"] is None


@pytest.mark.network
@pytest.mark.slow  # the session's zip build takes ~20 s (and downloads the wheels once)
def test_install_enable_prepare_disable_with_bundled_numba(zips, tmp_path):
    """Fresh install of the linux-x64 zip; numba may come only from the bundled wheels."""
    resources, report, log = _install_check(zips["linux-x64"], tmp_path, "bundle")
    _assert_installed_and_disabled(report, resources)

    # Blender extracted the bundled wheels into the profile's site-packages.
    content = report["site_packages_content"]
    versions = build_extension.pinned_versions()
    assert "numba" in content and "llvmlite" in content, content
    assert "numba-{}.dist-info".format(versions["numba"]) in content, content
    assert "llvmlite-{}.dist-info".format(versions["llvmlite"]) in content, content

    # The operator ran, with the bundled numba, caching kernels in the extension user dir.
    assert report["operator_error"] is None, log
    assert report["operator_result"] == ["FINISHED"], log
    assert report["numba_file"].startswith(report["site_packages"] + os.sep), report["numba_file"]
    assert report["llvmlite_file"].startswith(report["site_packages"] + os.sep), report["llvmlite_file"]
    assert report["numba_version"] == versions["numba"]
    # Kernels are cached in a subfolder named by the solver's source fingerprint.
    assert os.path.dirname(os.path.normpath(report["numba_cache_dir"])) == os.path.normpath(report["expected_cache_dir"])
    cached = report["cache_files"]
    assert any(f.endswith(".nbi") for f in cached), cached
    assert any(f.endswith(".nbc") for f in cached), cached
    assert report["package_caches"] == [], report["package_caches"]

    # A second Blender session on the same profile: enabling alone brings the wheels back,
    # and the kernels load from the cache instead of being compiled again (no cache file is
    # rewritten, none is added).  This session then bakes a sample scene headless.
    blend = tmp_path / "scene" / "mirror_plane.blend"
    blend.parent.mkdir()
    shutil.copy(os.path.join(ROOT, "sample_blends", "mirror_plane.blend"), blend)
    _, again, log = _install_check(zips["linux-x64"], tmp_path, "bundle", reuse=True, bake=blend)
    _assert_installed_and_disabled(again, resources)
    assert again["operator_result"] == ["FINISHED"], log
    assert again["numba_file"] == report["numba_file"]
    assert again["cache_files"] == cached, (sorted(cached), sorted(again["cache_files"]))
    assert again["package_caches"] == []
    print("prepare_solver: {:.1f} s compiling, {:.1f} s from the cache".format(
        report["operator_seconds"], again["operator_seconds"]))

    # The headless bake (blender -b scene.blend --python-expr "import bpy; bpy.ops.caustics.bake()"):
    # the installed extension baked, wrote the texture next to the .blend and saved the .blend.
    assert again["bake_error"] is None, again["bake_error"] + "\n" + log
    assert again["bake_result"] == ["FINISHED"], log
    assert again["bake_node_groups"] == ["CausticBake"]
    # Textures go to //caustics/<blend name>/<receiver>.exr (addon/bake/names.texture_filename).
    exr = os.path.realpath(str(blend.parent / "caustics" / "mirror_plane" / "Floor.exr"))
    assert again["bake_images"]["CausticBake Floor"] == [exr, [256, 256]]
    assert os.path.join("mirror_plane", "Floor.exr") in again["bake_files"] and os.path.getsize(exr) > 1000
    assert again["bake_blend_saved"]
    assert again["reopened_node_groups"] == ["CausticBake"]
    assert again["reopened_images"] == ["CausticBake Floor"]
    assert again["reopened_material_with_group"][0] == "Floor"
    print("headless bake: {:.1f} s".format(again["bake_seconds"]))


@pytest.mark.network
@pytest.mark.slow  # the session's zip build takes ~20 s (and downloads the wheels once)
def test_without_numba_the_operator_fails_cleanly(zips, tmp_path):
    """numba missing: the add-on still enables; the operator reports an error, no traceback."""
    resources, report, log = _install_check(zips["linux-x64"], tmp_path, "none")
    _assert_installed_and_disabled(report, resources)
    assert report["operator_result"] is None  # the ERROR report makes bpy.ops raise
    assert "needs numba and llvmlite" in report["operator_error"], report["operator_error"]
    assert "Traceback" not in log, log
    assert report["numba_file"] is None
    # The bake is greyed out with the reason (poll_message_set), not a traceback.
    assert "numba/llvmlite missing" in report["bake_poll_error"], report["bake_poll_error"]
