"""The operator's frame range (the panel's *Animation*: *Scene Frame Range*) under the bpy
module: an EXR sequence per receiver, each frame equal to a single-frame bake of that frame,
hooked into the material as an image sequence that Cycles renders frame by frame; Esc between
frames keeps the finished frames; Clear removes files, images and nodes; Undo restores."""

import functools
import json
import os
import time
import types

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pytestmark = [pytest.mark.bpy, pytest.mark.usefixtures("fresh_state")]

from addon.bake.apply import FILES_MANIFEST, GROUP_NAME  # noqa: E402
from addon.bake.output import MANIFEST_LOCK  # noqa: E402
from addon.bake.exr import read_exr  # noqa: E402
from addon.ui import operators, panels, state  # noqa: E402

from fixtures.animated_scene import MIRROR_PLANE, build_animated_mirror  # noqa: E402
from fixtures.checks import snapshot  # noqa: E402
from fixtures.modal import Event, ModalStub

SEQ = ["Floor.0001.exr", "Floor.0002.exr", "Floor.0003.exr"]




def _open_animated(tmp_path, frame=2):
    """The animated mirror scene saved in ``tmp_path`` (the sequence goes to //caustics/anim/), set
    to bake the scene's frame range (1 to 3) at 32², standing at ``frame``."""
    build_animated_mirror(resolution=32)
    path = str(tmp_path / "anim.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    props = bpy.context.scene.caustic_bake
    props.resolution, props.samples, props.frame_range = 32, 1, "SCENE"
    bpy.context.scene.frame_set(frame)
    return path


def _tex_node():
    mat = bpy.data.objects["Floor"].material_slots[0].material
    return mat.node_tree.nodes["CausticBake Irradiance"]


def _frame_shown(frame):
    """The sequence frame the receiver's texture node shows at scene frame ``frame`` (its image
    user, evaluated: what playback and the renderers read)."""
    bpy.context.scene.frame_set(frame)
    mat = bpy.data.objects["Floor"].material_slots[0].material.evaluated_get(bpy.context.evaluated_depsgraph_get())
    return mat.node_tree.nodes["CausticBake Irradiance"].image_user.frame_current


def _single_frame_bake(frame):
    """A single-frame bake of ``frame`` with the panel's settings (the pipeline, no operator)."""
    from addon.bake.extract import extract_scene
    from addon.bake.pipeline import bake
    from addon.ui.properties import bake_settings

    props = bpy.context.scene.caustic_bake
    return bake(extract_scene(resolution=int(props.resolution), frame=frame), bake_settings(props)).images["Floor"]


def test_default_is_the_current_frame_and_the_panel_draws_the_setting(tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    props = bpy.context.scene.caustic_bake
    assert props.frame_range == "CURRENT"
    from addon.ui.properties import bake_frames

    assert bake_frames(props, bpy.context.scene) is None
    assert issubclass(panels.RENDER_PT_caustic_bake_animation, bpy.types.Panel)
    assert panels.RENDER_PT_caustic_bake_animation.bl_parent_id == panels.RENDER_PT_caustic_bake.bl_idname
    log = _draw_animation_panel()
    assert ("prop", "frame_range") in log and not any(e[0] == "label" for e in log)
    _open_animated(tmp_path)
    assert bake_frames(bpy.context.scene.caustic_bake, bpy.context.scene) == [1, 2, 3]
    labels = [e[1] for e in _draw_animation_panel() if e[0] == "label"]
    assert labels == ["Frames 1-3: 3 EXR(s) per receiver"]


def test_scene_range_writes_a_sequence_hooked_as_an_image_sequence(tmp_path):
    path = _open_animated(tmp_path, frame=2)
    bpy.ops.ed.undo_push(message="before the bake")
    before = snapshot()
    assert bpy.ops.caustics.bake("EXEC_DEFAULT", True, save_blend=False) == {"FINISHED"}
    folder = tmp_path / "caustics" / "anim"
    assert sorted(f for f in os.listdir(folder) if f.endswith(".exr")) == SEQ
    assert set(SEQ) <= set(json.loads((folder / FILES_MANIFEST).read_text()))
    assert bpy.context.scene.frame_current == 2  # set back after baking frames 1 to 3
    # Each frame's texture is the single-frame bake of that frame, and the caustic moves.
    seq = [read_exr(folder / name) for name in SEQ]
    for frame, img in zip((1, 2, 3), seq):
        np.testing.assert_array_equal(img, _single_frame_bake(frame))
    assert bpy.context.scene.frame_current == 3
    bpy.context.scene.frame_set(2)
    peaks = [np.unravel_index(np.argmax(img[:, :, 0]), img.shape[:2]) for img in seq]
    assert len(set(peaks)) == 3, peaks
    # The material shows an image sequence, frame f from the file of frame f.
    img = bpy.data.images["CausticBake Floor"]
    assert img.source == "SEQUENCE" and img.filepath == "//caustics/anim/Floor.0001.exr"
    assert img.colorspace_settings.name == "Non-Color"
    tex = _tex_node()
    assert tex.image == img
    iu = tex.image_user
    assert (iu.frame_start, iu.frame_offset, iu.frame_duration) == (1, 0, 3)
    assert iu.use_auto_refresh and not iu.use_cyclic
    assert [_frame_shown(f) for f in (1, 3, 2)] == [1, 3, 2]
    # Undo restores the scene as it was before the bake.
    bpy.ops.ed.undo()
    assert snapshot() == before
    assert GROUP_NAME not in bpy.data.node_groups
    assert os.path.exists(path)


def test_a_later_range_is_mapped_to_its_own_files(tmp_path):
    """Frames 2 to 3 only: the files are numbered by frame, the image user's offset maps them."""
    _open_animated(tmp_path)
    bpy.context.scene.frame_start = 2
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    folder = tmp_path / "caustics" / "anim"
    assert sorted(f for f in os.listdir(folder) if f.endswith(".exr")) == SEQ[1:]
    iu = _tex_node().image_user
    assert (iu.frame_start, iu.frame_offset, iu.frame_duration) == (2, 1, 2)
    assert bpy.data.images["CausticBake Floor"].filepath == "//caustics/anim/Floor.0002.exr"
    # After the range: the last baked frame.
    assert [_frame_shown(f) for f in (2, 3, 7)] == [2, 3, 3]


@pytest.mark.parametrize("engine", ["CYCLES", "BLENDER_EEVEE"])
def test_renders_show_each_frames_caustic(tmp_path, engine):
    """Cycles and EEVEE, top view, one pixel per texel, direct light only: the render at frame 3
    minus the render at frame 1 is the floor's albedo x (E3 - E1) / pi of the baked EXRs."""
    _open_animated(tmp_path)
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    sc = bpy.context.scene
    sc.render.engine = engine
    if engine == "CYCLES":
        sc.cycles.device = "CPU"
        sc.cycles.samples = 4
        sc.cycles.use_denoising = False
        sc.cycles.max_bounces = 0
        sc.cycles.caustics_reflective = sc.cycles.caustics_refractive = False
        if hasattr(sc.cycles, "filter_width"):
            sc.cycles.filter_width = 0.01  # rays through the pixel centres: the texel values
        else:
            sc.render.filter_size = 0.01
    else:
        sc.eevee.taa_render_samples = 1
    sc.view_settings.view_transform = "Standard"
    bpy.data.objects["Mirror"].visible_shadow = False
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    renders = {}
    for frame in (1, 3):
        sc.frame_set(frame)
        sc.render.filepath = str(tmp_path / f"render{frame}.exr")
        bpy.ops.render.render(write_still=True)
        renders[frame] = read_exr(tmp_path / f"render{frame}.exr")
    E1, E3 = read_exr(tmp_path / "caustics" / "anim" / SEQ[0]), read_exr(tmp_path / "caustics" / "anim" / SEQ[2])
    albedo = 0.8
    expected = albedo * (E3 - E1) / np.pi
    got = renders[3] - renders[1]
    assert np.abs(expected).max() > 0.05 * (albedo * E1.max() / np.pi)  # the caustic moved
    corr = np.corrcoef(got.ravel(), expected.ravel())[0, 1]
    if engine == "CYCLES":  # rays through the pixel centres read the texel values
        err = np.abs(got - expected)
        assert err.max() < 0.05 * np.abs(expected).max() and corr > 0.995, (err.max() / np.abs(expected).max(), corr)
    else:  # EEVEE filters differently: the same change, as strong as the EXRs say
        assert corr > 0.97, corr
        assert abs(got.sum() - expected.sum()) < 0.05 * np.abs(expected).sum(), (got.sum(), expected.sum())


def test_esc_between_frames_keeps_the_finished_frames(tmp_path, monkeypatch):
    _open_animated(tmp_path, frame=3)
    # short ticks: the progress of frame 1 shows before it ends (a 32² frame can be done
    # within the operator's 0.1 s tick, and the next one started)
    monkeypatch.setattr(operators.BakeJob, "step", functools.partialmethod(operators.BakeJob.step, budget=0.002))
    op = ModalStub(bpy.context)
    messages = []
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        assert op.modal(bpy.context, Event("TIMER")) == {"RUNNING_MODAL"}
        messages.append(state.STATE.message)
        if op._job.done_frames:
            break
    assert op._job.done_frames == [1] and op._job.frame_index == 1
    assert messages[0].startswith("frame 1/3: ") and messages[-1].startswith(("frame 1/3: ", "frame 2/3: "))
    assert op.modal(bpy.context, Event("ESC", "PRESS")) == {"FINISHED"}
    assert not state.STATE.running and op._job.steps is None
    assert any(kind == {"WARNING"} and "cancelled at frame 2/3" in m and "kept the 1 finished frame(s) 1-1" in m
               for kind, m in op.reports), op.reports
    folder = tmp_path / "caustics" / "anim"
    assert sorted(f for f in os.listdir(folder) if f.endswith(".exr")) == SEQ[:1]
    np.testing.assert_array_equal(read_exr(folder / SEQ[0]), _single_frame_bake(1))
    iu = _tex_node().image_user
    assert (iu.frame_start, iu.frame_duration) == (1, 1) and bpy.data.images["CausticBake Floor"].source == "SEQUENCE"
    assert [_frame_shown(f) for f in (1, 3)] == [1, 1]  # the finished frame shows throughout


def test_an_earlier_sequence_stays_until_the_new_range_is_done(tmp_path):
    """The frames of a new range are staged: the earlier bake's files are untouched while it
    runs, and replaced, all of them, when it ends."""
    _open_animated(tmp_path)
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    folder = tmp_path / "caustics" / "anim"
    old = {name: read_exr(folder / name) for name in SEQ}
    assert old[SEQ[0]].max() > 0
    for light in bpy.data.lights:
        light.energy *= 2.0  # the new bake: twice the caustic
    op = ModalStub(bpy.context)
    mid_range = False
    for _ in range(10000):
        if op.modal(bpy.context, Event("TIMER")) != {"RUNNING_MODAL"}:
            break
        if 1 <= len(op._job.done_frames) < 3:  # mid-range: new frames done, the old ones still in place
            mid_range = True
            assert sorted(f for f in os.listdir(folder) if f.endswith(".exr")) == SEQ
            for name in SEQ:
                np.testing.assert_array_equal(read_exr(folder / name), old[name])
    assert mid_range and op._job.done_frames == [1, 2, 3]
    for name in SEQ:
        np.testing.assert_allclose(read_exr(folder / name), 2.0 * old[name], rtol=1e-5, atol=1e-6 * old[name].max())
    assert sorted(os.listdir(folder)) == sorted(SEQ + [FILES_MANIFEST, MANIFEST_LOCK])  # no staging folder left


def test_esc_in_the_first_frame_changes_nothing(tmp_path, monkeypatch):
    _open_animated(tmp_path, frame=3)
    before = snapshot()
    # a tick that waits for nothing: the first tick returns while the first frame is under way
    # (a 32² frame can be done within the operator's 0.1 s tick)
    monkeypatch.setattr(operators.BakeJob, "step", functools.partialmethod(operators.BakeJob.step, budget=0.0))
    op = ModalStub(bpy.context)
    assert op.modal(bpy.context, Event("TIMER")) == {"RUNNING_MODAL"}
    assert not op._job.done_frames
    assert op.modal(bpy.context, Event("ESC", "PRESS")) == {"CANCELLED"}
    assert snapshot() == before and bpy.context.scene.frame_current == 3
    assert not (tmp_path / "caustics").exists()


def test_clear_removes_the_sequence_files_images_and_nodes(tmp_path):
    _open_animated(tmp_path)
    before = snapshot()
    folder = tmp_path / "caustics" / "anim"
    folder.mkdir(parents=True)
    user_file = folder / "Floor.0007.exr"  # the user's own file in the same folder
    user_file.write_bytes(b"mine")
    assert bpy.ops.caustics.bake(save_blend=False) == {"FINISHED"}
    assert all((folder / name).is_file() for name in SEQ)
    assert bpy.ops.caustics.clear() == {"FINISHED"}
    assert snapshot() == before
    assert not operators.has_bake()
    assert sorted(os.listdir(folder)) == sorted([FILES_MANIFEST, MANIFEST_LOCK, user_file.name])
    assert json.loads((folder / FILES_MANIFEST).read_text()) == []
    assert user_file.read_bytes() == b"mine"


def test_a_users_file_in_the_sequence_is_never_overwritten(tmp_path):
    _open_animated(tmp_path)
    folder = tmp_path / "caustics" / "anim"
    folder.mkdir(parents=True)
    user_file = folder / SEQ[1]
    user_file.write_bytes(b"mine")
    before = snapshot()
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake(save_blend=False)
    msg = str(err.value)
    assert "Floor.0002.exr exists and was not written by Caustic Bake" in msg and "Traceback" not in msg
    assert user_file.read_bytes() == b"mine" and snapshot() == before
    assert sorted(os.listdir(folder)) == [SEQ[1]]


def test_an_unsaved_file_cannot_bake_a_sequence(tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for name in ("Floor", "Mirror", "Point"):
        bpy.ops.wm.append(directory=os.path.join(MIRROR_PLANE, "Object"), filename=name)
    bpy.context.scene.caustic_bake.frame_range = "SCENE"
    assert not bpy.data.filepath
    with pytest.raises(RuntimeError) as err:
        bpy.ops.caustics.bake()
    assert "cannot be packed: save the .blend" in str(err.value)
    assert GROUP_NAME not in bpy.data.node_groups


class _FakeLayout:
    def __init__(self, log):
        self.log = log

    def _child(self, *a, **k):
        return _FakeLayout(self.log)

    row = column = box = split = _child

    def label(self, text="", icon="NONE", **k):
        self.log.append(("label", text, icon))

    def prop(self, data, name, **k):
        assert name in data.bl_rna.properties, name
        self.log.append(("prop", name))

    def separator(self, **k):
        pass


def _draw_animation_panel():
    log = []
    panel = panels.RENDER_PT_caustic_bake_animation
    assert panel.poll(bpy.context)
    panel.draw(types.SimpleNamespace(layout=_FakeLayout(log)), bpy.context)
    return log
