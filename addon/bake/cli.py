"""``python -m addon bake SCENE.blend --out DIR ...``: bake a .blend with the bpy module.

Writes ``DIR/<receiver object name>.exr`` (float32 RGB irradiance, W/m²) and ``DIR/report.json``.
With ``--frames A:B`` it writes an EXR sequence per receiver into ``DIR``:
``DIR/<receiver>.<frame, 4 digits>.exr`` (:func:`addon.bake.pipeline.texture_filename`, the names
the Blender operator gives a sequence), each frame's report ``DIR/report.<frame>.json`` and
``DIR/report.json``, the index of every frame reported in ``DIR`` (so jobs that bake different
frames into one folder, e.g. render-farm chunks, add up to one sequence).  ``--dask ADDRESS``
or ``--dask-local N`` bakes the frames on the workers of a Dask cluster
(:func:`bake_frame_task`, one task per frame; dask is imported only then; the workers need the
bpy module, this package importable and the .blend and ``DIR`` at the same paths).

Files are written all or nothing (:mod:`addon.bake.output`: temporary files renamed into
place), and listed in ``DIR/.caustic_bake_files.json``; a file in ``DIR`` the bake would
replace that is not listed there (a user's) is refused before the bake, unless ``--force``.
Receivers whose names make the same file name get unique ones (:mod:`addon.bake.names`).
A long bake prints its estimate before it starts (addon.bake.estimate) and a progress line
with the time left every 10 s; a very large one (over 10 minutes by the estimate) asks first on
a terminal and elsewhere stops with one line unless ``--yes``.  Wrong input and write
failures exit with code 2 and a one-line reason on stderr (no traceback); Ctrl-C (SIGINT) with
code 130 and one line.
"""

import os
import re
import socket
import sys
import time

from .settings import DEFAULT_PLAN_THRESHOLD, ESTIMATORS, SOLVERS


class UserError(Exception):
    """Bad input: reported as one line, exit code 2."""


BPY_MISSING = "the bake needs Blender's Python module: pip install bpy==5.0.1 (Python 3.11)"


