#!/usr/bin/env python3
# SPDX-License-Identifier: GPL-3.0-or-later
"""Build the Caustic Bake extension zip(s) with Blender's own extension tool.

    .venv/bin/python tools/build_extension.py            # one zip per platform in dist/
    .venv/bin/python tools/build_extension.py --single   # one zip with every platform's wheels

Steps:
1. download the numba and llvmlite wheels (versions pinned in requirements.txt) for CPython
   3.11 and 3.13 on linux-x64, windows-x64 and macos-arm64 into build/wheel_cache/ (once;
   reruns reuse the cache and need no network).  numpy is not bundled: Blender ships it.
2. copy the extension files into build/staging/ (the files git knows about, filtered with the
   manifest's ``[build] paths_exclude_pattern``, using Blender's own pattern matcher);
   put the wheels in build/staging/wheels/ and write ``wheels`` and ``platforms`` into the
   staged manifest (the committed blender_manifest.toml never holds generated content);
3. ``blender_ext.py build --split-platforms`` (from the bpy package) into dist/, then
   ``blender_ext.py validate`` on every zip; print the zip paths and sizes.

Exit status 0 only if every step succeeded.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUILD_DIR = os.path.join(ROOT, "build")
WHEEL_CACHE = os.path.join(BUILD_DIR, "wheel_cache")
STAGING = os.path.join(BUILD_DIR, "staging")
DIST = os.path.join(ROOT, "dist")
MANIFEST = "blender_manifest.toml"

#: The packages bundled as wheels (numpy is not: Blender ships it).
BUNDLED = ("numba", "llvmlite")

#: CPython versions of the Blender releases we support: 4.2 - 5.0 use 3.11, 5.1+ uses 3.13.
PYTHON_VERSIONS = ("3.11", "3.13")

#: Blender platform -> the wheel platform tags pip may pick for it.  Linux: Blender needs
#: glibc >= 2.28, so manylinux up to 2_28 is fine.  macOS: numba/llvmlite publish
#: macosx_12_0_arm64 wheels (older tags listed so an older build would also be found).
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx_14_0_arm64", "macosx_13_0_arm64", "macosx_12_0_arm64", "macosx_11_0_arm64"),
}


def log(*args):
    print("[build_extension]", *args, flush=True)


def pinned_versions(requirements=os.path.join(ROOT, "requirements.txt")):
    """``{name: version}`` for the bundled packages, read from requirements.txt (``name==x.y.z``)."""
    found = {}
    with open(requirements, encoding="utf-8") as fh:
        for line in fh:
            m = re.match(r"^\s*([A-Za-z0-9_.-]+)\s*==\s*([^\s#;]+)", line)
            if m and m.group(1).lower() in BUNDLED:
                found[m.group(1).lower()] = m.group(2)
    missing = [name for name in BUNDLED if name not in found]
    if missing:
        raise SystemExit("requirements.txt does not pin {} with ==".format(", ".join(missing)))
    return found


def blender_ext_tool():
    """Paths of ``blender_ext.py`` and Blender's list of valid tags, inside the bpy package."""
    spec = importlib.util.find_spec("bpy")  # does not import bpy
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("the bpy module is not installed in this Python ({})".format(sys.executable))
    bpy_dir = list(spec.submodule_search_locations)[0]
    for version in sorted(os.listdir(bpy_dir), reverse=True):
        scripts = os.path.join(bpy_dir, version, "scripts")
        tool = os.path.join(scripts, "addons_core", "bl_pkg", "cli", "blender_ext.py")
        tags = os.path.join(scripts, "modules", "_bpy_internal", "extensions", "tags.py")
        if os.path.isfile(tool):
            return tool, (tags if os.path.isfile(tags) else "")
    raise SystemExit("blender_ext.py not found under {}".format(bpy_dir))


def load_blender_ext(tool):
    """Import blender_ext.py as a module (plain Python) to reuse its path pattern matcher."""
    spec = importlib.util.spec_from_file_location("_caustic_blender_ext", tool)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------------------
