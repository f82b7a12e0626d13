"""The Blender UI layer (addon/ui) under the bpy module: properties, the bake operator
(synchronous in background mode, and its modal steps driven from the test), cancel, undo,
clear, poll messages, one-line errors and the panels' draw code in every state."""

import os
import shutil
import types

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = [pytest.mark.bpy, pytest.mark.usefixtures("fresh_state")]

from addon.bake.apply import FILES_MANIFEST, GROUP_NAME  # noqa: E402
from addon.ui import operators, panels, state  # noqa: E402

from fixtures.checks import snapshot  # noqa: E402
from fixtures.modal import Event, ModalStub

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")




def _open_copy(tmp_path, name="mirror_plane", resolution=32, samples=1):
    """Open a copy of a sample scene (the bake writes next to it and saves it)."""
    path = str(tmp_path / (name + ".blend"))
    shutil.copy(os.path.join(SAMPLES, name + ".blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    props = bpy.context.scene.caustic_bake
    props.resolution = resolution
    props.samples = samples
    return path


def _pixels(img):
    w, h = img.size
    px = np.empty(w * h * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(h, w, 4)[:, :, :3]


def _assert_baked(receiver="Floor"):
    group = bpy.data.node_groups.get(GROUP_NAME)
    assert group is not None
    img = bpy.data.images["CausticBake " + receiver]
    mat = bpy.data.objects[receiver].material_slots[0].material
    gnode = mat.node_tree.get_output_node("CYCLES").inputs["Surface"].links[0].from_node
    assert gnode.type == "GROUP" and gnode.node_tree is group
    assert _pixels(img).max() > 0  # the mirror's caustic is on the floor
    return img


# -- registration and properties ---------------------------------------------------------------

def test_registered_classes_and_properties():
    for name in ("CAUSTICS_OT_bake", "CAUSTICS_OT_clear", "CAUSTICS_OT_prepare_solver",
                 "RENDER_PT_caustic_bake", "OBJECT_PT_caustic_bake"):
        assert hasattr(bpy.types, name), name
    bpy.ops.wm.read_factory_settings(use_empty=True)
    props = bpy.context.scene.caustic_bake
    assert props.resolution == 256 and props.solver == "spoly" and props.device == "numba"
    # Only options the bake really has: its estimators and solvers.
    from addon.bake.settings import ESTIMATORS, SOLVERS

    assert {e.identifier for e in props.bl_rna.properties["solver"].enum_items} == set(SOLVERS)
    assert {e.identifier for e in props.bl_rna.properties["estimator"].enum_items} == set(ESTIMATORS)
    assert {e.identifier for e in props.bl_rna.properties["device"].enum_items} == {"numba", "opencl"}
    from addon.ui.properties import bake_settings

    s = bake_settings(props)
    assert (s.bounces, s.estimator) == ("auto", "forward-flux") and s.plan_threshold == pytest.approx(0.005)
    props.samples, props.light_samples, props.bounces, props.device = 9, 5, "2", "opencl"
    s = bake_settings(props)
    assert (s.samples, s.light_samples, s.bounces, s.device, s.resolution) == (9, 5, 2, "opencl", 0)
    assert (s.estimator, s.solver, s.sms_seeds, s.photons) == ("forward-flux", "spoly", 16, 1_000_000)
    props.estimator, props.solver, props.sms_seeds, props.photons = "path-points", "sms", 8, 12345
    s = bake_settings(props)
    assert (s.estimator, s.solver, s.sms_seeds, s.photons) == ("path-points", "sms", 8, 12345)
    props.estimator, props.solver = "forward-flux", "spoly"
    props.quality = "PREVIEW"
    s = bake_settings(props)
    assert (s.samples, s.light_samples, s.bounces) == (1, 1, 2)


def test_object_properties_drive_extraction(tmp_path):
    from addon.bake.extract import extract_scene, readiness

    _open_copy(tmp_path)
    floor, mirror = bpy.data.objects["Floor"], bpy.data.objects["Mirror"]
    assert readiness(bpy.context.scene) == (1, 1)
    floor.caustic_bake.resolution = 24
    model = extract_scene(resolution=40)
    assert [(r.name, r.resolution) for r in model.receivers] == [("Floor", (24, 24))]
    assert model.casters().size > 0
    mirror.caustic_bake.role = "none"  # no caster any more: the mirror becomes a receiver too
    mirror.caustic_bake.receiver = "no"
    model = extract_scene(resolution=40)
    assert model.casters().size == 0 and [r.name for r in model.receivers] == ["Floor"]
    floor.caustic_bake.receiver = "no"
    assert readiness(bpy.context.scene) == (0, 1)
    # "auto" in the group falls back to the custom properties (scripts, the CLI).
    floor.caustic_bake.receiver = "auto"
    floor["caustic_receiver"] = "no"
    assert readiness(bpy.context.scene) == (0, 1)


# -- the bake operator ----------------------------------------------------------------------

def test_background_bake_applies_writes_and_saves(tmp_path):
    path = _open_copy(tmp_path)
    assert bpy.app.background
    assert bpy.ops.caustics.bake() == {"FINISHED"}
    img = _assert_baked()
    w, h = img.size
    assert (w, h) == (32, 32)
    exr = tmp_path / "caustics" / "mirror_plane" / "Floor.exr"
    assert exr.is_file() and os.path.realpath(bpy.path.abspath(img.filepath)) == os.path.realpath(exr)
    # Background mode saved the .blend: the bake is in the file.
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=path)
    assert GROUP_NAME in bpy.data.node_groups and "CausticBake Floor" in bpy.data.images
    # A second bake replaces the first (no duplicates) and overwrites its own file.
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    assert sorted(i.name for i in bpy.data.images) == ["CausticBake Floor"]


def test_unsaved_file_packs_and_user_files_are_never_overwritten(tmp_path):
    # Unsaved: the textures are packed.
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for name in ("Floor", "Mirror", "Point"):
        bpy.ops.wm.append(directory=os.path.join(SAMPLES, "mirror_plane.blend", "Object"), filename=name)
    bpy.context.scene.caustic_bake.resolution = 16
    bpy.context.scene.caustic_bake.samples = 1
    assert not bpy.data.filepath
    assert bpy.ops.caustics.bake() == {"FINISHED"}
    assert bpy.data.images["CausticBake Floor"].packed_file is not None
    # A file the add-on did not write is not overwritten: a one-line error, nothing applied.
    _open_copy(tmp_path)
    folder = tmp_path / "caustics" / "mirror_plane"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / FILES_MANIFEST).unlink(missing_ok=True)
    user_file = folder / "Floor.exr"
    user_file.write_bytes(b"the user's own file")
    before = snapshot()
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake()
    msg = str(err.value)
    assert "not written by Caustic Bake" in msg and "Traceback" not in msg
    assert user_file.read_bytes() == b"the user's own file"
    assert snapshot() == before


def _slow_scene(tmp_path):
    """Enough work for many chunks: metal ring, 64 x 64 texels, 4 samples each, the exact-path
    estimator (its bands are the modal steps; the flux estimator is one step per light sample
    and chain)."""
    _open_copy(tmp_path, "metal_ring", resolution=64, samples=4)
    bpy.context.scene.caustic_bake.estimator = "path-points"
    bpy.context.scene.caustic_bake.bounces = "1"  # the exact two-bounce chains would take minutes


def test_modal_steps_then_cancel_leave_the_scene_unchanged(tmp_path):
    _slow_scene(tmp_path)
    before = snapshot()
    op = ModalStub(bpy.context)
    assert op.modal(bpy.context, Event("MOUSEMOVE")) == {"PASS_THROUGH"}
    assert op.modal(bpy.context, Event("TIMER")) == {"RUNNING_MODAL"}
    assert state.STATE.running and state.STATE.message
    assert not bpy.ops.caustics.bake.poll()  # one bake at a time
    _draw_render_panel()  # the "baking" state draws
    assert op.modal(bpy.context, Event("ESC", "PRESS")) == {"CANCELLED"}
    assert not state.STATE.running
    assert op._job.steps is None
    assert any("cancelled" in m for _, m in op.reports)
    assert snapshot() == before
    assert not (tmp_path / "caustics").exists()


def test_modal_steps_to_the_end_apply_the_bake(tmp_path):
    _open_copy(tmp_path)
    op = ModalStub(bpy.context)
    results = []
    for _ in range(10000):
        results.append(op.modal(bpy.context, Event("TIMER")))
        if results[-1] != {"RUNNING_MODAL"}:
            break
    assert results[-1] == {"FINISHED"}, op.reports
    assert not state.STATE.running
    _assert_baked()
    assert any(kind == {"INFO"} and "1 receiver" in m for kind, m in op.reports)


def test_undo_restores_the_state_before_the_bake(tmp_path):
    """Real undo under the bpy module: the operator's own undo step (bl_options UNDO; a
    Python call pushes it when asked with undo=True, as a click in the UI does)."""
    _open_copy(tmp_path)
    bpy.ops.ed.undo_push(message="before the bake")
    before = snapshot()
    assert bpy.ops.caustics.bake("EXEC_DEFAULT", True, save_blend=False) == {"FINISHED"}
    _assert_baked()
    assert snapshot() != before
    bpy.ops.ed.undo()
    assert snapshot() == before
    assert GROUP_NAME not in bpy.data.node_groups
    # Redo brings the bake back: the step was the operator's own (had it pushed none, redo
    # would land on "before the bake").
    bpy.ops.ed.redo()
    _assert_baked()
    bpy.ops.ed.undo()
    assert bpy.ops.caustics.clear.poll() is False


def test_clear_removes_everything_the_bake_made(tmp_path):
    _open_copy(tmp_path)
    before = snapshot()
    assert not bpy.ops.caustics.clear.poll()
    bpy.ops.caustics.bake(save_blend=False)
    assert operators.has_bake() and bpy.ops.caustics.clear.poll()
    assert bpy.ops.caustics.clear() == {"FINISHED"}
    assert snapshot() == before
    assert not operators.has_bake()


# -- poll messages and one-line errors -------------------------------------------------------

def _poll_error():
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake()
    return str(err.value)


def test_poll_messages(tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert "No receivers" in _poll_error()
    _open_copy(tmp_path)
    bpy.data.objects["Point"].hide_render = True
    assert "No lights" in _poll_error()
    bpy.data.objects["Point"].hide_render = False
    assert bpy.ops.caustics.bake.poll()
    state._numba_missing = "numba"
    assert "numba" in _poll_error()


def test_user_errors_are_one_line_reports(tmp_path):
    _open_copy(tmp_path)
    floor = bpy.data.objects["Floor"]
    floor.data.uv_layers.remove(floor.data.uv_layers[0])
    floor.data.update()
    floor.caustic_bake.receiver = "yes"
    msg = _poll_error()
    assert "has no UV map" in msg and "Traceback" not in msg and len(msg.strip().splitlines()) <= 2, msg
    _open_copy(tmp_path)
    bpy.data.objects["Mirror"].data.vertices[0].co = (float("nan"), 0.0, 0.0)
    bpy.data.objects["Mirror"].data.update()
    msg = _poll_error()
    assert "NaN" in msg and "Traceback" not in msg, msg
    assert GROUP_NAME not in bpy.data.node_groups


def test_unexpected_errors_are_reported_briefly(tmp_path, monkeypatch, capsys):
    _open_copy(tmp_path)

    def boom(*a, **k):
        raise ZeroDivisionError("simulated bug")

    monkeypatch.setattr("addon.bake.pipeline.bake_steps", boom)
    msg = _poll_error()
    assert "ZeroDivisionError: simulated bug" in msg and "Traceback" not in msg
    assert "Traceback" in capsys.readouterr().err  # the details go to the console


# -- panels ------------------------------------------------------------------------------------

class FakeLayout:
    """Records what a panel draws; checks every property and operator it names exists."""

    def __init__(self, log):
        self.log = log

    def _child(self, *a, **k):
        return FakeLayout(self.log)

    row = column = box = split = column_flow = grid_flow = _child

    def label(self, text="", icon="NONE", **k):
        self.log.append(("label", text, icon))

    def prop(self, data, name, **k):
        assert name in data.bl_rna.properties, name
        self.log.append(("prop", name))

    def operator(self, idname, **k):
        mod, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, mod), op), idname
        self.log.append(("operator", idname))

    def progress(self, factor=0.0, type="BAR", text=""):
        assert 0.0 <= factor <= 1.0
        self.log.append(("progress", text))

    def separator(self, **k):
        pass


