"""Operators.  Thin: they call into addon.solver / addon.bake and report; no maths here.

- ``caustics.prepare_solver``: compile (or load) the solver kernels the next bake of the open
  scene uses (its planned chains and light types: ``addon.bake.warm_up.prepare_for``; without a
  bakeable scene every chain the settings allow) and say how long it took.
- ``caustics.bake``: from the UI (invoke) a modal operator that runs the bake in chunks
  (``addon.bake.pipeline.bake_steps``) on one worker thread (:class:`ChunkWorker`; the pipeline
  never touches bpy) and polls it from a window-manager timer, waiting at most 0.1 s per tick,
  with a progress bar and status text; Esc / right-click answers at the next tick, however long
  the chunk running, and leaves the scene exactly as it was (nothing is applied before the bake
  is complete; the chunk still running finishes on its thread and is discarded).  With the frame range (the panel's
  *Animation*) it bakes frame after frame (progress "frame k/N"), writes each finished frame's
  EXRs, and shows them as image sequences; Esc then keeps the finished frames and shows those.
  From scripts and in background mode (``blender -b``) execute() bakes synchronously; in
  background mode it then saves the .blend (``save_blend``, default: yes there if the file has a
  path).  Undo restores the Blender data as it was before the bake (images, node group,
  materials); files written or deleted on disk stay so.  The textures go to the .blend's own
  folder in the output folder (``//caustics/<blend name>/<receiver>.exr``), are written all or
  nothing before the previous bake is touched, and a failed write (read-only folder, full
  disk) is one line with the previous bake's files, images and nodes unchanged.
- ``caustics.clear``: removes what the bake added (images, node group, material copies, nodes)
  and the files of baked image sequences (only files Caustic Bake wrote).

Errors are reported in the UI as one line (self.report), never as a traceback; unexpected
exceptions are reported briefly and their traceback goes to the console.
"""

import queue
import threading
import time
import traceback
import warnings
from concurrent.futures import Future, TimeoutError as FutureTimeout

import bpy

from . import numba_cache
from .state import MISSING_NUMBA, SHORT_MISSING_NUMBA, STATE, numba_missing


class UserError(Exception):
    """A problem the user can fix: reported as one line, no traceback."""


def _is_numba_import_error(ex):
    """True if ``ex`` (an ImportError) is about numba/llvmlite themselves (missing or broken)."""
    name = (getattr(ex, "name", None) or "").split(".")[0]
    return name in ("numba", "llvmlite") or "numba" in str(ex).lower() or "llvmlite" in str(ex).lower()


def load_solver():
    """Import numba and the solver lazily (after register() pointed numba's cache at the
    extension user directory); raises UserError when numba / llvmlite cannot be imported."""
    cache_dir = numba_cache.directory()
    try:
        import llvmlite  # noqa: F401
        import numba  # noqa: F401

        from .. import solver

        if cache_dir:
            from ..solver.runtime.jit import configure_cache

            configure_cache(cache_dir)
    except ImportError as ex:
        if _is_numba_import_error(ex):
            raise UserError(MISSING_NUMBA.format(ex)) from None
        raise
    return solver


def _report_failure(op, ex, what):
    """One line in the UI; a traceback in the console only for bugs."""
    from ..bake.scene import SceneError

    from ..bake.output import OutputError

    if isinstance(ex, (UserError, SceneError, OutputError, FileExistsError)):
        op.report({"ERROR"}, "Caustic Bake: {}".format(ex))
    elif isinstance(ex, OSError):  # cannot write the textures (permissions, disk full, ...)
        op.report({"ERROR"}, "Caustic Bake: cannot write the textures: {}".format(ex))
    else:
        traceback.print_exception(type(ex), ex, ex.__traceback__)
        op.report({"ERROR"}, "Caustic Bake: {} failed ({}: {}); details in the console".format(what, type(ex).__name__, ex))


