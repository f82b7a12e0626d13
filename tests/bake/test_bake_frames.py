"""Frame ranges on the command line: ``--frames A:B`` writes an EXR sequence per receiver
(the names the Blender operator gives a sequence) with per-frame reports, each frame equal to
a single-frame bake of that frame; ``--dask-local N`` writes the same files bit for bit."""

import json
import os
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.__main__ import main  # noqa: E402
from addon.bake import cli  # noqa: E402
from addon.bake.exr import read_exr  # noqa: E402
from addon.bake.output import FILES_MANIFEST, MANIFEST_LOCK  # noqa: E402
from addon.bake.extract import extract_scene, open_blend  # noqa: E402
from addon.bake.pipeline import BakeSettings, bake, texture_filename  # noqa: E402

from fixtures.animated_scene import save_animated_mirror  # noqa: E402

ARGS = ["--resolution", "32", "--samples", "1", "--seed", "5"]


def _err_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    return err[0]


@pytest.fixture(scope="module")
def animated_blend(tmp_path_factory):
    return save_animated_mirror(tmp_path_factory.mktemp("anim") / "anim.blend")


def test_texture_filename_is_blenders_frame_numbering():
    assert texture_filename("Floor") == "Floor.exr"
    assert texture_filename("Floor", 1) == "Floor.0001.exr"
    assert texture_filename("Plane.001", 12345) == "Plane.001.12345.exr"
    assert texture_filename("a/b", 0) == "a_b.0000.exr"
    with pytest.raises(ValueError):
        texture_filename("Floor", -1)


def test_frames_write_the_sequence_each_frame_equal_to_its_single_frame_bake(animated_blend, tmp_path, capsys):
    out = tmp_path / "seq"
    dask_before = "distributed" in sys.modules
    assert main(["bake", animated_blend, "--out", str(out), "--frames", "1:3"] + ARGS) == 0
    lines = capsys.readouterr().out
    assert all(f"frame {f}: baked 1 receiver(s)" in lines for f in (1, 2, 3)), lines
    names = sorted(os.listdir(out))
    assert names == [FILES_MANIFEST, MANIFEST_LOCK, "Floor.0001.exr", "Floor.0002.exr", "Floor.0003.exr",
                     "report.0001.json", "report.0002.json", "report.0003.json", "report.json"]
    assert sorted(json.loads((out / FILES_MANIFEST).read_text())) == names[2:]  # every file it wrote, listed
    seq = [read_exr(out / f"Floor.{f:04d}.exr") for f in (1, 2, 3)]
    open_blend(animated_blend)
    for f, img in zip((1, 2, 3), seq):
        single = bake(extract_scene(resolution=32, frame=f), BakeSettings(resolution=32, samples=1, seed=5))
        assert single.report["scene"]["frame"] == f
        np.testing.assert_array_equal(img, single.images["Floor"])
    # The caustic moves: the brightest texel is elsewhere at each frame.
    peaks = [np.unravel_index(np.argmax(img[:, :, 0]), img.shape[:2]) for img in seq]
    assert len(set(peaks)) == 3, peaks
    index = json.loads((out / "report.json").read_text())
    assert index["frames"] == [1, 2, 3] and index["sequence"] is True
    assert index["files"] == {"Floor": ["Floor.0001.exr", "Floor.0002.exr", "Floor.0003.exr"]}
    for f in (1, 2, 3):
        per = index["per_frame"][str(f)]
        full = json.loads((out / per["report"]).read_text())
        assert per["report"] == f"report.{f:04d}.json" and full["scene"]["frame"] == f
        assert per["input"]["frame"] == f and per["files"] == {"Floor": f"Floor.{f:04d}.exr"}
        assert per["receivers"] == full["receivers"] and per["plan_summary"] == full["plan"]["summary"]
        assert per["estimators"] == ["forward-flux"] and per["counts"]["sub_triangles"] > 0
        assert per["receivers"]["Floor"]["max_irradiance"] == pytest.approx(float(seq[f - 1].max()), rel=1e-6)
    assert index["timings"]["bake_total"] == pytest.approx(sum(index["per_frame"][str(f)]["timings"]["bake_total"]
                                                               for f in (1, 2, 3)))
    assert len((out / "report.json").read_bytes()) < 3 * len((out / "report.0001.json").read_bytes())
    # A second job with other frames into the same folder (a farm chunk) extends the index.
    assert main(["bake", animated_blend, "--out", str(out), "--frames", "4:4"] + ARGS) == 0
    assert json.loads((out / "report.json").read_text())["frames"] == [1, 2, 3, 4]
    np.testing.assert_array_equal(read_exr(out / "Floor.0001.exr"), seq[0])  # untouched
    assert dask_before or "distributed" not in sys.modules  # dask is imported only for --dask


