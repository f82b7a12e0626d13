"""The bake operator's outputs under faults: each .blend bakes into its own folder and reopens
showing its own bake; a failed write (OpenEXR error, full disk, read-only folder) is one line
and leaves the previous bake's files, images and nodes exactly as they were; Clear finds the
add-on's node group by its tag, not by its name."""

import errno
import os
import shutil

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = [pytest.mark.bpy, pytest.mark.usefixtures("fresh_state")]

from addon.bake import exr  # noqa: E402
from addon.bake.apply import TAG_KEY  # noqa: E402
from addon.ui import operators  # noqa: E402

from fixtures.checks import snapshot  # noqa: E402
from fixtures.faults import make_read_only  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")




def _open_copy(folder, sample, name=None, resolution=16):
    path = str(folder / ((name or sample) + ".blend"))
    shutil.copy(os.path.join(SAMPLES, sample + ".blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    props = bpy.context.scene.caustic_bake
    props.resolution = resolution
    props.samples = 1
    return path


def _pixels(img):
    w, h = img.size
    px = np.empty(w * h * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(h, w, 4)[:, :, :3]


def _files(folder):
    return {os.path.relpath(os.path.join(r, n), folder): open(os.path.join(r, n), "rb").read()
            for r, _, names in os.walk(folder) for n in names}


def test_two_blends_in_one_folder_keep_their_own_bakes(tmp_path):
    a = _open_copy(tmp_path, "mirror_plane", "a")
    assert bpy.ops.caustics.bake() == {"FINISHED"}  # background mode: saved
    b = _open_copy(tmp_path, "metal_ring", "b")
    assert bpy.ops.caustics.bake() == {"FINISHED"}
    fa, fb = tmp_path / "caustics" / "a" / "Floor.exr", tmp_path / "caustics" / "b" / "Floor.exr"
    assert not np.array_equal(exr.read_exr(fa), exr.read_exr(fb))
    for path, exr_path in ((a, fa), (b, fb)):
        bpy.ops.wm.open_mainfile(filepath=path)
        img = bpy.data.images["CausticBake Floor"]
        assert img.filepath == f"//caustics/{os.path.basename(path)[:-6]}/Floor.exr"
        np.testing.assert_array_equal(_pixels(img), exr.read_exr(exr_path))


def _bake_then_fail(tmp_path, monkeypatch, fail):
    _open_copy(tmp_path, "mirror_plane")
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    folder = tmp_path / "caustics"
    files, before = _files(folder), snapshot()
    pixels = _pixels(bpy.data.images["CausticBake Floor"])
    bpy.context.scene.caustic_bake.seed = 7
    bpy.context.scene.caustic_bake.resolution = 24
    fail(folder / "mirror_plane")
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake(save_blend=False)
    msg = str(err.value).strip()
    assert "\n" not in msg and "Traceback" not in msg
    assert _files(folder) == files  # byte-identical, no temporary or partial file
    assert snapshot() == before
    np.testing.assert_array_equal(_pixels(bpy.data.images["CausticBake Floor"]), pixels)
    return msg


def test_an_openexr_error_keeps_the_previous_bake(tmp_path, monkeypatch):
    def fail(_folder):
        def write(path, image, compression="ZIP"):
            open(path, "wb").write(b"half")
            raise RuntimeError("Cannot write image file\nOpenEXR: No space left on device")
        monkeypatch.setattr(exr, "write_exr", write)

    msg = _bake_then_fail(tmp_path, monkeypatch, fail)
    floor = tmp_path / "caustics" / "mirror_plane" / "Floor.exr"
    assert msg == f"Error: Caustic Bake: cannot write {floor}: OpenEXR: No space left on device"


def test_a_full_disk_keeps_the_previous_bake(tmp_path, monkeypatch):
    def fail(_folder):
        def write(path, image, compression="ZIP"):
            raise OSError(errno.ENOSPC, "No space left on device")
        monkeypatch.setattr(exr, "write_exr", write)

    assert _bake_then_fail(tmp_path, monkeypatch, fail).endswith("Floor.exr: No space left on device")


def test_a_read_only_folder_keeps_the_previous_bake(tmp_path, monkeypatch):
    def fail(folder):
        make_read_only(folder, monkeypatch)

    try:
        assert _bake_then_fail(tmp_path, monkeypatch, fail).endswith("Floor.exr: Permission denied")
    finally:
        os.chmod(tmp_path / "caustics" / "mirror_plane", 0o755)


def test_clear_removes_its_own_group_beside_a_users_group_of_that_name(tmp_path):
    _open_copy(tmp_path, "mirror_plane")
    mine = bpy.data.node_groups.new("CausticBake", "ShaderNodeTree")
    mine.use_fake_user = True
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    ours = [g for g in bpy.data.node_groups if g.get(TAG_KEY)]
    assert len(ours) == 1 and ours[0].name != "CausticBake"
    assert bpy.ops.caustics.clear() == {"FINISHED"}
    assert [g.name for g in bpy.data.node_groups] == ["CausticBake"] and bpy.data.node_groups[0] == mine
    assert not operators.has_bake()


def test_the_operator_reports_the_warnings_of_report_json(tmp_path):
    _open_copy(tmp_path, "mirror_plane")
    off = bpy.data.objects.new("Off", bpy.data.lights.new("Off", "POINT"))
    off.data.energy = 0.0
    bpy.context.scene.collection.objects.link(off)
    job = operators.BakeJob(bpy.context)
    job.start(bpy.context)
    job.run()
    job.finish(bpy.context)
    assert "light 'Off' has zero power: it adds no light" in job.result.report["warnings"]
    reports = []
    stub = type("Op", (), {"report": lambda self, kind, msg: reports.append((set(kind), msg))})()
    operators.CAUSTICS_OT_bake._report_warnings(stub, job)
    assert len(reports) == 1 and reports[0][0] == {"WARNING"}
    first = job.warnings[0]
    more = " (+{} more in the console)".format(len(job.warnings) - 1) if len(job.warnings) > 1 else ""
    assert reports[0][1] == "Caustic Bake: " + first + more
    assert "light 'Off' has zero power: it adds no light" in job.warnings


def test_prepare_solver_prepares_the_chains_of_the_open_scene(tmp_path):
    _open_copy(tmp_path, "metal_ring")
    reports = []
    stub = type("Op", (), {"report": lambda self, kind, msg: reports.append((set(kind), msg))})()
    assert operators.CAUSTICS_OT_prepare_solver.execute(stub, bpy.context) == {"FINISHED"}
    assert len(reports) == 1 and reports[0][0] == {"INFO"}
    assert reports[0][1].startswith("Caustic solver ready for forward-flux (R, RR) in ") and reports[0][1].endswith(" s")
    assert bpy.ops.caustics.prepare_solver() == {"FINISHED"}


def test_the_memory_budget_setting_stops_a_bake_that_does_not_fit(tmp_path):
    _open_copy(tmp_path, "mirror_plane", resolution=4096)
    bpy.context.scene.caustic_bake.memory_budget = 0.5
    before = snapshot()
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake(save_blend=False)
    msg = str(err.value).strip()
    assert msg.startswith("Error: Caustic Bake: the bake needs about ") and msg.endswith(
        "more than its memory budget of 0.5 GB; lower the resolution or raise the memory budget")
    assert snapshot() == before and not (tmp_path / "caustics").exists()


def test_receivers_whose_names_sanitise_alike_get_their_own_files(tmp_path):
    _open_copy(tmp_path, "mirror_plane")
    floor = bpy.data.objects["Floor"]
    for name, dx in (("Floor.001", 5.0), ("Floor_001", 10.0), ("floor", 15.0)):
        ob = floor.copy()
        ob.data = floor.data.copy()
        ob.name = name
        ob.location.x += dx
        bpy.context.scene.collection.objects.link(ob)
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    folder = tmp_path / "caustics" / "mirror_plane"
    files = {"Floor": "Floor.exr", "Floor.001": "Floor.001.exr", "Floor_001": "Floor_001.exr", "floor": "floor_2.exr"}
    assert sorted(n for n in os.listdir(folder) if n.endswith(".exr")) == sorted(files.values())
    for name, fname in files.items():
        img = bpy.data.images["CausticBake " + name]
        assert img.filepath == "//caustics/mirror_plane/" + fname
        np.testing.assert_array_equal(_pixels(img), exr.read_exr(folder / fname))
    assert _pixels(bpy.data.images["CausticBake Floor"]).max() > 0
