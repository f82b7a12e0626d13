"""The names of the files a bake writes, shared by the CLI, the Dask workers and the Blender
operator (no bpy, no numba: the UI layer imports it at draw time)."""


def safe_filename(name):
    """``name`` (an object name) as a file name: characters that no file system allows, or
    that Windows does not, become ``_``; surrounding spaces and trailing dots go."""
    bad = '<>:"/\\|?*\0'
    out = "".join("_" if (c in bad or ord(c) < 32) else c for c in name).strip().rstrip(".")
    return out or "receiver"


def texture_filename(receiver, frame=None):
    """The file name of receiver ``receiver``'s texture, for the CLI and the Blender operator
    alike: ``<receiver>.exr`` for one frame, ``<receiver>.<frame>.exr`` in a sequence with the
    frame number zero-padded to 4 digits (Blender's ``####``: an Image with source ``SEQUENCE``
    loaded from one file of the sequence finds frame f in the file numbered f)."""
    stem = safe_filename(receiver)
    if frame is None:
        return stem + ".exr"
    if int(frame) < 0:
        raise ValueError(f"frame {frame}: a sequence's frames are numbered from 0")
    return f"{stem}.{int(frame):04d}.exr"


def frame_report_filename(frame):
    """The file name of one frame's report in a sequence's folder: ``report.<frame>.json``."""
    return f"report.{int(frame):04d}.json"