def test_frame_and_dask_errors_are_one_line(animated_blend, tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "o")
    cases = {
        ("--frames", "5:2"): "the last frame is before the first",
        ("--frames=-2:1",): "frames must be 0 or more",
        ("--dask-local", "2"): "give --frames A:B",
        ("--frames", "1:2", "--dask-local", "0"): "--dask-local must be at least 1",
        ("--frames", "1:2", "--dask-local", "2", "--dask", "tcp://x:1"): "exclude each other",
    }
    for extra, reason in cases.items():
        assert main(["bake", animated_blend, "--out", out] + list(extra)) == 2, extra
        assert reason in _err_line(capsys), extra
    # dask not installed: one line saying what to install; nothing is baked.
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["bake", animated_blend, "--out", out, "--frames", "1:2", "--dask-local", "2"]) == 2
    line = _err_line(capsys)
    assert line == "error: " + cli.DASK_MISSING
    assert not os.path.exists(out)


def test_an_unreachable_scheduler_is_one_line(tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "o"
    with pytest.raises(cli.UserError, match="^cannot reach the Dask scheduler at tcp://127.0.0.1:1: "):
        cli._bake_frames_on_dask(str(tmp_path / "x.blend"), [1, 2], str(out), BakeSettings(), 8,
                                 address="tcp://127.0.0.1:1", connect_timeout=1)
    assert not out.exists()


def test_a_worker_without_bpy_answers_one_line(tmp_path):
    """A Dask worker without the bpy module: the frame's task says so (the driver stops the
    bake with that line) instead of a traceback."""
    import ast
    import subprocess

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    code = ("import sys; sys.modules['bpy'] = None; from addon.bake.cli import bake_frame_task; "
            f"print(bake_frame_task(3, 'x.blend', {str(tmp_path)!r}, None, 8))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert result["frame"] == 3 and result["error"].startswith(cli.BPY_MISSING + " (on the Dask worker ")


@pytest.mark.slow
def test_dask_local_cluster_equals_the_serial_bake_bit_for_bit(animated_blend, tmp_path, capsys):
    pytest.importorskip("distributed")
    serial, spread = tmp_path / "serial", tmp_path / "dask"
    assert main(["bake", animated_blend, "--out", str(serial), "--frames", "1:3"] + ARGS) == 0
    assert main(["bake", animated_blend, "--out", str(spread), "--frames", "1:3", "--dask-local", "2"] + ARGS) == 0
    out = capsys.readouterr().out
    assert all(f"frame {f}: baked 1 receiver(s)" in out for f in (1, 2, 3)), out
    exrs = sorted(f for f in os.listdir(serial) if f.endswith(".exr"))
    assert exrs == ["Floor.0001.exr", "Floor.0002.exr", "Floor.0003.exr"]
    assert sorted(os.listdir(spread)) == sorted(os.listdir(serial))
    assert json.loads((spread / FILES_MANIFEST).read_text()) == json.loads((serial / FILES_MANIFEST).read_text())
    for name in exrs:
        a, b = read_exr(serial / name), read_exr(spread / name)
        assert a.max() > 0
        assert a.dtype == b.dtype == np.float32 and np.array_equal(a, b), name
    index = json.loads((spread / "report.json").read_text())
    assert index["frames"] == [1, 2, 3]
    # Each frame was baked by a worker process, not by this one, with cores / 2 threads (the
    # serial bake used every core: the texture does not depend on the thread count).
    reports = [json.loads((spread / f"report.{f:04d}.json").read_text()) for f in (1, 2, 3)]
    pids = {r["input"]["pid"] for r in reports}
    assert os.getpid() not in pids
    assert {r["settings"]["threads"] for r in reports} == {max(1, (os.cpu_count() or 1) // 2)}
