"""Faults while writing a bake's files (addon/bake/output.py, names.py, the CLI): names unique
after sanitising, all-or-nothing writes (a failing EXR writer, a full disk, a read-only
folder, SIGINT while writing or renaming leave the previous files byte-identical and no
temporary file), and the CLI never overwriting a file it did not write in --out."""

import errno
import json
import os

import numpy as np
import pytest

from addon.bake import exr, output
from addon.bake.names import blend_folder, texture_filename, texture_stems

from fixtures.faults import make_read_only


def test_stems_are_unique_after_sanitising_and_ignore_case():
    names = ["Floor.001", "Floor_001", "a/b", "a_b", "Floor", "floor", "a_b_2"]
    stems = texture_stems(names)
    assert stems == {"Floor": "Floor", "Floor.001": "Floor.001", "Floor_001": "Floor_001", "a_b": "a_b",
                     "a_b_2": "a_b_2", "floor": "floor_2", "a/b": "a_b_3"}
    assert texture_stems(list(reversed(names))) == stems  # order does not matter
    assert len({s.casefold() for s in stems.values()}) == len(names)
    assert texture_filename("a/b", 7, receivers=["a_b", "a/b"]) == "a_b_2.0007.exr"
    assert texture_filename("a/b", receivers=["a/b"]) == "a_b.exr"
    assert blend_folder("//caustics/", "/x/glass sphere.blend") == "//caustics/glass sphere/"
    assert blend_folder("/out/", "") == "/out/untitled/"


def _images(seed):
    rng = np.random.default_rng(seed)
    return {f"R{k}.exr": rng.uniform(0, 3, (6, 7, 3)).astype(np.float32) for k in range(3)}


def _state(folder):
    return {n: (folder / n).read_bytes() for n in sorted(os.listdir(folder))}


def _failing_writer(monkeypatch, exc, after=1):
    """The EXR writer writes ``after`` files properly, then writes half a file and raises ``exc``."""
    real = exr.write_exr
    calls = []

    def write(path, image, compression="ZIP"):
        calls.append(path)
        if len(calls) > after:
            with open(path, "wb") as fh:
                fh.write(b"v/1\x01 half an EXR")
            raise exc
        real(path, image, compression)

    monkeypatch.setattr(exr, "write_exr", write)
    return calls


@pytest.mark.parametrize("exc, reason", [
    (RuntimeError("Cannot write image file\nOpenEXR: No space left on device"), "OpenEXR: No space left on device"),
    (OSError(errno.ENOSPC, "No space left on device"), "No space left on device"),
])
def test_a_failing_write_leaves_the_previous_files_and_no_partial_one(tmp_path, monkeypatch, exc, reason):
    folder = tmp_path / "out"
    output.write_textures(str(folder), _images(0))
    before = _state(folder)
    calls = _failing_writer(monkeypatch, exc, after=1)
    with pytest.raises(output.OutputError) as err:
        output.write_textures(str(folder), _images(1))
    assert len(calls) == 2
    msg = str(err.value)
    assert "\n" not in msg and msg == f"cannot write {folder / 'R1.exr'}: {reason}"
    assert _state(folder) == before  # byte-identical, no temporary file left
    assert sorted(json.loads((folder / output.FILES_MANIFEST).read_text())) == ["R0.exr", "R1.exr", "R2.exr"]


def test_a_failed_first_write_forgets_the_names_it_recorded(tmp_path, monkeypatch):
    folder = tmp_path / "out"
    _failing_writer(monkeypatch, RuntimeError("boom"), after=0)
    with pytest.raises(output.OutputError, match="boom"):
        output.write_textures(str(folder), _images(0))
    assert _state(folder) == {output.FILES_MANIFEST: b"[]", output.MANIFEST_LOCK: b""}


def test_a_read_only_folder_is_one_line_and_changes_nothing(tmp_path, monkeypatch):
    folder = tmp_path / "out"
    output.write_textures(str(folder), _images(0))
    before = _state(folder)
    make_read_only(folder, monkeypatch)
    try:
        with pytest.raises(output.OutputError) as err:
            output.write_textures(str(folder), _images(1))
    finally:
        os.chmod(folder, 0o755)
    assert str(err.value) == f"cannot write {folder / 'R0.exr'}: Permission denied"
    assert _state(folder) == before