# Wheels


def _wheel_matches(filename, name, version, cp):
    return filename.startswith("{}-{}-{}-{}-".format(name, version, cp, cp)) and filename.endswith(".whl")


def fetch_wheels(versions, platforms, python_versions, offline=False):
    """Download (or reuse from build/wheel_cache) one wheel per package, Python and platform.

    Returns ``{blender_platform: [wheel paths]}``.
    """
    result = {}
    for platform in platforms:
        tags = PLATFORMS[platform]
        result[platform] = []
        for py in python_versions:
            cp = "cp" + py.replace(".", "")
            target = os.path.join(WHEEL_CACHE, "{}-{}".format(cp, platform))
            os.makedirs(target, exist_ok=True)

            def cached():
                files = sorted(os.listdir(target))
                return {
                    name: [f for f in files if _wheel_matches(f, name, versions[name], cp)] for name in BUNDLED
                }

            have = cached()
            if not all(len(have[name]) == 1 for name in BUNDLED):
                if offline:
                    raise SystemExit("wheels for {} {} are not in {} (offline)".format(cp, platform, target))
                cmd = [
                    sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                    "--disable-pip-version-check", "--quiet",
                    "--python-version", py, "--implementation", "cp", "--abi", cp,
                ]
                for tag in tags:
                    cmd += ["--platform", tag]
                cmd += ["--dest", target]
                cmd += ["{}=={}".format(name, versions[name]) for name in BUNDLED]
                log("downloading", " ".join("{}=={}".format(n, versions[n]) for n in BUNDLED), "for", cp, platform)
                subprocess.run(cmd, check=True)
                have = cached()
            for name in BUNDLED:
                if len(have[name]) != 1:
                    raise SystemExit(
                        "expected exactly one {}=={} wheel for {} {} in {}, found {}".format(
                            name, versions[name], cp, platform, target, have[name] or "none"
                        )
                    )
                result[platform].append(os.path.join(target, have[name][0]))
    return result


# ---------------------------------------------------------------------------------------
# Staging