def _draw(panel, context):
    log = []
    stub = types.SimpleNamespace(layout=FakeLayout(log))
    assert panel.poll(context)
    panel.draw(stub, context)
    return log


def _draw_render_panel():
    return _draw(panels.RENDER_PT_caustic_bake, bpy.context)


def _labels(log):
    return " | ".join(e[1] for e in log if e[0] == "label")


def test_panels_draw_in_every_state(tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    log = _draw_render_panel()  # no receivers, no lights
    assert "No receivers" in _labels(log) and "No lights" in _labels(log)
    assert ("operator", "caustics.bake") in log and ("prop", "resolution") in log
    state._numba_missing = "numba"  # numba missing
    assert "numba" in _labels(_draw_render_panel())
    state.forget_numba_check()
    _open_copy(tmp_path)  # ready
    log = _draw_render_panel()
    assert "No receivers" not in _labels(log) and "Baked" not in _labels(log)
    bpy.ops.caustics.bake(save_blend=False)  # baked
    log = _draw_render_panel()
    assert "Baked: 1 texture(s)" in _labels(log) and "CausticBake Floor" in _labels(log)
    state.STATE.start()  # baking
    state.STATE.update(0.25, "Floor: rows 8/32")
    log = _draw_render_panel()
    assert ("progress", "25%  Floor: rows 8/32") in log and "Esc" in _labels(log)
    assert ("operator", "caustics.bake") not in log
    state.STATE.reset()
    # Object panel: a receiver, a mesh without UVs, and not shown for a light.
    floor = bpy.data.objects["Floor"]
    ctx = types.SimpleNamespace(scene=bpy.context.scene, object=floor)
    log = _draw(panels.OBJECT_PT_caustic_bake, ctx)
    assert {("prop", "role"), ("prop", "receiver"), ("prop", "resolution")} <= set(log)
    floor.data.uv_layers.remove(floor.data.uv_layers[0])
    assert "No UV map" in _labels(_draw(panels.OBJECT_PT_caustic_bake, ctx))
    assert not panels.OBJECT_PT_caustic_bake.poll(types.SimpleNamespace(scene=bpy.context.scene, object=bpy.data.objects["Point"]))
