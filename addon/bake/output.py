"""Writing a bake's files without losing or overwriting anything (no bpy).

- All or nothing: :func:`write_files` writes every file of a bake to a temporary file in the
  target folder first (``.<name>.<random>.tmp``) and only when all of them are complete
  renames each over its final name (``os.replace``, atomic on one file system).  A failure
  (read-only folder, disk full, OpenEXR's ``RuntimeError``) removes the temporary files and
  raises :class:`OutputError` with one line; the files already there are untouched.  The
  renames themselves are all or none (:func:`replace_all`: a rename that fails undoes the
  ones done), for a bake's textures as for a frame range's staged frames (:func:`move_files`).
- Only our own files: the folder's manifest (:data:`FILES_MANIFEST`, JSON list of names) lists
  what Caustic Bake wrote there; :func:`foreign_files` names the files a bake would replace
  that are not in it (a user's files: refused, never overwritten).  The names are recorded
  before the renames, so a file is never ours on disk without being listed.
"""

import json
import os
import tempfile

from . import exr

FILES_MANIFEST = ".caustic_bake_files.json"
MANIFEST_LOCK = ".caustic_bake_files.lock"


class OutputError(OSError):
    """A bake's files could not be written (one line; nothing partial was left behind)."""

    def __init__(self, message, errno=None):
        super().__init__(message)
        self.errno = errno


def _reason(ex):
    if isinstance(ex, OSError) and ex.strerror:
        return ex.strerror
    lines = str(ex).strip().splitlines()
    return lines[-1] if lines else type(ex).__name__


def written_here(folder):
    """The names the manifest of ``folder`` lists (empty when there is none)."""
    try:
        with open(os.path.join(folder, FILES_MANIFEST), encoding="utf-8") as fh:
            names = json.load(fh)
        return {n for n in names if isinstance(n, str)}
    except (OSError, ValueError, TypeError):
        return set()


def record_written(folder, add=(), forget=()):
    """Add ``add`` to and drop ``forget`` from ``folder``'s manifest (written atomically, under
    an exclusive lock where the platform has ``fcntl``, so that processes baking into one
    folder at once, e.g. render-farm tasks, do not lose each other's names)."""
    with _manifest_lock(folder):
        names = (written_here(folder) | set(add)) - set(forget)
        write_text(os.path.join(folder, FILES_MANIFEST), json.dumps(sorted(names), indent=1))


class _manifest_lock:
    def __init__(self, folder):
        self.path = os.path.join(folder, MANIFEST_LOCK)
        self.fh = None

    def __enter__(self):
        try:
            import fcntl
        except ImportError:  # Windows: no lock
            return self
        try:
            self.fh = open(self.path, "a")
        except OSError as ex:
            raise OutputError(f"cannot write {self.path}: {_reason(ex)}", ex.errno) from None
        fcntl.flock(self.fh.fileno(), fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc):
        if self.fh is not None:
            self.fh.close()  # releases the lock
        return False


def foreign_files(folder, names):
    """The paths of ``names`` in ``folder`` that exist and that Caustic Bake did not write."""
    written = written_here(folder)
    return [os.path.join(folder, n) for n in names if n not in written and os.path.lexists(os.path.join(folder, n))]


def write_text(path, text):
    """Write ``text`` to ``path`` through a temporary file renamed over it (:class:`OutputError`)."""
    _write_all(os.path.dirname(path) or ".", {os.path.basename(path): lambda tmp: _write_plain(tmp, text)})


def _write_plain(tmp, text):
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)


def write_files(folder, writers, record=True):
    """Write the files ``writers`` ({file name: function(temporary path) writing it}) into
    ``folder`` all or nothing (see the module doc); ``record``: list them in the folder's
    manifest.  Returns {file name: absolute path}.  Raises :class:`OutputError`."""
    folder = os.path.abspath(folder)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as ex:
        raise OutputError(f"cannot create the folder {folder}: {_reason(ex)}", ex.errno) from None
    new = set(writers) - written_here(folder) if record else set()
    if new:
        record_written(folder, add=new)  # OutputError when the folder cannot be written
    try:
        return _write_all(folder, writers)
    except BaseException:  # OutputError, or an interrupt: the names recorded for this write are forgotten
        if new:
            try:
                record_written(folder, forget=new)
            except OSError:
                pass
        raise


def _write_all(folder, writers):
    staged = {}
    try:
        for name, write in writers.items():
            path = os.path.join(folder, name)
            try:
                fd, tmp = tempfile.mkstemp(prefix="." + name + ".", suffix=".tmp", dir=folder)
                os.close(fd)
                staged[name] = tmp
                write(tmp)
                os.chmod(tmp, 0o644)
            except (OSError, RuntimeError) as ex:
                raise OutputError(f"cannot write {path}: {_reason(ex)}", getattr(ex, "errno", None)) from None
        return replace_all(folder, staged)
    finally:
        for tmp in staged.values():
            if os.path.lexists(tmp):
                try:
                    os.unlink(tmp)
                except OSError:
                    pass


def move_files(source, folder, names):
    """Move the files ``names`` from the folder ``source`` into ``folder``, each renamed over
    the file of its name there (atomic per file), listed in ``folder``'s manifest first.
    Returns {file name: absolute path}.  Raises :class:`OutputError`."""
    folder = os.path.abspath(folder)
    record_written(folder, add=names)
    return replace_all(folder, {name: os.path.join(source, name) for name in names})


def replace_all(folder, sources):
    """Rename each file ``sources[name]`` over ``folder``/name, all or none: the files already
    there are first renamed aside (``.<name>.<random>.old``), and when a rename fails the ones
    done are undone (the earlier files back, the sources back where they were) before
    :class:`OutputError` is raised (and before an interrupt, SIGINT, goes on); on success the earlier files are deleted.  Renames within
    one file system are atomic; this makes the set of them one step too.  Returns {name:
    absolute path}."""
    done = []  # (name, path, source, the earlier file's aside name or None)
    try:
        for name, src in sources.items():
            path = os.path.join(folder, name)
            aside = None
            try:
                if os.path.lexists(path):
                    fd, aside = tempfile.mkstemp(prefix="." + name + ".", suffix=".old", dir=folder)
                    os.close(fd)
                    os.replace(path, aside)
                os.replace(src, path)
            except BaseException as ex:  # OSError, or an interrupt
                if aside is not None:
                    try:
                        if os.path.lexists(path):
                            os.unlink(aside)  # the earlier file was never moved aside
                        else:
                            os.replace(aside, path)  # this one's earlier file back
                    except OSError:
                        pass  # it stays under its aside name, never deleted
                if isinstance(ex, OSError):
                    raise OutputError(f"cannot write {path}: {_reason(ex)}", ex.errno) from None
                raise
            done.append((name, path, src, aside))
    except BaseException:  # OutputError, or an interrupt (SIGINT) between two renames: undo all
        for name, path, src, aside in reversed(done):  # undo: sources back, earlier files back
            try:
                os.replace(path, src)
                if aside is not None:
                    os.replace(aside, path)
            except OSError:
                pass
        raise
    for _name, _path, _src, aside in done:
        if aside is not None:
            try:
                os.unlink(aside)
            except OSError:
                pass
    return {name: path for name, path, _src, _aside in done}


def write_textures(folder, images, record=True):
    """Write ``images`` ({file name: (H, W, 3) irradiance}) as EXRs into ``folder``, all or
    nothing (:func:`write_files`).  Returns {file name: absolute path}."""
    return write_files(folder, {name: (lambda tmp, img=img: exr.write_exr(tmp, img)) for name, img in images.items()},
                       record=record)