def test_foreign_files_are_those_not_in_the_manifest(tmp_path):
    output.write_textures(str(tmp_path), {"Floor.exr": np.zeros((2, 2, 3))})
    (tmp_path / "Wall.exr").write_bytes(b"mine")
    assert output.foreign_files(str(tmp_path), ["Floor.exr", "Wall.exr", "Ceiling.exr"]) == [str(tmp_path / "Wall.exr")]


# -- the CLI (bpy) ---------------------------------------------------------------------------

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MIRROR = os.path.join(REPO, "sample_blends", "mirror_plane.blend")
ARGS = ["--resolution", "16", "--samples", "1"]


def _err_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    return err[0]


@pytest.mark.bpy
def test_cli_refuses_a_users_file_in_out_unless_forced(tmp_path, capsys):
    pytest.importorskip("bpy")
    from addon.__main__ import main

    out = tmp_path / "out"
    out.mkdir()
    (out / "report.json").write_text("the user's report")
    assert main(["bake", MIRROR, "--out", str(out)] + ARGS) == 2
    assert _err_line(capsys) == (f"error: {out / 'report.json'} exists and was not written by Caustic Bake; choose "
                                 "another --out or pass --force to overwrite it")
    assert sorted(os.listdir(out)) == ["report.json"] and (out / "report.json").read_text() == "the user's report"
    (out / "report.json").unlink()
    (out / "Floor.exr").write_bytes(b"the user's texture")
    assert main(["bake", MIRROR, "--out", str(out), "--frames", "1:1"] + ARGS) == 0  # other names: no clash
    assert main(["bake", MIRROR, "--out", str(out)] + ARGS) == 2
    assert f"{out / 'Floor.exr'} exists and was not written by Caustic Bake" in _err_line(capsys)
    assert (out / "Floor.exr").read_bytes() == b"the user's texture"
    assert main(["bake", MIRROR, "--out", str(out), "--force"] + ARGS) == 0
    assert exr.read_exr(out / "Floor.exr").max() > 0
    # Its own files it replaces without asking.
    assert main(["bake", MIRROR, "--out", str(out)] + ARGS) == 0
    assert {"Floor.exr", "report.json", "Floor.0001.exr", "report.0001.json"} <= output.written_here(str(out))


@pytest.mark.bpy
def test_cli_write_failure_is_one_line_rc2_and_keeps_the_previous_bake(tmp_path, capsys, monkeypatch):
    pytest.importorskip("bpy")
    from addon.__main__ import main

    out = tmp_path / "out"
    assert main(["bake", MIRROR, "--out", str(out)] + ARGS) == 0
    before = _state(out)
    _failing_writer(monkeypatch, RuntimeError("Cannot write image file"), after=0)
    capsys.readouterr()
    assert main(["bake", MIRROR, "--out", str(out), "--seed", "5"] + ARGS) == 2
    assert _err_line(capsys) == f"error: cannot write {out / 'Floor.exr'}: Cannot write image file"
    assert _state(out) == before


@pytest.mark.bpy
def test_cli_prints_progress_with_the_time_left(tmp_path, capsys, monkeypatch):
    pytest.importorskip("bpy")
    from addon.__main__ import main
    from addon.bake import cli, pipeline

    monkeypatch.setattr(cli, "PROGRESS_INTERVAL", 0.0)
    monkeypatch.setattr(pipeline.Progress, "eta", lambda self: 65.0)
    assert main(["bake", MIRROR, "--out", str(tmp_path / "o")] + ARGS) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("progress ")]
    pcts = [int(line.split()[1]) for line in lines]
    assert len(lines) >= 5 and pcts == sorted(pcts) and pcts[0] < 10
    assert lines[-1] == "progress 100 %: Floor: padded"
    assert all(line.endswith("(about 1 min 5 s left)") for line in lines[:-1])


def _failing_rename(monkeypatch, fail_on, exc=None):
    """os.replace fails (EIO, or raises ``exc``) when it renames a new file over ``fail_on``
    (not when it puts an earlier file back from aside, ``.old``)."""
    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append((os.path.basename(src), os.path.basename(dst)))
        if os.path.basename(dst) == fail_on and not str(src).endswith(".old"):
            raise exc if exc is not None else OSError(errno.EIO, "Input/output error")
        real(src, dst)

    monkeypatch.setattr(output.os, "replace", replace)
    return calls