class CAUSTICS_OT_prepare_solver(bpy.types.Operator):
    """Compile (or load from the cache) the kernels the bake settings use now, so that the next bake starts at once"""

    bl_idname = "caustics.prepare_solver"
    bl_label = "Prepare Caustic Solver"
    bl_options = {"REGISTER"}

    def execute(self, context):
        try:
            load_solver()
            from ..bake.extract import readiness
            from ..bake.warm_up import prepare_for, warm_up
            from .properties import bake_settings

            props = context.scene.caustic_bake
            settings = bake_settings(props)
            chains = None
            if all(readiness(context.scene)):  # a scene to bake: exactly what its bake will use
                from ..bake.extract import extract_scene
                from ..bake.scene import SceneError

                try:
                    seconds, chains = prepare_for(extract_scene(resolution=int(props.resolution)), settings)
                except SceneError:
                    chains = None
            if chains is None:  # nothing to bake yet: every chain the settings allow
                seconds = warm_up(settings)
        except UserError as ex:
            self.report({"ERROR"}, str(ex))
            return {"CANCELLED"}
        except ImportError as ex:
            traceback.print_exc()
            self.report({"ERROR"}, "Caustic Bake: could not load the solver: {}".format(ex))
            return {"CANCELLED"}
        except Exception as ex:  # a bug: say so in the UI, keep the details in the console
            traceback.print_exc()
            self.report({"ERROR"}, "Caustic Bake: preparing the solver failed: {}".format(ex))
            return {"CANCELLED"}

        what = " ({})".format(", ".join(chains) or "direct light only") if chains is not None else ""
        self.report({"INFO"}, "Caustic solver ready for {}{} in {:.1f} s".format(settings.estimator, what, seconds))
        return {"FINISHED"}


class ChunkWorker:
    """One daemon thread that runs the chunks of one modal bake, one at a time (the pipeline
    never touches bpy; extraction and applying stay on Blender's main thread).  The modal
    operator waits for a chunk at most its time budget, so Esc is answered within a timer tick
    even while one chunk (a forward image) takes seconds; a cancelled bake's chunk still running
    finishes on this thread and its generator is then closed there (:data:`ABANDONED` holds
    such chunks; a new bake waits for them)."""

    def __init__(self):
        self.jobs = queue.Queue()
        threading.Thread(target=self._loop, name="caustic-bake", daemon=True).start()

    def _loop(self):
        while True:
            item = self.jobs.get()
            if item is None:
                return
            fn, fut = item
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except BaseException as ex:  # handed to the main thread by Future.result()
                    fut.set_exception(ex)

    def submit(self, fn):
        fut = Future()
        self.jobs.put((fn, fut))
        return fut

    def stop(self):
        self.jobs.put(None)


ABANDONED = set()  # futures of cancelled bakes' chunks still running or whose generator is not closed yet


def abandoned_running():
    """Whether a cancelled bake's last chunk is still running on its worker thread, or its
    generator is still being closed there.  (Not the future's done(): a future is done before
    its done-callbacks, the closing among them, have run.)"""
    return bool(ABANDONED)


