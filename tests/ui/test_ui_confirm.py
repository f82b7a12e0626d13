"""A very large bake asks first (addon/bake/estimate.py): the operator shows a confirmation
dialog naming the estimate and starts nothing until it is answered; its OK runs execute with
``confirmed``, which starts the modal bake."""

import os
import shutil

import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.bake import estimate  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")


def test_operator_shows_a_confirmation_before_a_very_large_bake(tmp_path, monkeypatch, fresh_state):

    from addon.ui import operators
    from addon.ui.state import STATE
    from fixtures.modal import Event

    path = str(tmp_path / "mirror_plane.blend")
    shutil.copy(os.path.join(SAMPLES, "mirror_plane.blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    bpy.context.scene.caustic_bake.resolution = 16
    monkeypatch.setattr(estimate, "CONFIRM_SECONDS", 0.0)

    class WindowManager:
        asked = []

        def invoke_confirm(self, op, event, **kw):
            self.asked.append(kw)
            return {"RUNNING_MODAL"}

    class Context:
        scene = bpy.context.scene
        window_manager = WindowManager()

    class Op:
        confirmed = False

        def report(self, kind, message):
            raise AssertionError(message)

    op = Op()
    images = len(bpy.data.images)
    assert operators.CAUSTICS_OT_bake._start_modal(op, Context(), Event("LEFTMOUSE", "PRESS")) == {"RUNNING_MODAL"}
    (asked,) = WindowManager.asked
    assert asked["confirm_text"] == "Bake" and asked["message"].startswith("This bake needs at least about ")
    assert "256 texels" in asked["message"]
    assert op.confirmed and op._job is None and not STATE.running  # nothing started until the answer
    assert len(bpy.data.images) == images
