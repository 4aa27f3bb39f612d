"""Writing output files safely: only regular files, atomically, and an artifact's files all or none.

- :func:`check_writable`, :func:`check_folder`, :func:`check_regular`: an output path is refused *before* any
  work when its folder cannot be created or written, or when something that is not a regular file (a device,
  fifo, socket, or a folder where a file is expected) is there;
- :func:`atomic_write_bytes`: a temp file in the same folder, fsync, ``os.replace``; refuses non-regular files;
  an OS error (a full disk, a read-only file system) is one ``SdpError`` naming the path;
- :func:`artifact_writes`: the files written inside form one artifact (an ``.npz`` and its timing sidecar; a
  checkpoint with its metrics and timing): if any write fails, or the process is interrupted between them, the
  files written so far are removed and the files they replaced get their earlier bytes back.

:mod:`sdp_cli.data.artifacts` re-exports these.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
import tempfile
from pathlib import Path
import shutil

from sdp_cli.errors import SdpError


def ensure_dir(path: str | os.PathLike, what: str) -> Path:
    """Create the output folder ``path`` (``what``: e.g. "run folder") or raise one clear ``SdpError``."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SdpError(f"cannot create the {what} {path}: {e.strerror or e}") from None
    if not os.access(path, os.W_OK):
        raise SdpError(f"cannot write into the {what} {path}: permission denied")
    return path


def check_writable(*paths: str | os.PathLike | None) -> None:
    """``SdpError`` unless every output path's folder can be created and written, and the path is free or a
    regular file (before any work: a device, fifo, socket or folder there is refused)."""
    for p in paths:
        if p is None:
            continue
        check_regular(p)
        parent = Path(p).parent
        if not parent.is_dir():   # created with the first write (nothing is left behind by a refused run)
            _check_creatable(p, parent)
            continue
        if not os.access(parent, os.W_OK):
            raise SdpError(f"cannot write {p}: permission denied")


def check_folder(path: str | os.PathLike | None, what: str) -> None:
    """``SdpError`` unless the output folder ``path`` (``what``: e.g. "report folder") exists as a folder or
    can be created (before any work; nothing is created)."""
    if path is None:
        return
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SdpError(f"cannot write the {what} {path}: it exists and is not a folder")
    if not path.exists():
        try:
            _check_creatable(path / "_", path)
        except SdpError as e:
            raise SdpError(f"cannot create the {what} {path}: " + str(e).split(": ", 1)[1]) from None


def _check_creatable(p, parent: Path) -> None:
    """The nearest existing ancestor of ``parent`` is a writable folder (a file there: refused)."""
    anc = parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise SdpError(f"cannot write {p}: {anc} is not a folder")
    if not os.access(anc, os.W_OK):
        raise SdpError(f"cannot write {p}: permission denied")
    made = _missing_parents(parent)   # try: create the folders (as the first write will), then remove them
    try:
        for d in made:
            d.mkdir()
    except OSError as e:
        raise SdpError(f"cannot write {p}: {e.strerror or e}") from None
    finally:
        for d in reversed(made):
            try:
                d.rmdir()
            except OSError:
                pass


def check_regular(path: str | os.PathLike) -> None:
    """``SdpError`` if ``path`` exists and is not a regular file (a folder, device, fifo or socket): outputs
    replace only regular files."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as e:   # a path under a file (ENOTDIR), too long, ...
        raise SdpError(f"cannot write {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(mode):
        raise SdpError(f"cannot write {path}: it is a folder")
    if not stat.S_ISREG(mode):
        raise SdpError(f"cannot write {path}: it exists and is not a regular file (a device, fifo or socket); "
                       "sdp writes only regular files")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: the writes of the artifact being written (:func:`artifact_writes`), or None outside one
_WRITES: contextvars.ContextVar[list | None] = contextvars.ContextVar("sdp_artifact_writes", default=None)


@contextlib.contextmanager
def artifact_writes():
    """The files written inside form one artifact: if the block raises (an OS error such as a full disk,
    an ``SdpError``, Ctrl-C), the files :func:`atomic_write_bytes` created in it are removed, those it
    replaced get their earlier bytes back (a hard link kept until the block ends) and the folders it created
    are removed again. Nested blocks belong to the outermost one."""
    if _WRITES.get() is not None:
        yield
        return
    log: list[tuple[str, Path, Path | None]] = []
    token = _WRITES.set(log)
    try:
        yield
    except BaseException:
        _WRITES.reset(token)
        _undo(log)
        raise
    _WRITES.reset(token)
    for kind, _, backup in log:
        if kind == "file" and backup is not None:
            backup.unlink(missing_ok=True)


def _undo(log: list) -> None:
    for kind, path, backup in reversed(log):
        try:
            if kind == "dir":
                path.rmdir()          # only if empty: never what another process put there
            elif backup is not None:
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        except OSError:
            pass


def _record(kind: str, path: Path, backup: Path | None = None) -> None:
    log = _WRITES.get()
    if log is not None and not any(k == kind and p == path for k, p, _ in log):
        log.append((kind, path, backup))


def _missing_parents(folder: Path) -> list[Path]:
    """The folders ``folder.mkdir(parents=True)`` would create, outermost first."""
    out = []
    while not folder.exists() and folder != folder.parent:
        out.append(folder)
        folder = folder.parent
    return out[::-1]


def _backup(path: Path) -> Path | None:
    """A hard link to the file ``path`` replaces (inside :func:`artifact_writes`, the first time), else None."""
    log = _WRITES.get()
    if log is None or not path.is_file() or any(k == "file" and p == path for k, p, _ in log):
        return None
    backup = path.with_name(f".{path.name}.{os.getpid()}.bak")
    backup.unlink(missing_ok=True)
    try:
        os.link(path, backup)
    except OSError:        # no hard links here: a copy

        shutil.copy2(path, backup)
    return backup


def atomic_write_bytes(path: str | os.PathLike, writer) -> Path:
    """Call ``writer(fileobj)`` on a temp file next to ``path``, then rename it into place. Refuses a path that
    is not a regular file (:func:`check_regular`); an OS error (full disk, read-only file system, permission)
    is one ``SdpError`` naming ``path``, with the temp file removed."""
    path = Path(path)
    check_regular(path)
    try:
        for d in _missing_parents(path.parent):
            d.mkdir()
            _record("dir", d)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise SdpError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())   # mkstemp makes 0600; artifacts get the usual permissions
        backup = _backup(path)
        try:
            os.replace(tmp, path)
        except BaseException:
            if backup is not None:
                backup.unlink(missing_ok=True)
            raise
        _record("file", path, backup)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise SdpError(f"cannot write {path}: {e.strerror or e}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