def _advance(steps):
    """The next step of a pipeline generator: (("step", (fraction, message)) or ("done",
    result), [warning texts raised meanwhile])."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            value = ("step", next(steps))
        except StopIteration as done:
            value = ("done", done.value)
    return value, [str(w.message) for w in caught]


def output_directory(props):
    """Where the textures go: the .blend's own folder in the output folder
    (:func:`addon.bake.names.blend_folder`: ``//caustics/<blend name>/`` by default), or None
    (pack) when the output folder is relative to an unsaved .blend."""
    from ..bake.names import blend_folder

    directory = props.output_dir or "//caustics/"
    if directory.startswith("//") and not bpy.data.filepath:
        return None
    return blend_folder(directory, bpy.data.filepath)


class BakeJob:
    """One bake of the active scene, in steps: :meth:`start` (extract, check), :meth:`step`
    (bounded chunks of the pipeline's generator), :meth:`finish` (apply to the scene) or
    :meth:`cancel`.  The modal operator drives it from a timer; execute() and tests drive it
    directly.

    The current frame (``frames`` None): nothing in Blender changes before :meth:`finish`.
    A frame range (the panel's *Scene Frame Range*): the frames are baked one after the other
    (the scene is set to each), each frame's textures are written to a staging folder inside
    the output folder as it finishes (:func:`addon.bake.apply.write_sequence_frame`), and
    :meth:`finish` moves the finished frames over the earlier bake's and shows them as image
    sequences, also after :meth:`cancel` (``done_frames``); until then the earlier bake's files
    are untouched, and a range cancelled before its first frame leaves them as they were.  The
    scene's frame is set back to where it was."""

    #: Smaller chunks than the pipeline's defaults, so that one timer tick stays short.
    MODAL_BATCH_TUPLES = 1 << 16
    MODAL_BAND_SAMPLES = 1 << 18
    MODAL_STEP_SECONDS = 0.15  # forward-flux chunks sized by time (a progress step, Esc)

    def __init__(self, context, modal=False):
        self.scene_name = context.scene.name
        self.modal = modal
        self.steps = None
        self.result = None
        self.model = None
        self.warnings = []
        self.frames = None  # the frame range being baked, or None: the current frame
        self.frame_index = 0
        self.done_frames = []
        self.written = {}  # frame -> {receiver: path of its EXR} (staged until finish)
        self.receivers = []
        self.uv_maps = {}
        self.original_frame = None
        self.t0 = time.perf_counter()
        self._worker = None  # modal: the ChunkWorker running the chunks
        self._pending = None  # modal: the Future of the chunk running on it

    def start(self, context):
        load_solver()
        from ..bake.apply import foreign_files
        from ..bake.pipeline import bake_steps
        from ..bake.extract import extract_scene
        from .properties import bake_frames, bake_settings

        props = context.scene.caustic_bake
        settings = bake_settings(props)
        if self.modal:
            settings.batch_tuples = self.MODAL_BATCH_TUPLES
            settings.band_samples = self.MODAL_BAND_SAMPLES
            settings.step_seconds = self.MODAL_STEP_SECONDS
        self.settings = settings
        self.resolution = int(props.resolution)
        self.directory = output_directory(props)
        self.pack = bool(props.pack)
        self.frames = bake_frames(props, context.scene)
        if self.frames is None:
            self.model = extract_scene(resolution=self.resolution)
            clash = foreign_files([r.name for r in self.model.receivers], self.directory)
            if clash:
                raise UserError("{} exists and was not written by Caustic Bake; choose another output folder".format(clash[0]))
            self.steps = bake_steps(self.model, settings)
            return
        if self.directory is None:
            raise UserError("a frame range is written as an EXR sequence, which cannot be packed: save the .blend "
                            "or set an absolute Output Folder")
        if self.pack:
            self.warnings.append("image sequences are not packed: the frames stay in {}".format(self.directory))
        self.original_frame = context.scene.frame_current
        self._start_frame(0)
        clash = foreign_files(self.receivers, self.directory, self.frames)
        if clash:
            self.cancel()
            raise UserError("{} exists and was not written by Caustic Bake; choose another output folder".format(clash[0]))

    def estimate(self):
        """The :class:`~addon.bake.estimate.BakeEstimate` of the whole job, after :meth:`start`
        (a frame range: the first frame's, for every frame)."""
        from ..bake.estimate import estimate_bake

        one = estimate_bake(self.model, self.settings)
        return one if self.frames is None else one.times(len(self.frames))

    def _start_frame(self, index):
        """Extract the scene at the range's frame ``index`` and start its bake."""
        from ..bake.apply import receivers_uv_maps
        from ..bake.extract import extract_scene
        from ..bake.pipeline import bake_steps

        frame = self.frames[index]
        self.frame_index = index
        self.model = extract_scene(resolution=self.resolution, frame=frame)
        names = [r.name for r in self.model.receivers]
        if index == 0:
            self.receivers = names
            self.uv_maps = receivers_uv_maps(self.model)
        elif names != self.receivers:
            raise UserError("the receivers change at frame {} ({} instead of {}): a sequence needs the same receivers "
                            "at every frame".format(frame, ", ".join(names) or "none", ", ".join(self.receivers)))
        self.steps = bake_steps(self.model, self.settings)

    def _bake_done(self, result):
        """A frame's bake finished: True when the whole job is done."""
        self.result = result
        if self.frames is None:
            return True
        from ..bake.apply import write_sequence_frame

        frame = self.frames[self.frame_index]
        self.written[frame] = write_sequence_frame(result.images, self.directory, frame)
        self.done_frames.append(frame)
        for w in result.report.get("warnings", []):
            w = "frame {}: {}".format(frame, w)
            if w not in self.warnings:
                self.warnings.append(w)
        if self.frame_index + 1 == len(self.frames):
            return True
        self._start_frame(self.frame_index + 1)
        return False

    def _progress(self, fraction, message):
        if self.frames is None:
            STATE.update(fraction, message)
            return
        n = len(self.frames)
        done = self.frame_index + (fraction if fraction is not None else 0.0)
        STATE.update(done / n, "frame {}/{}: {}".format(self.frame_index + 1, n, message))

    def step(self, budget=0.1):
        """Run chunks for about ``budget`` seconds; True when the bake is done.  A modal job
        runs them on its :class:`ChunkWorker` and returns after ``budget`` even when a chunk is
        still running (it is picked up by the next call); otherwise at least one chunk runs
        here."""
        t_end = time.perf_counter() + budget
        while True:
            if self.modal:
                if self._pending is None:
                    if self._worker is None:
                        self._worker = ChunkWorker()
                    steps = self.steps
                    self._pending = self._worker.submit(lambda: _advance(steps))
                try:
                    (kind, value), caught = self._pending.result(timeout=max(0.0, t_end - time.perf_counter()))
                except FutureTimeout:
                    if self.frames is not None and not STATE.message.startswith("frame "):
                        STATE.update(None, "frame {}/{}: starting".format(self.frame_index + 1, len(self.frames)))
                    return False
                finally:
                    if self._pending is not None and self._pending.done():
                        self._pending = None
            else:
                (kind, value), caught = _advance(self.steps)
            for text in caught:
                if text not in self.warnings:
                    self.warnings.append(text)
            if kind == "done":
                if self._bake_done(value):
                    STATE.update(1.0, "applying")
                    self._stop_worker()
                    return True
                continue
            self._progress(*value)
            if time.perf_counter() >= t_end:
                return False

    def run(self):
        while not self.step(budget=1e9):
            pass

    def _stop_worker(self):
        if self._worker is not None:
            self._worker.stop()
            self._worker = None

    def cancel(self):
        """Abandon the bake in progress (the frames already finished stay: ``done_frames``)
        and set the scene's frame back.  A chunk still running on the worker thread finishes
        there, and its generator is closed then (:data:`ABANDONED` until it has)."""
        steps, pending = self.steps, self._pending
        self.steps = self._pending = None
        if pending is not None and not pending.done():
            ABANDONED.add(pending)

            def close(fut, steps=steps):
                try:
                    if steps is not None:
                        steps.close()
                finally:
                    ABANDONED.discard(fut)  # only now may a new bake start (and never stuck if closing raised)

            pending.add_done_callback(close)
        elif steps is not None:
            steps.close()
        self._stop_worker()
        self._restore_frame()
        if self.frames is not None and not self.done_frames and self.directory is not None:
            from ..bake.apply import discard_staged_frames

            discard_staged_frames(self.directory)  # nothing to keep: the earlier bake stays as it was

    def _restore_frame(self):
        scene = bpy.data.scenes.get(self.scene_name)
        if self.original_frame is not None and scene is not None:
            scene.frame_set(self.original_frame)

    def finish(self, context):
        """Apply the result (a frame range: its finished frames) to the scene; returns the
        one-line summary."""
        from ..bake.apply import (apply_bake, apply_sequence, clear_bake, eevee_settings_for_casters,
                                  publish_sequence_frames, receivers_uv_maps, write_textures)

        result = self.result
        props = context.scene.caustic_bake
        if self.frames is None:
            # Every texture is written (all or nothing) before the earlier bake is touched: a
            # failed write leaves the earlier bake's files, images and nodes as they were.
            files = write_textures(result.images, self.directory) if self.directory is not None else None
            clear_bake(delete_files=True, keep_files=(files or {}).values())  # a new bake replaces every earlier one
            done = apply_bake(result.images, receivers_uv_maps(self.model), directory=self.directory, pack=self.pack,
                              files=files)
            self.warnings = list(result.report.get("warnings", [])) + self.warnings
            what = ""
        else:
            self._restore_frame()
            # the finished frames, staged until now, replace the earlier bake's files only here
            self.written = publish_sequence_frames(self.receivers, self.directory, self.done_frames)
            keep = [p for paths in self.written.values() for p in paths.values()]
            clear_bake(delete_files=True, keep_files=keep)  # an earlier sequence's other frames go
            done = apply_sequence(self.receivers, self.uv_maps, self.directory, self.done_frames)
            what = ", frames {}-{} of {}-{}".format(self.done_frames[0], self.done_frames[-1], self.frames[0], self.frames[-1])
        eevee = eevee_settings_for_casters(self.model)
        eevee_line = "EEVEE: turned on {} (Clear restores)".format(", ".join(eevee)) if eevee else None
        if eevee_line:
            what += "; " + eevee_line
        plan = result.report.get("plan", {}).get("summary", [])
        props.last_plan = "\n".join(plan + ([eevee_line] if eevee_line else []))  # the panel lists these lines
        return "Caustic Bake: {} receiver(s){} in {:.1f} s ({}): {}".format(
            len(done), what, time.perf_counter() - self.t0, ", ".join(result.report.get("estimators", {})) or "nothing",
            "; ".join(plan))


def confirmation_message(estimate):
    """The question a very large bake asks before it starts (its :class:`~addon.bake.estimate.BakeEstimate`)."""
    return "This bake needs {} ({:,} texels). Bake it now?".format(estimate.line(), estimate.texels)


class CAUSTICS_OT_bake(bpy.types.Operator):
    """Bake caustic irradiance textures onto the receivers (Esc cancels)"""

    bl_idname = "caustics.bake"
    bl_label = "Bake Caustics"
    bl_options = {"REGISTER", "UNDO"}

    save_blend: bpy.props.BoolProperty(
        name="Save .blend",
        description="Save the .blend after the bake (default: only in background mode, blender -b, "
        "when the file has a path)",
        default=False,
        options={"SKIP_SAVE"},
    )
    confirmed: bpy.props.BoolProperty(
        name="Confirmed",
        description="The user confirmed a very large bake (set by the confirmation dialog; the bake then runs "
        "in the background with a progress bar)",
        default=False,
        options={"SKIP_SAVE", "HIDDEN"},
    )

    @classmethod
    def poll(cls, context):
        if STATE.running:
            cls.poll_message_set("A caustic bake is running (Esc cancels it)")
            return False
        if abandoned_running():
            cls.poll_message_set("The cancelled caustic bake is finishing its current step")
            return False
        if numba_missing():
            cls.poll_message_set(SHORT_MISSING_NUMBA)
            return False
        if context.scene is None or not hasattr(context.scene, "caustic_bake"):
            return False
        from ..bake.extract import readiness

        receivers, lights = readiness(context.scene)
        if not receivers:
            cls.poll_message_set("No receivers: give a mesh a UV map, or set Receiver to Yes in Object properties")
            return False
        if not lights:
            cls.poll_message_set("No lights in the scene (hidden-from-render lights do not count)")
            return False
        return True

    # -- synchronous (scripts, background mode) ------------------------------------------
    def execute(self, context):
        if self.confirmed and not bpy.app.background and context.window is not None:
            return self._start_modal(context)  # the confirmation dialog's OK: the UI's bake
        job = BakeJob(context)
        try:
            job.start(context)
            job.run()
            message = job.finish(context)
        except Exception as ex:
            job.cancel()
            _report_failure(self, ex, "the bake")
            if not self._keep_finished_frames(context, job, "failed"):
                return {"CANCELLED"}
            return {"FINISHED"}
        self._report_warnings(job)
        self.report({"INFO"}, message)
        save = self.save_blend if self.properties.is_property_set("save_blend") else bpy.app.background
        if save and bpy.data.filepath:
            bpy.ops.wm.save_mainfile()
        return {"FINISHED"}

    # -- modal (the UI) -------------------------------------------------------------------
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        return self._start_modal(context, event)

    def _start_modal(self, context, event=None):
        """Start the bake in the background of the UI (progress bar, Esc cancels).  With
        ``event`` (invoke), a very large bake (addon.bake.estimate.needs_confirmation) first asks:
        the dialog's OK runs :meth:`execute` with ``confirmed``, which comes back here."""
        from ..bake.estimate import needs_confirmation

        self._timer = None
        self._job = BakeJob(context, modal=True)
        try:
            self._job.start(context)
        except Exception as ex:
            self._job.cancel()
            _report_failure(self, ex, "the bake")
            return {"CANCELLED"}
        estimate = self._job.estimate() if event is not None and not self.confirmed else None
        if estimate is not None and needs_confirmation(estimate):
            self._job.cancel()
            self._job = None
            self.confirmed = True
            return context.window_manager.invoke_confirm(
                self, event, title="Caustic Bake: a very large bake", message=confirmation_message(estimate),
                confirm_text="Bake", icon="WARNING")
        STATE.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.02, window=context.window)
        wm.progress_begin(0, 1000)
        wm.modal_handler_add(self)
        self._status(context, "Caustic Bake: starting (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            self._job.cancel()
            kept = self._keep_finished_frames(context, self._job, "cancelled")
            self._end(context)
            if kept:
                return {"FINISHED"}  # the finished frames were applied: one undo step
            self.report({"WARNING"}, "Caustic Bake cancelled; nothing was changed")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            done = self._job.step()
            if done:
                message = self._job.finish(context)
        except Exception as ex:
            self._job.cancel()
            _report_failure(self, ex, "the bake")
            kept = self._keep_finished_frames(context, self._job, "failed")
            self._end(context)
            return {"FINISHED"} if kept else {"CANCELLED"}
        if not done:
            context.window_manager.progress_update(int(1000 * STATE.fraction))
            self._status(context, "Caustic Bake {:.0f}%: {} (Esc to cancel)".format(100 * STATE.fraction, STATE.message))
            self._redraw(context)
            return {"RUNNING_MODAL"}
        self._end(context)
        self._report_warnings(self._job)
        self.report({"INFO"}, message)
        return {"FINISHED"}

    def _keep_finished_frames(self, context, job, why):
        """A frame range stopped (cancelled or failed) after some frames: show those (their
        files are written).  True if something was applied."""
        if job.frames is None or not job.done_frames:
            return False
        try:
            message = job.finish(context)
        except Exception as ex:
            _report_failure(self, ex, "applying the finished frames")
            return False
        self.report({"WARNING"}, "Caustic Bake {} at frame {}/{}; kept the {} finished frame(s) {}-{}".format(
            why, len(job.done_frames) + 1, len(job.frames), len(job.done_frames), job.done_frames[0], job.done_frames[-1]))
        self.report({"INFO"}, message)
        return True

    def cancel(self, context):  # Blender ends the operator (file load, window closed)
        if getattr(self, "_job", None) is not None:
            self._job.cancel()
        self._end(context)

    def _end(self, context):
        STATE.reset()
        wm = context.window_manager
        if getattr(self, "_timer", None) is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._status(context, None)
        self._redraw(context)

    @staticmethod
    def _status(context, text):
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(text)

    @staticmethod
    def _redraw(context):
        screen = getattr(context, "screen", None)
        for area in (screen.areas if screen is not None else ()):
            if area.type == "PROPERTIES":
                area.tag_redraw()

    def _report_warnings(self, job):
        if job.warnings:
            more = " (+{} more in the console)".format(len(job.warnings) - 1) if len(job.warnings) > 1 else ""
            self.report({"WARNING"}, "Caustic Bake: {}{}".format(job.warnings[0], more))
            for w in job.warnings:
                print("Caustic Bake warning:", w)


def baked_images():
    """Names of the images an earlier bake made (what Clear would remove)."""
    from ..bake.apply import TAG_KEY

    return sorted(img.name for img in bpy.data.images if img.get(TAG_KEY))


def has_bake():
    from ..bake.apply import STATE_KEY, node_groups

    return bool(baked_images()) or bool(node_groups()) or any(m.get(STATE_KEY) is not None for m in bpy.data.materials)


class CAUSTICS_OT_clear(bpy.types.Operator):
    """Remove the baked caustic textures and the nodes and node group the bake added"""

    bl_idname = "caustics.clear"
    bl_label = "Clear Caustics"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if STATE.running:
            cls.poll_message_set("A caustic bake is running")
            return False
        if not has_bake():
            cls.poll_message_set("Nothing to clear: no caustic bake in this file")
            return False
        return True

    def execute(self, context):
        from ..bake.apply import clear_bake

        n = len(baked_images())
        try:
            clear_bake(delete_files=True)
        except Exception as ex:
            _report_failure(self, ex, "clearing")
            return {"CANCELLED"}
        if hasattr(context.scene, "caustic_bake"):
            context.scene.caustic_bake.last_plan = ""
        self.report({"INFO"}, "Caustic Bake: cleared {} texture(s)".format(n))
        return {"FINISHED"}
