"""``python -m addon bake``: outputs, frames, and one-line errors for bad input."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.__main__ import main  # noqa: E402
from addon.bake.pipeline import BakeSettings, bake  # noqa: E402
from addon.bake.exr import read_exr  # noqa: E402
from addon.bake.extract import extract_scene, open_blend  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")


def _err_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    return err[0]


def _save(path, build):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    build()
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return str(path)


def _floor(uv=True, verts=((-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0))):
    me = bpy.data.meshes.new("Floor")
    me.from_pydata(list(verts), [], [(0, 1, 2, 3)])
    if uv:
        me.uv_layers.new(name="UVMap")
    ob = bpy.data.objects.new("Floor", me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _light():
    ob = bpy.data.objects.new("Point", bpy.data.lights.new("Point", "POINT"))
    bpy.context.scene.collection.objects.link(ob)
    ob.location = (0, 0, 2)


def test_entry_point_reports_a_missing_file_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "addon", "bake", str(tmp_path / "nope.blend"), "--out", str(tmp_path / "o")],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"error: no such file: {tmp_path / 'nope.blend'}"]


def test_bad_input_gives_one_line_and_nonzero_exit(tmp_path, capsys):
    out = str(tmp_path / "out")
    text = tmp_path / "notes.blend"
    text.write_text("not a blend file")
    assert main(["bake", str(text), "--out", out]) == 2
    assert "not a .blend file" in _err_line(capsys)
    assert main(["bake", os.path.join(SAMPLES, "mirror_plane.blend"), "--out", out, "--frames", "5-7"]) == 2
    assert "--frames must look like A:B" in _err_line(capsys)
    assert main(["bake", os.path.join(SAMPLES, "mirror_plane.blend"), "--out", out, "--frames", "5:2"]) == 2
    assert "the last frame is before the first" in _err_line(capsys)
    assert main(["bake", os.path.join(SAMPLES, "mirror_plane.blend"), "--out", out, "--samples", "0"]) == 2
    _err_line(capsys)
    cases = {
        "no receivers": lambda: (_floor(uv=False), _light()),
        "no lights": lambda: _floor(),
        "'Floor' has no UV map": lambda: (_floor(uv=False).__setitem__("caustic_receiver", "yes"), _light()),
        "'Floor' has zero area": lambda: (_floor(verts=((0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0))), _light()),
        "NaN": lambda: (_floor(verts=((0, 0, 0), (1, 0, 0), (float("nan"), 1, 0), (0, 1, 0))), _light()),
        "no meshes": lambda: _light(),
    }
    for i, (reason, build) in enumerate(cases.items()):
        path = _save(tmp_path / f"bad{i}.blend", build)
        capsys.readouterr()
        assert main(["bake", path, "--out", out]) == 2, reason
        line = _err_line(capsys)
        assert reason in line, (reason, line)
    assert not os.path.exists(os.path.join(out, "report.json"))


def test_bake_writes_exr_and_report(tmp_path, capsys):
    out = tmp_path / "out"
    blend = os.path.join(SAMPLES, "mirror_plane.blend")
    assert main(["bake", blend, "--out", str(out), "--resolution", "32", "--samples", "4", "--seed", "3",
                 "--one-bounce", "points"]) == 0
    assert "baked 1 receiver(s)" in capsys.readouterr().out
    img = read_exr(out / "Floor.exr")
    report = json.loads((out / "report.json").read_text())
    # The same numbers as a bake of the extracted scene in this process.
    open_blend(blend)
    res = bake(extract_scene(resolution=32), BakeSettings(resolution=32, samples=4, seed=3, one_bounce="points"))
    np.testing.assert_array_equal(img, res.images["Floor"])
    assert img.shape == (32, 32, 3) and img.max() > 0 and np.count_nonzero(img[:, :, 0]) > 100
    assert report["settings"]["resolution"] == 32 and report["files"] == {"Floor": "Floor.exr"}
    assert report["counts"]["paths_visible"] > 0 and report["counts"]["texels_touched"] > 100
    for stage in ("extract", "raster", "cull", "solve", "visibility", "write", "bake_total"):
        assert stage in report["timings"]
    assert report["chains"][0]["chain"] == "R" and report["input"]["blend"] == blend


def test_device_option(tmp_path, capsys):
    """--device opencl: the one-bounce solve of the path-points estimator runs on OpenCL, the
    tables once on the device and the tuples as index pairs (or falls back to Numba with a
    warning); either way the texture matches the CPU bake to solver precision."""
    blend = os.path.join(SAMPLES, "mirror_plane.blend")
    assert main(["bake", blend, "--out", str(tmp_path / "o"), "--device", "gpu"]) == 2
    assert "--device must be numba, opencl or opencl:N" in _err_line(capsys)
    args = ["--resolution", "24", "--samples", "1", "--seed", "2", "--one-bounce", "points"]
    assert main(["bake", blend, "--out", str(tmp_path / "cl"), "--device", "opencl"] + args) == 0
    assert main(["bake", blend, "--out", str(tmp_path / "cpu")] + args) == 0
    cl, cpu = read_exr(tmp_path / "cl" / "Floor.exr"), read_exr(tmp_path / "cpu" / "Floor.exr")
    report = json.loads((tmp_path / "cl" / "report.json").read_text())
    from addon.solver.opencl.backend import OpenCLUnavailable, list_devices

    try:
        has_device = bool(list_devices())
    except OpenCLUnavailable:
        has_device = False
    assert report["settings"]["device"] == "opencl"
    assert report["devices"]["path-points"].startswith("opencl: ") if has_device else \
        report["devices"]["path-points"] == "cpu (numba)"
    assert report["counts"]["paths_visible"] > 0 and cpu.max() > 0
    np.testing.assert_allclose(cl, cpu, rtol=1e-5, atol=1e-6 * cpu.max())


def test_frames_write_a_sequence_per_receiver(tmp_path, capsys):
    out = tmp_path / "anim"
    blend = os.path.join(SAMPLES, "water_pool.blend")
    assert main(["bake", blend, "--out", str(out), "--resolution", "16", "--samples", "1", "--frames", "1:2"]) == 0
    a = read_exr(out / "PoolFloor.0001.exr")
    b = read_exr(out / "PoolFloor.0002.exr")
    assert json.loads((out / "report.0002.json").read_text())["input"]["frame"] == 2
    assert json.loads((out / "report.json").read_text())["frames"] == [1, 2]
    assert a.max() > 0 and b.max() > 0 and not np.array_equal(a, b), "the waves move between frames"


def test_demo_still_runs(capsys):
    assert main(["demo", "--width", "16", "--height", "4"]) == 0
    assert "Concave mirror" in capsys.readouterr().out


def test_preview_shows_the_written_exr_without_a_second_copy(tmp_path, capsys):
    """--preview renders the bake through the node group from the EXRs the CLI wrote: no
    second copy of each texture next to them, nothing written next to the .blend."""
    blend = os.path.join(SAMPLES, "metal_ring.blend")
    before = sorted(os.listdir(SAMPLES))
    out = tmp_path / "ring"
    png = tmp_path / "preview.png"
    assert main(["bake", blend, "--out", str(out), "--resolution", "16", "--samples", "1",
                 "--preview", str(png), "--preview-samples", "1"]) == 0
    assert png.is_file() and png.stat().st_size > 0
    report = json.loads((out / "report.json").read_text())
    exrs = sorted(f for f in os.listdir(out) if f.endswith(".exr"))
    assert exrs == sorted(report["files"].values())  # exactly one EXR per receiver
    assert sorted(os.listdir(SAMPLES)) == before
    for name, fname in report["files"].items():
        img = bpy.data.images[f"CausticBake {name}"]
        assert os.path.samefile(bpy.path.abspath(img.filepath), out / fname)
        H, W = img.size[1], img.size[0]
        px = np.array(img.pixels[:], dtype=np.float32).reshape(H, W, 4)[:, :, :3]
        np.testing.assert_allclose(px, read_exr(str(out / fname)), rtol=1e-6, atol=1e-7)
