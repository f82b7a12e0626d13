"""Esc answers at once while a long chunk runs: the modal bake runs its chunks on a worker
thread and waits at most its time budget per timer tick; a cancelled bake's chunk finishes on
that thread, is discarded, and a new bake waits for it."""

import os
import shutil
import time

import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from addon.bake import pipeline  # noqa: E402
from addon.ui import operators, state  # noqa: E402

from fixtures.checks import snapshot  # noqa: E402
from fixtures.modal import Event, ModalStub

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAMPLES = os.path.join(REPO, "sample_blends")
CHUNK = 3.0  # seconds of the long chunk
CLOSING = 0.3  # seconds its generator takes to close (its finally)



def test_esc_answers_while_a_long_chunk_runs(tmp_path, monkeypatch):
    path = str(tmp_path / "mirror_plane.blend")
    shutil.copy(os.path.join(SAMPLES, "mirror_plane.blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    bpy.context.scene.caustic_bake.resolution = 16
    real = pipeline.bake_steps
    closed = []

    def bake_steps(scene, settings=None):
        gen = real(scene, settings)

        def steps():
            try:
                yield next(gen)
                time.sleep(CHUNK)  # one chunk that takes seconds (a large forward image)
                return (yield from gen)
            finally:
                time.sleep(CLOSING)  # closing takes a while too: a new bake must wait for it as well
                closed.append(time.monotonic())

        return steps()

    monkeypatch.setattr(pipeline, "bake_steps", bake_steps)
    before = snapshot()
    state.STATE.reset()
    op = ModalStub(bpy.context)
    ticks = []
    for _ in range(5):
        t0 = time.monotonic()
        assert op.modal(bpy.context, Event("TIMER")) == {"RUNNING_MODAL"}
        ticks.append(time.monotonic() - t0)
    assert max(ticks) < 0.3, ticks  # every tick returns within its budget
    t0 = time.monotonic()
    assert op.modal(bpy.context, Event("ESC", "PRESS")) == {"CANCELLED"}
    assert time.monotonic() - t0 < 0.5
    t_esc = time.monotonic()
    assert snapshot() == before and not state.STATE.running and op._job.steps is None
    assert any("cancelled" in m for _, m in op.reports)
    assert operators.abandoned_running() and not closed
    assert not bpy.ops.caustics.bake.poll()  # a new bake waits for the cancelled chunk
    while operators.abandoned_running() and time.monotonic() < t_esc + 30:
        time.sleep(0.01)
    assert len(closed) == 1 and bpy.ops.caustics.bake.poll()  # then the cancelled bake's generator is closed
    assert snapshot() == before and not (tmp_path / "caustics").exists()