def test_a_rename_failing_midway_undoes_the_renames_done(tmp_path, monkeypatch):
    """The textures are complete but the second rename fails: the first texture's earlier file
    comes back, nothing else is left (no temporary or aside file), one line."""
    folder = tmp_path / "out"
    output.write_textures(str(folder), _images(0))
    before = _state(folder)
    calls = _failing_rename(monkeypatch, "R1.exr")
    with pytest.raises(output.OutputError) as err:
        output.write_textures(str(folder), _images(1))
    assert str(err.value) == f"cannot write {folder / 'R1.exr'}: Input/output error"
    assert any(dst == "R0.exr" for _src, dst in calls)  # the first one had been replaced ...
    assert _state(folder) == before  # ... and is back, byte-identical


def test_publishing_frames_is_all_or_none(tmp_path, monkeypatch):
    """A frame range's staged frames move over the earlier sequence all or none: a rename
    failing midway puts the earlier frames back and the staged ones back in staging (Esc /
    a retry can still use them)."""
    folder, staging = tmp_path / "seq", tmp_path / "seq" / ".staging"
    output.write_textures(str(folder), {f"F.{k:04d}.exr": np.full((2, 2, 3), k, np.float32) for k in range(1, 4)})
    output.write_textures(str(staging), {f"F.{k:04d}.exr": np.full((2, 2, 3), 10 + k, np.float32) for k in range(1, 4)},
                          record=False)
    before = {n: (folder / n).read_bytes() for n in sorted(os.listdir(folder)) if n.endswith(".exr")}
    staged = {n: (staging / n).read_bytes() for n in sorted(os.listdir(staging)) if n.endswith(".exr")}
    _failing_rename(monkeypatch, "F.0003.exr")
    with pytest.raises(output.OutputError):
        output.move_files(str(staging), str(folder), ["F.0001.exr", "F.0002.exr", "F.0003.exr"])
    assert {n: (folder / n).read_bytes() for n in sorted(os.listdir(folder)) if n.endswith(".exr")} == before
    assert {n: (staging / n).read_bytes() for n in sorted(os.listdir(staging)) if n.endswith(".exr")} == staged
    assert not [n for n in os.listdir(folder) if n.endswith((".old", ".tmp"))]
    monkeypatch.undo()
    moved = output.move_files(str(staging), str(folder), ["F.0001.exr", "F.0002.exr", "F.0003.exr"])
    assert exr.read_exr(moved["F.0003.exr"])[0, 0, 0] == 13.0


def test_an_interrupt_while_writing_or_renaming_leaves_the_previous_files(tmp_path, monkeypatch):
    """SIGINT (KeyboardInterrupt) in the middle of the EXR writes, or between two renames after
    the first texture replaced its earlier file: the interrupt goes on, the previous files are
    byte-identical, no temporary or aside file is left and the manifest lists what it did."""
    folder = tmp_path / "out"
    output.write_textures(str(folder), _images(0))
    before = _state(folder)
    _failing_writer(monkeypatch, KeyboardInterrupt(), after=1)
    with pytest.raises(KeyboardInterrupt):
        output.write_textures(str(folder), _images(1))
    assert _state(folder) == before
    monkeypatch.undo()
    calls = _failing_rename(monkeypatch, "R2.exr", KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        output.write_textures(str(folder), _images(1))
    assert any(dst == "R1.exr" for _src, dst in calls)  # R0 and R1 had been replaced ...
    assert _state(folder) == before  # ... and are back
    monkeypatch.undo()
    fresh = tmp_path / "fresh"  # a first bake interrupted: its names are forgotten again
    _failing_rename(monkeypatch, "R1.exr", KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        output.write_textures(str(fresh), _images(1))
    assert _state(fresh) == {output.FILES_MANIFEST: b"[]", output.MANIFEST_LOCK: b""}


def test_cli_ctrl_c_is_one_line_and_rc_130(tmp_path, capsys, monkeypatch):
    pytest.importorskip("bpy")
    from addon.__main__ import main
    from addon.bake import cli

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_bake_open_scene", interrupted)
    blend = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "sample_blends",
                         "mirror_plane.blend")
    assert main(["bake", blend, "--out", str(tmp_path / "o"), "--resolution", "8"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: interrupted; files written before stay as they were, none is partly written"]
