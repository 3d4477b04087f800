"""Reading and writing the files the user names: regular files only, sizes
bounded before reading, results written then renamed, every error one line
naming its path.

Reading refuses FIFOs, devices and directories before opening them (a FIFO
would block, ``/dev/zero`` would never end) and a file larger than the
caller's limit before reading it. Writing goes to a temporary file beside the
target, flushed to disk, then renamed over it: a kill or a full disk leaves
either the old file or the new one, never half of one.
"""
from __future__ import annotations

import fcntl
import os
import stat
from pathlib import Path
from typing import Callable

from has_control.common.errors import HasControlError

MiB = 1 << 20


def io_error(path: str | Path, exc: OSError, doing: str,
             error: type[HasControlError] = HasControlError) -> HasControlError:
    """One line naming ``path``: ``PATH: cannot write: No space left on device``."""
    return error(f"{path}: cannot {doing}: {exc.strerror or exc}")


def regular_file(path: str | Path, limit: int | None = None,
                 error: type[HasControlError] = HasControlError) -> Path:
    """``path`` if it is a regular file of at most ``limit`` bytes, else ``error``."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError as exc:
        raise io_error(path, exc, "read", error) from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a directory" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO or device?)"
        raise error(f"{path}: {kind}: expected a regular file")
    if limit is not None and st.st_size > limit:
        raise error(f"{path}: {st.st_size} bytes: larger than the limit of {limit} bytes")
    return path


def read_bytes(path: str | Path, limit: int | None = None,
               error: type[HasControlError] = HasControlError) -> bytes:
    """The bytes of a regular file (see :func:`regular_file`); never more than ``limit``."""
    path = regular_file(path, limit, error)
    try:
        with open(path, "rb") as f:
            data = f.read() if limit is None else f.read(limit + 1)
    except OSError as exc:
        raise io_error(path, exc, "read", error) from None
    if limit is not None and len(data) > limit:
        raise error(f"{path}: larger than the limit of {limit} bytes")
    return data


def read_text(path: str | Path, limit: int, error: type[HasControlError] = HasControlError) -> str:
    """The UTF-8 text of a regular file of at most ``limit`` bytes."""
    data = read_bytes(path, limit, error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.start})") from None


def _kind(mode: int) -> str:
    return ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")


def output_target(path: str | Path) -> Path:
    """The file a write to ``path`` replaces: ``path``, or for a symlink the
    file it points to (written through, the link kept). An existing target
    that is not a regular file (a device, FIFO, directory, socket) is refused
    in one line naming ``path``: a rename over it would replace it."""
    p = Path(path)
    target = Path(os.path.realpath(p)) if p.is_symlink() else p
    try:
        st = os.stat(target)
    except FileNotFoundError:
        return target
    except OSError as exc:
        raise io_error(path, exc, "write") from None
    if not stat.S_ISREG(st.st_mode):
        via = f" (a link to {target})" if target != p else ""
        raise HasControlError(f"{path}{via}: {_kind(st.st_mode)}: expected a regular file or a new path; not replaced")
    return target


def check_output(path: str | Path, what: str = "file") -> Path:
    """Before any work: ``path`` can be written as a ``what`` ("file" or
    "directory"): a new path, an existing regular file (or a link to one) or
    directory, whose nearest existing folder is a writable directory. The
    target (:func:`output_target`) for a file; one line naming ``path`` if not."""
    p = Path(path)
    if str(path) == "":
        raise HasControlError("'': an empty path")
    if what == "directory":
        if p.exists() and not p.is_dir():
            raise HasControlError(f"{path}: exists and is not a directory")
        target = p
    else:
        target = output_target(p)
    folder = target if what == "directory" and target.exists() else target.parent
    while not folder.exists() and folder != folder.parent:
        if folder.is_symlink():
            raise HasControlError(f"{path}: {folder} is a dangling link")
        folder = folder.parent
    if not folder.is_dir():
        raise HasControlError(f"{path}: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        reason = "read-only file system" if _read_only_fs(folder) else "permission denied"
        raise HasControlError(f"{path}: cannot write: {folder} is not writable ({reason})")
    return target


def _read_only_fs(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def write_atomic(path: str | Path, data: bytes | str | Callable[[Path], object]) -> Path:
    """Write ``data`` (bytes, text, or a function that writes the file it is
    given) to a temporary file beside the target, flush it to disk and rename
    it over the target. The target is ``path``, or the file a symlink
    ``path`` points to; anything but a regular file or a new path is refused
    (:func:`output_target`). On failure the temporary file is removed and
    the error names ``path``, never the temporary file."""
    target = output_target(path)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        if callable(data):
            data(tmp)
        else:
            tmp.write_bytes(data.encode() if isinstance(data, str) else data)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError as exc:
        _unlink_quietly(tmp)
        raise io_error(path, exc, "write") from None
    except BaseException:
        _unlink_quietly(tmp)
        raise
    return Path(path)


def _unlink_quietly(tmp: Path) -> None:
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass


def check_new_output(path: str | Path, force: bool, what: str) -> None:
    """Refuse, before any work, to replace ``path`` (a file, or a non-empty
    directory) unless ``force``; and a directory where a file is wanted or the
    other way round (``what``: "file" or "directory")."""
    p = Path(path)
    if not p.exists() and not p.is_symlink():
        return
    if what == "directory" and not p.is_dir():
        raise HasControlError(f"{p}: exists and is not a directory")
    if what == "file" and p.is_dir():
        raise HasControlError(f"{p}: is a directory")
    if what == "directory" and not any(p.iterdir()):
        return
    if not force:
        raise HasControlError(f"{p}: exists already and is not empty; --force to overwrite"
                              if what == "directory" else f"{p}: exists already; --force to overwrite")


class DirectoryLock:
    """An advisory lock (``fcntl.flock``) on ``DIR/name``, held until
    :meth:`release` or the process ends; a second holder is refused at once."""

    def __init__(self, directory: str | Path, name: str, what: str):
        self.path = Path(directory) / name
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise io_error(self.path, exc, "lock") from None
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise HasControlError(f"{directory}: {what} is in use by another process "
                                  f"(lock {self.path} held)") from None

    def release(self) -> None:
        if getattr(self, "_fd", None) is not None:
            os.close(self._fd)
            self._fd = None

    __del__ = release