def source_files():
    """Repository-relative paths of the files to consider: what git tracks plus untracked files
    that are not ignored; without git, every file under the root."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=ROOT, check=True, capture_output=True,
        ).stdout
        paths = [p for p in out.decode("utf-8").split("\0") if p]
        return sorted(p for p in paths if os.path.isfile(os.path.join(ROOT, p)))
    except (OSError, subprocess.CalledProcessError):
        paths = []
        for dirpath, dirnames, filenames in os.walk(ROOT):
            dirnames[:] = [d for d in dirnames if not d.startswith(".") and d not in ("build", "dist")]
            for f in filenames:
                paths.append(os.path.relpath(os.path.join(dirpath, f), ROOT).replace(os.sep, "/"))
        return sorted(paths)


def excluded(matcher, relpath):
    """True if ``relpath`` or one of its parent folders matches the exclude patterns
    (the same test blender_ext.py applies while it walks the tree)."""
    parts = relpath.split("/")
    for i in range(1, len(parts)):
        if matcher.test_path("/".join(parts[:i]) + "/"):
            return True
    return matcher.test_path(relpath)


def stage(blender_ext, manifest_text, wheels_by_platform):
    """Fill build/staging with the extension files, the wheels and the generated manifest."""
    manifest = tomllib.loads(manifest_text)
    for key in ("wheels", "platforms"):
        if key in manifest:
            raise SystemExit("{} must not declare '{}': build_extension.py generates it".format(MANIFEST, key))
    patterns = manifest.get("build", {}).get("paths_exclude_pattern", [])
    matcher = blender_ext.PathPatternMatch(patterns)

    if os.path.exists(STAGING):
        shutil.rmtree(STAGING)
    os.makedirs(STAGING)
    copied = 0
    for rel in source_files():
        if rel == MANIFEST or excluded(matcher, rel):
            continue
        dst = os.path.join(STAGING, *rel.split("/"))
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        shutil.copy2(os.path.join(ROOT, rel), dst)
        copied += 1

    wheel_dir = os.path.join(STAGING, "wheels")
    os.makedirs(wheel_dir)
    wheels_rel = []
    for platform in wheels_by_platform:
        for path in wheels_by_platform[platform]:
            shutil.copy2(path, wheel_dir)
            wheels_rel.append("./wheels/" + os.path.basename(path))

    # Top-level keys must come before the first [table] in TOML: insert them there.
    generated = (
        "# Generated by tools/build_extension.py (staged copy only).\n"
        "platforms = [{}]\n".format(", ".join('"{}"'.format(p) for p in wheels_by_platform))
        + "wheels = [\n" + "".join('  "{}",\n'.format(w) for w in wheels_rel) + "]\n\n"
    )
    lines = manifest_text.splitlines(keepends=True)
    first_table = next((i for i, line in enumerate(lines) if re.match(r"^\s*\[", line)), len(lines))
    staged_text = "".join(lines[:first_table]) + generated + "".join(lines[first_table:])
    staged = tomllib.loads(staged_text)  # must still parse
    assert staged["wheels"] == wheels_rel and staged["platforms"] == list(wheels_by_platform)
    with open(os.path.join(STAGING, MANIFEST), "w", encoding="utf-8") as fh:
        fh.write(staged_text)
    log("staged {} files and {} wheels in {}".format(copied, len(wheels_rel), os.path.relpath(STAGING, ROOT)))
    return staged


# ---------------------------------------------------------------------------------------
# Build


def run_tool(tool, *args):
    cmd = [sys.executable, tool, *args]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    output = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        raise SystemExit("{} failed ({}):\n{}".format(" ".join(args[:1]), proc.returncode, output))
    return output


def build(platforms=tuple(PLATFORMS), python_versions=PYTHON_VERSIONS, single=False, offline=False):
    """Build and validate the zip(s); returns ``{platform or "all": zip path}``."""
    t0 = time.perf_counter()
    tool, tags = blender_ext_tool()
    blender_ext = load_blender_ext(tool)
    versions = pinned_versions()
    wheels = fetch_wheels(versions, platforms, python_versions, offline=offline)

    with open(os.path.join(ROOT, MANIFEST), encoding="utf-8") as fh:
        manifest_text = fh.read()
    staged = stage(blender_ext, manifest_text, wheels)

    os.makedirs(DIST, exist_ok=True)
    prefix = "{}-{}".format(staged["id"], staged["version"])
    for name in os.listdir(DIST):  # stale zips of this extension
        if name.startswith(prefix) and name.endswith(".zip"):
            os.remove(os.path.join(DIST, name))

    args = ["build", "--source-dir", STAGING, "--output-dir", DIST, "--valid-tags", tags]
    if not single:
        args.append("--split-platforms")
    run_tool(tool, *args)

    if single:
        zips = {"all": os.path.join(DIST, prefix + ".zip")}
    else:
        zips = {p: os.path.join(DIST, "{}-{}.zip".format(prefix, p.replace("-", "_"))) for p in platforms}
    for key, path in zips.items():
        if not os.path.isfile(path):
            raise SystemExit("expected {} was not built".format(path))
        run_tool(tool, "validate", "--valid-tags", tags, path)
    log("built and validated in {:.1f} s:".format(time.perf_counter() - t0))
    for key, path in zips.items():
        print("{}  {:.1f} MB  ({})".format(path, os.path.getsize(path) / 1e6, key), flush=True)
    return zips


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--platform", action="append", choices=sorted(PLATFORMS),
        help="build only for this Blender platform (repeatable; default: all)",
    )
    parser.add_argument("--single", action="store_true", help="one zip with the wheels of every platform")
    parser.add_argument(
        "--offline", action="store_true", help="use only build/wheel_cache, never download",
    )
    args = parser.parse_args(argv)
    platforms = tuple(p for p in PLATFORMS if p in (args.platform or PLATFORMS))
    build(platforms=platforms, single=args.single, offline=args.offline)
    return 0


if __name__ == "__main__":
    sys.exit(main())
