"""The names of the files a bake writes, shared by the CLI, the Dask workers and the Blender
operator (no bpy, no numba: the UI layer imports it at draw time).

A receiver's file stem is its object name made safe for every file system
(:func:`safe_filename`) and then unique among the bake's receivers ignoring case
(:func:`texture_stems`: ``a/b`` and ``a_b``, or ``Floor`` and ``floor``, never share a file).
The operator writes into a folder of its own per .blend (:func:`blend_folder`).
"""

import os


def safe_filename(name):
    """``name`` (an object name) as a file name: characters that no file system allows, or
    that Windows does not, become ``_``; surrounding spaces and trailing dots go."""
    bad = '<>:"/\\|?*\0'
    out = "".join("_" if (c in bad or ord(c) < 32) else c for c in name).strip().rstrip(".")
    return out or "receiver"


def texture_stems(receivers):
    """{receiver: file stem} for the receiver names of one bake: :func:`safe_filename` of each,
    made unique ignoring case (file systems that ignore case would merge them otherwise).
    Names that sanitising leaves unchanged keep their stem; the others, in sorted order, get
    ``_2``, ``_3``, ... where their stem is taken.  The same set of names always gives the
    same stems, whatever their order."""
    names = sorted(set(receivers), key=lambda n: (safe_filename(n) != n, n))
    taken, out = set(), {}
    for name in names:
        stem = safe_filename(name)
        cand, k = stem, 2
        while cand.casefold() in taken:
            cand, k = f"{stem}_{k}", k + 1
        taken.add(cand.casefold())
        out[name] = cand
    return out


def texture_filename(receiver, frame=None, receivers=None):
    """The file name of receiver ``receiver``'s texture, for the CLI, the Dask workers and the
    Blender operator alike: ``<stem>.exr`` for one frame, ``<stem>.<frame>.exr`` in a sequence
    with the frame number zero-padded to 4 digits (Blender's ``####``: an Image with source
    ``SEQUENCE`` loaded from one file of the sequence finds frame f in the file numbered f).
    ``receivers``: every receiver name of the bake, so that the stem is unique among them
    (:func:`texture_stems`); without it the stem is :func:`safe_filename` of the name."""
    stem = texture_stems(list(receivers) + [receiver])[receiver] if receivers is not None else safe_filename(receiver)
    if frame is None:
        return stem + ".exr"
    if int(frame) < 0:
        raise ValueError(f"frame {frame}: a sequence's frames are numbered from 0")
    return f"{stem}.{int(frame):04d}.exr"


def frame_report_filename(frame):
    """The file name of one frame's report in a sequence's folder: ``report.<frame>.json``."""
    return f"report.{int(frame):04d}.json"


def blend_folder(directory, blend_path):
    """The operator's output folder for the .blend at ``blend_path``: ``directory``/<blend file
    name without .blend>/ (``//caustics/`` gives ``//caustics/<blend>/``), so that every .blend
    baking into one folder keeps its own textures; an unsaved file's is ``untitled``."""
    stem = os.path.splitext(os.path.basename(blend_path or ""))[0]
    return directory.rstrip("/\\") + "/" + safe_filename(stem or "untitled") + "/"
