"""A frame range baked on the workers of a Dask cluster (``--dask ADDRESS``, ``--dask-local N``).

One task per frame, :func:`addon.bake.cli.bake_frame_task`: a worker opens the .blend with the
bpy module, bakes that frame and writes its files of the sequence, exactly as the serial
``--frames`` loop does, so the textures are the serial bake's bit for bit (the bake is
deterministic for its settings, whichever process runs it).  This process only hands out the
frames, prints each frame's line as it finishes and rebuilds ``report.json`` from the frame
reports at the end.  dask is imported here, only when a Dask option is given.
"""

from .cli import UserError

DASK_MISSING = ("--dask and --dask-local need dask.distributed, which is not installed: "
                "pip install 'dask[distributed]==2026.8.0'")


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise UserError(DASK_MISSING) from None
    return distributed


def bake_frames_on_dask(blend, frames, out_dir, settings, resolution, address=None, local_workers=None,
                        connect_timeout=30):
    """Bake ``frames`` of ``blend`` into ``out_dir`` on the Dask cluster at ``address``, or on a
    local cluster of ``local_workers`` processes (one thread each); returns the frames' results
    ({"frame", "line", "warnings", "files"}) in frame order.  A frame that fails stops the bake
    with its one-line reason (:class:`UserError`); frames already written stay."""
    import os

    distributed = _import_distributed()
    from .pipeline import write_sequence_report

    os.makedirs(out_dir, exist_ok=True)
    cluster = None
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
        from .cli import _print_frames, bake_frame_task

        with client:
            futures = client.map(bake_frame_task, frames, blend=blend, out_dir=out_dir, settings=settings,
                                 resolution=resolution, pure=False)
            results = {}
            try:
                for fut in distributed.as_completed(futures):
                    r = fut.result()
                    if "error" in r:
                        raise UserError(r["error"])
                    results[r["frame"]] = r
                    _print_frames([r])
            finally:
                client.cancel([f for f in futures if not f.done()])
    finally:
        if cluster is not None:
            cluster.close()
        if os.path.isdir(out_dir):
            write_sequence_report(out_dir)
    return [results[f] for f in frames]