def add_arguments(parser):
    parser.add_argument("blend", help="the .blend file to bake")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--resolution", type=int, default=None, help="texels per side for every receiver (default: 256, or the object's caustic_resolution)")
    parser.add_argument("--samples", type=int, default=4, help="supersamples per texel (default 4)")
    parser.add_argument("--bounces", default="auto", choices=("auto", "1", "2"),
                        help="specular bounces: auto (default: the planner bakes the chains of up to 2 bounces that "
                        "carry at least --plan-threshold of a receiver's caustic energy), or 1 / 2 to force every chain "
                        "of up to that many bounces")
    parser.add_argument("--plan-threshold", type=float, default=DEFAULT_PLAN_THRESHOLD, metavar="SHARE",
                        help="--bounces auto: skip chains below this share of a receiver's caustic energy (default 0.005)")
    parser.add_argument("--frames", default=None, help="frame range A:B (inclusive, A >= 0): an EXR sequence per receiver, "
                        "DIR/<receiver>.<frame>.exr; default: the current frame, DIR/<receiver>.exr")
    parser.add_argument("--dask", default=None, metavar="ADDRESS",
                        help="bake the --frames on the workers of the Dask cluster whose scheduler is at ADDRESS "
                        "(e.g. tcp://farm:8786; needs dask[distributed]; the workers need the bpy module, this "
                        "package on their PYTHONPATH and the .blend and --out at the same paths)")
    parser.add_argument("--dask-local", type=int, default=None, metavar="N",
                        help="bake the --frames on a local Dask cluster of N worker processes (one task at a time "
                        "each; without --threads each bakes with cores / N threads)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (supersample jitter, light samples)")
    parser.add_argument("--light-samples", type=int, default=1, help="samples of light radius / area / sun angle (default 1: point lights)")
    parser.add_argument("--margin", type=int, default=16, help="texels of padding over UV seams (default 16)")
    parser.add_argument("--threads", type=int, default=0, help="worker threads (default: all cores)")
    parser.add_argument("--device", default="numba", metavar="DEVICE",
                        help="numba (CPU, default), opencl (first OpenCL device) or opencl:N: forward-flux refines its "
                        "sub-triangles, traces their points and splats them there (the same texture; the flux terms "
                        "on the CPU), path-points solves every chain there (on a CPU device two bounces build their "
                        "systems on Numba beside it); a missing pyopencl / device runs on Numba with a warning")
    parser.add_argument("--estimator", default=None, choices=ESTIMATORS,
                        help="forward-flux (default: forward-traced sub-triangles, their flux spread over their images: "
                        "texel averages, noise-free), path-points (every exact path at every texel supersample, solved by "
                        "--solver), path-seeded (exact two-bounce paths by Newton from forward-image seeds) or photon "
                        "(light tracing)")
    parser.add_argument("--solver", default=None, choices=SOLVERS,
                        help="path-points: spoly (Specular Polynomials, every chain; default), newton (MNEE from Path "
                        "Cuts seeds: R, T), sms (Specular Manifold Sampling: R, T) or curve (dimension-reduction MNEE: "
                        "T); chains a solver cannot solve are skipped with a warning")
    parser.add_argument("--method", default=None, choices=SOLVERS + ("photon",),
                        help="alias: spoly/newton/sms/curve = --estimator path-points --solver NAME (spoly alone "
                        "keeps the default estimator), photon = --estimator photon")
    parser.add_argument("--one-bounce", default=None, choices=("flux", "points"),
                        help="alias: the estimator of R and T (flux = forward-flux, points = path-points)")
    parser.add_argument("--two-bounce", default=None, choices=("flux", "seeded", "exact"),
                        help="alias: the estimator of RR, RT, TR, TT (flux = forward-flux, seeded = path-seeded, "
                        "exact = path-points)")
    parser.add_argument("--sms-seeds", type=int, default=16, help="method sms: random Newton seeds per tuple (default 16)")
    parser.add_argument("--photons", type=int, default=1_000_000, help="method photon: photons traced (default 1,000,000)")
    parser.add_argument("--memory-budget", type=float, default=None, metavar="GB",
                        help="memory the bake's textures may take, in GB (default: half the memory available); a bake "
                        "that needs more stops before it starts, with one line")
    parser.add_argument("--yes", action="store_true",
                        help="bake a very large job without asking (default: a bake estimated to take more than 10 "
                        "minutes asks on a terminal, and stops with one line elsewhere)")
    parser.add_argument("--force", action="store_true",
                        help="overwrite files in --out that Caustic Bake did not write (default: refuse with the file's name)")
    parser.add_argument("--preview", default=None, metavar="PNG",
                        help="also render the baked scene with Cycles (scene camera, Cycles' own caustics off) to this PNG")
    parser.add_argument("--preview-samples", type=int, default=32, help="Cycles samples for --preview (default 32)")


def _frames(spec):
    if spec is None:
        return None
    try:
        a, b = spec.split(":")
        a, b = int(a), int(b)
    except ValueError:
        raise UserError(f"--frames must look like A:B (for example 1:24), got {spec!r}") from None
    if b < a:
        raise UserError(f"--frames {spec}: the last frame is before the first")
    if a < 0:
        raise UserError(f"--frames {spec}: frames must be 0 or more (they number the sequence's files)")
    return list(range(a, b + 1))


def run(args):
    """Run the bake command; returns the exit code."""
    from .output import OutputError

    try:
        return _run(args)
    except (UserError, OutputError) as ex:
        print(f"error: {ex}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C / SIGINT: every write is all or nothing, so nothing is partial
        print("error: interrupted; files written before stay as they were, none is partly written", file=sys.stderr)
        return 130


def _run(args):
    path = os.path.abspath(args.blend)
    if not os.path.isfile(path):
        raise UserError(f"no such file: {args.blend}")
    if args.samples < 1:
        raise UserError("--samples must be at least 1")
    if args.resolution is not None and not 1 <= args.resolution <= 16384:
        raise UserError("--resolution must be between 1 and 16384")
    if args.light_samples < 1 or args.margin < 0 or args.threads < 0:
        raise UserError("--light-samples must be >= 1, --margin and --threads >= 0")
    if not 1 <= args.sms_seeds <= 4096 or args.photons < 1:
        raise UserError("--sms-seeds must be in [1, 4096] and --photons at least 1")
    if getattr(args, "memory_budget", None) is not None and not args.memory_budget > 0:
        raise UserError("--memory-budget must be a positive number of GB")
    if not 0.0 <= args.plan_threshold < 1.0:
        raise UserError("--plan-threshold must be in [0, 1)")
    if not re.fullmatch(r"numba|opencl(:\d+)?", args.device or ""):
        raise UserError(f"--device must be numba, opencl or opencl:N, got {args.device!r}")
    frames = _frames(args.frames)
    if args.preview and frames:
        raise UserError("--preview renders one frame; leave out --frames")
    if args.dask is not None and args.dask_local is not None:
        raise UserError("--dask and --dask-local exclude each other: give one")
    if args.dask_local is not None and args.dask_local < 1:
        raise UserError("--dask-local must be at least 1 (worker processes)")
    if (args.dask is not None or args.dask_local is not None) and not frames:
        raise UserError("--dask and --dask-local spread a frame range: give --frames A:B")
    if args.dask is None:  # on a remote cluster only the workers need bpy
        try:
            import bpy  # noqa: F401
        except ImportError:
            raise UserError(BPY_MISSING) from None
    with open(path, "rb") as fh:
        magic = fh.read(7)
    if magic != b"BLENDER" and magic[:2] not in (b"\x1f\x8b", b"\x28\xb5"):  # plain, gzip or zstd
        raise UserError(f"not a .blend file: {args.blend}")
    settings = settings_from_args(args)
    resolution = args.resolution or 256
    if args.dask_local is not None and not settings.threads:
        # the local workers share this machine's cores (the texture does not depend on the count)
        settings.threads = max(1, (os.cpu_count() or 1) // args.dask_local)
    out = os.path.abspath(args.out)
    force = bool(getattr(args, "force", False))
    if args.dask is not None or args.dask_local is not None:
        if not force:
            refuse_foreign(out, sequence_names_in(out, frames))
        results = _bake_frames_on_dask(path, frames, out, settings, resolution,
                                      address=args.dask, local_workers=args.dask_local)
        _print_frames(results)
        return 0
    from .extract import open_blend

    try:
        open_blend(path)
    except RuntimeError as ex:
        raise UserError(f"could not open {args.blend}: {str(ex).strip().splitlines()[-1]}") from None
    if frames:
        if not force:
            refuse_foreign(out, [SEQUENCE_REPORT])
        done = 0
        try:
            for frame in frames:
                check = confirm_large_bake(args, len(frames)) if frame == frames[0] else None
                _print_frames([bake_frame(path, frame, out, settings, resolution, force=force, confirm=check)])
                done += 1
        finally:
            if done:
                write_sequence_index(out)  # the index of every frame in the folder
        return 0
    scene, result = _bake_open_scene(path, None, settings, resolution, out_dir=None if force else out,
                                     confirm=confirm_large_bake(args))
    result.write(out)  # all or nothing: OutputError (one line) leaves the folder as it was
    print(f"{summary_line(result.report)} -> {args.out}")
    for w in result.report["warnings"]:
        print(f"warning: {w}")
    if args.preview:
        render_preview(scene, result, args.out, args.preview, args.preview_samples)
        print(f"preview -> {args.preview}")
    return 0


SEQUENCE_REPORT = "report.json"


def refuse_foreign(out_dir, names):
    """Raise :class:`UserError` naming the first of ``names`` in ``out_dir`` that exists and
    that Caustic Bake did not write there (the folder's manifest); ``--force`` skips this."""
    from .output import foreign_files

    clash = foreign_files(out_dir, names) if os.path.isdir(out_dir) else []
    if clash:
        raise UserError(f"{clash[0]} exists and was not written by Caustic Bake; choose another --out or pass --force "
                        "to overwrite it")


def sequence_names_in(out_dir, frames):
    """The files in ``out_dir`` a bake of ``frames`` may write, whatever its receivers: the
    sequence index, the frames' reports and every ``*.<frame>.exr`` of those frames."""
    from .names import frame_report_filename

    tags = {f".{int(f):04d}.exr" for f in frames}
    names = [SEQUENCE_REPORT] + [frame_report_filename(f) for f in frames]
    if os.path.isdir(out_dir):
        names += [n for n in os.listdir(out_dir) if any(n.endswith(t) for t in tags)]
    return names


def write_sequence_index(out_dir):
    """Rebuild ``out_dir/report.json`` from the frame reports there and list it in the folder's manifest."""
    from .output import record_written
    from .pipeline import write_sequence_report

    write_sequence_report(out_dir)
    record_written(out_dir, add=[SEQUENCE_REPORT])


PROGRESS_INTERVAL = 10.0  # seconds between the progress lines of a long bake


class ProgressPrinter:
    """The ``progress(fraction, message)`` callback of a CLI bake: a line
    ``progress 37 %: <what runs now> (about 2 min 5 s left)`` on stdout at most every
    :data:`PROGRESS_INTERVAL` seconds, the first after that long (short bakes print none)."""

    def __init__(self, prefix=""):
        self.prefix = prefix
        self.last = time.perf_counter()

    def __call__(self, fraction, message):
        now = time.perf_counter()
        if now - self.last >= PROGRESS_INTERVAL and fraction is not None:
            print(f"{self.prefix}progress {100 * fraction:.0f} %: {message}", flush=True)
            self.last = now


LONG_BAKE_SECONDS = 60.0  # a bake estimated to take longer prints its estimate before it starts


def confirm_large_bake(args, frames=1):
    """The check :func:`_bake_open_scene` runs on the bake's estimate (addon.bake.estimate) of
    ``frames`` frames before it starts: prints the estimate of a long bake, and for a very large
    one (``needs_confirmation``) asks on a terminal, or stops with one line elsewhere, unless
    ``--yes``."""
    from .estimate import needs_confirmation

    def check(estimate):
        total = estimate.times(frames)
        if total.seconds >= LONG_BAKE_SECONDS:
            print(f"estimate: {total.line()}", flush=True)
        if not needs_confirmation(total) or getattr(args, "yes", False):
            return
        question = f"the bake needs {total.line()} ({total.texels:,} texels)"
        if sys.stdin is not None and sys.stdin.isatty():
            if input(f"{question}; bake it? [y/N] ").strip().lower() in ("y", "yes"):
                return
            raise UserError(f"{question}; not baked")
        raise UserError(f"{question}; pass --yes to bake it")

    return check


def _bake_open_scene(path, frame, settings, resolution, out_dir=None, progress=True, confirm=None):
    """Extract the open scene (at ``frame``, or the current frame) and bake it; returns
    (scene model, BakeResult) with ``report["input"]`` and the extraction time filled in.
    ``out_dir``: before the bake, refuse (:func:`refuse_foreign`) when a file the bake will
    write there exists and Caustic Bake did not write it; ``confirm``: called with the bake's
    :class:`~addon.bake.estimate.BakeEstimate` before it starts (it raises to stop)."""
    import bpy

    from .extract import extract_scene
    from .pipeline import bake_steps, run_steps
    from .scene import SceneError

    t0 = time.perf_counter()
    try:
        scene = extract_scene(resolution=resolution, frame=frame)
        t_extract = time.perf_counter() - t0
        if out_dir is not None:
            from .names import frame_report_filename, texture_filename

            names = [r.name for r in scene.receivers]
            refuse_foreign(out_dir, [texture_filename(n, frame, receivers=names) for n in names] + [
                SEQUENCE_REPORT if frame is None else frame_report_filename(frame)])
        steps = bake_steps(scene, settings)  # the scene, settings and memory budget checked here
        if confirm is not None:
            from .estimate import estimate_bake

            try:
                confirm(estimate_bake(scene, settings))
            except UserError:
                steps.close()
                raise
        prefix = f"frame {frame}: " if frame is not None else ""
        result = run_steps(steps, progress=ProgressPrinter(prefix) if progress else None)
    except SceneError as ex:
        where = f" (frame {frame})" if frame is not None else ""
        raise UserError(f"{ex}{where}") from None
    result.report["input"] = {"blend": path, "frame": int(bpy.context.scene.frame_current),
                              "host": socket.gethostname(), "pid": os.getpid()}
    result.report["timings"]["extract"] = t_extract
    return scene, result


def bake_frame(path, frame, out_dir, settings, resolution, force=False, record=True, progress=True, confirm=None):
    """Bake frame ``frame`` of the open .blend (``path``, for the report) and write that
    frame's files of the sequence in ``out_dir`` (:meth:`BakeResult.write` with the frame, all
    or nothing), refusing to replace a file Caustic Bake did not write there unless ``force``;
    ``record``: list the files in the folder's manifest (the Dask driver does it for its
    workers; ``progress``: print progress lines).  Returns {"frame", "line" (the summary line),
    "warnings", "files" (receiver: texture), "written" (every file name written)}."""
    from .output import OutputError

    _, result = _bake_open_scene(path, frame, settings, resolution, out_dir=None if force else out_dir,
                                 progress=progress, confirm=confirm)
    try:
        files = result.write(out_dir, frame=frame, record=record)
    except OutputError as ex:
        raise UserError(str(ex)) from None
    return {"frame": frame, "line": f"{summary_line(result.report)} -> {out_dir}",
            "warnings": list(result.report["warnings"]), "files": files, "written": result.output_names(frame)}


def bake_frame_task(frame, blend, out_dir, settings, resolution):
    """One frame on a worker process (the Dask task): open ``blend`` with the bpy module, bake
    frame ``frame`` and write its files into ``out_dir``, as the serial ``--frames`` loop
    does (:func:`bake_frame`).  A bad scene comes back as {"frame", "error": one line}."""
    _forget_bpy_script_paths()
    try:
        from .extract import open_blend
    except ImportError as ex:
        if (getattr(ex, "name", None) or "").split(".")[0] not in ("bpy", "_bpy"):
            raise
        return {"frame": frame, "error": f"{BPY_MISSING} (on the Dask worker {socket.gethostname()})"}

    try:
        open_blend(blend)
    except RuntimeError as ex:
        return {"frame": frame, "error": f"could not open {blend}: {str(ex).strip().splitlines()[-1]}"}
    try:
        return bake_frame(blend, frame, out_dir, settings, resolution, force=True, record=False, progress=False)
    except UserError as ex:
        return {"frame": frame, "error": str(ex)}


DASK_MISSING = ("--dask and --dask-local need dask.distributed, which is not installed: "
                "pip install 'dask[distributed]==2026.8.0'")


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise UserError(DASK_MISSING) from None
    return distributed


def _bake_frames_on_dask(blend, frames, out_dir, settings, resolution, address=None, local_workers=None,
                         connect_timeout=30):
    """Bake ``frames`` of ``blend`` into ``out_dir`` on the Dask cluster at ``address``, or on a
    local cluster of ``local_workers`` processes (one thread each); returns the frames' results
    ({"frame", "line", "warnings", "files"}) in frame order.  One task per frame,
    :func:`bake_frame_task`: the serial loop's :func:`bake_frame` on a worker process, so the
    textures are the serial bake's bit for bit (the bake is deterministic for its settings,
    whichever process runs it); this process prints each frame's line as it finishes and
    rebuilds ``report.json`` from the frame reports at the end.  A frame that fails stops the
    bake with its one-line reason (:class:`UserError`); frames already written stay."""
    distributed = _import_distributed()
    from .output import record_written

    cluster = None
    results = {}
    try:
        if local_workers is not None:
            cluster = distributed.LocalCluster(n_workers=int(local_workers), processes=True, threads_per_worker=1,
                                               dashboard_address=None)
            client = distributed.Client(cluster)
        else:
            try:
                client = distributed.Client(address, timeout=connect_timeout)
            except (OSError, TimeoutError, ValueError) as ex:
                raise UserError(f"cannot reach the Dask scheduler at {address}: {ex}") from None
        with client:
            futures = client.map(bake_frame_task, frames, blend=blend, out_dir=out_dir, settings=settings,
                                 resolution=resolution, pure=False)
            try:
                for fut in distributed.as_completed(futures):
                    r = fut.result()
                    if "error" in r:
                        raise UserError(r["error"])
                    record_written(out_dir, add=r["written"])
                    results[r["frame"]] = r
                    _print_frames([r])
            finally:
                client.cancel([f for f in futures if not f.done()])
    finally:
        if cluster is not None:
            cluster.close()
        if results:
            write_sequence_index(out_dir)
    return [results[f] for f in frames]


def _forget_bpy_script_paths():
    """Before the first ``import bpy`` of a process: drop the folders of Blender's own Python
    scripts (``.../bpy/<version>/scripts/...``) from ``sys.path``.  A worker process spawned by a
    process that had imported bpy inherits them, and there ``import bpy`` would find the
    scripts' ``bpy`` package instead of the module itself."""
    if "bpy" in sys.modules:
        return
    sys.path[:] = [p for p in sys.path if not re.search(r"[\\/]bpy[\\/]\d+\.\d+[\\/]scripts([\\/]|$)", p)]


def _print_frames(results):
    for r in results:
        print(f"frame {r['frame']}: {r['line']}")
        for w in r["warnings"]:
            print(f"warning: frame {r['frame']}: {w}")


def settings_from_args(args):
    """The BakeSettings of the parsed command line (the aliases resolved by the pipeline)."""
    from .settings import BakeSettings, resolve_aliases

    settings = resolve_aliases(BakeSettings(resolution=args.resolution or 0, samples=args.samples,
                            bounces=args.bounces if args.bounces == "auto" else int(args.bounces),
                            plan_threshold=args.plan_threshold, seed=args.seed, light_samples=args.light_samples,
                            margin=args.margin, threads=args.threads, device=args.device, sms_seeds=args.sms_seeds,
                            photons=args.photons, method=args.method, one_bounce=args.one_bounce, two_bounce=args.two_bounce,
                            memory_budget=1e9 * (getattr(args, "memory_budget", None) or 0.0)))
    if args.estimator:  # explicit names win over the aliases
        settings.estimator = args.estimator
    if args.solver:
        settings.solver = args.solver
    return settings


def summary_line(report):
    """One line: receivers, time, what ran (estimators and their work) and the plan per receiver,
    e.g. ``baked 1 receiver(s) in 3.1 s [forward-flux: 52,110 sub-triangles]: Floor: TT 95.5 %, R 4.5 %
    (skipped: RR, RT, TR)``."""
    c = report["counts"]
    work = []
    for name, est in report.get("estimators", {}).items():
        if name == "forward-flux":
            what = f"{est['sub_triangles']:,} sub-triangles"
        elif name == "photon":
            what = f"{est['photons']:,} photons, {est['photons_deposited']:,} deposited"
        else:
            what = f"{c['tuples']:,} tuples, {c['paths_visible']:,} paths"
            if name == "path-points":
                name = f"path-points/{est['solver']}"
        work.append(f"{name} ({'/'.join(est['chains'])}): {what}")
    plan = "; ".join(report.get("plan", {}).get("summary", []))
    return (f"baked {len(report['receivers'])} receiver(s) in {report['timings']['bake_total']:.2f} s "
            f"[{'; '.join(work) or 'nothing'}]: {plan}")


def render_preview(scene_model, result, out_dir, png, samples):
    """Show the bake on the open scene (images from ``out_dir``) and render it with Cycles."""
    import bpy

    from .apply import apply_bake, receivers_uv_maps

    if bpy.context.scene.camera is None:
        raise UserError("--preview needs a scene camera")
    # the EXRs result.write() put in out_dir are what the preview shows (no second copy)
    files = {name: os.path.join(os.path.abspath(out_dir), fname) for name, fname in result.report.get("files", {}).items()}
    apply_bake(result.images, receivers_uv_maps(scene_model), directory=os.path.abspath(out_dir), files=files)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = max(1, int(samples))
    sc.cycles.use_denoising = False
    # Cycles' own (noisy) caustics off: the baked ones are shown instead.
    sc.cycles.caustics_reflective = False
    sc.cycles.caustics_refractive = False
    sc.render.image_settings.file_format = "PNG"
    sc.render.filepath = os.path.abspath(png)
    bpy.ops.render.render(write_still=True)
