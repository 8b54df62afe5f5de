"""Output folders: made with one-line refusals, and held by one writer at a time.

:func:`make_output_folder` refuses a path that exists and is not a folder (``--out`` naming a file) in one line,
instead of a ``FileExistsError`` traceback. :func:`folder_lock` is the one lock of a folder a command writes (a
training run, a study's ``--out``): an advisory ``flock`` on ``<folder>/.lock``, held for the whole command, so that
a second process writing the same folder is refused in one line naming the holder's pid. The kernel releases the
lock when its holder exits or is killed (``kill -9`` too), so a stale lock never blocks a rerun.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path

from seqtrojan.errors import ConfigError, SeqTrojanError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_FILE", "FolderInUse", "folder_lock", "make_output_folder"]

LOCK_FILE = ".lock"
"""the lock file inside a locked folder (left in place: removing it would race with the next holder)"""


class FolderInUse(SeqTrojanError):
    """Another process holds the folder's lock."""


def make_output_folder(path: Path, what: str) -> Path:
    """Create the folder ``path`` (and its parents) if needed; a path that exists as a file, or that cannot be
    created, is refused in one :class:`ConfigError` line naming ``what`` (e.g. ``--out``)."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what} {str(path)!r} exists and is not a folder: choose another path")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{what} {str(path)!r} cannot be created: {err.strerror or err}") from None
    return path


@contextlib.contextmanager
def folder_lock(folder: Path, what: str = "run folder") -> Iterator[None]:
    """Hold ``folder``'s lock (``<folder>/.lock``, exclusive, not waiting) for the block; the folder must exist.
    Raises :class:`FolderInUse` in one line when another process holds it."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno not in (errno.EAGAIN, errno.EACCES):
                raise ConfigError(f"cannot lock {what} {str(folder)!r}: {err.strerror or err}") from None
            raise FolderInUse(
                f"{what} {str(folder)!r} is in use by another seqtrojan process (pid {_holder(fd)}); wait for it "
                "or stop it"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _holder(fd: int) -> str:
    """The pid the holder wrote into the lock file ('unknown' while it has not yet)."""
    text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    return text if text.isdigit() else "unknown"
