"""Atomic file writes: a reader (or a crash) never sees a half-written data file.

Each writer writes ``NAME.part`` beside the target and renames it over the target, which is
atomic on POSIX file systems.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


def _part(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(path.name + ".part")


def write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 text to ``path`` atomically."""
    path = Path(path)
    tmp = _part(path)
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    path = Path(path)
    tmp = _part(path)
    tmp.write_bytes(data)
    tmp.replace(path)


def write_npz(path: str | Path, arrays: Mapping[str, NDArray[Any]]) -> None:
    """Write a compressed ``.npz`` of named arrays to ``path`` atomically (no pickles)."""
    path = Path(path)
    tmp = _part(path)
    with tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]  # numpy stubs mistype **kwds
    tmp.replace(path)


def write_figure(figure: Any, path: str | Path) -> None:
    """Save a matplotlib ``figure`` to ``path`` atomically, in the format its suffix names."""
    path = Path(path)
    tmp = _part(path)
    figure.savefig(tmp, format=path.suffix.lstrip(".").lower(), dpi=150)
    tmp.replace(path)


#: the advisory lock file inside a folder a command writes (a run's, a replay's)
LOCK_NAME = ".magrun-lock"


class FolderBusy(RuntimeError):
    """Another process holds the folder's lock: one writer per folder."""


class _ExclusiveLock:
    """An advisory, exclusive ``flock`` on the file ``path``, naming ``what`` it guards.
    Taken at once or not at all: :class:`FolderBusy` names the holder's process id and
    command. The lock file holds them while the lock is held and is removed on
    :meth:`release`; the operating system releases the lock of a process that dies, so a
    crash never leaves anything locked (a later writer takes the file it left)."""

    def __init__(self, path: Path, what: str) -> None:
        import fcntl
        import os
        import sys

        self.path = path
        for _ in range(10):  # a holder that releases between our open and its unlink: again
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.read(fd, 4096).decode("utf-8", "replace").strip() or "unknown"
                os.close(fd)
                raise FolderBusy(
                    f"{what} is being written by another magrun ({holder}); wait for it to "
                    "finish or choose another output"
                ) from None
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)  # the file was released and removed under us: take the new one
        else:
            raise FolderBusy(f"{what}: could not take its lock")
        self._fd: int | None = fd
        os.ftruncate(fd, 0)
        command = " ".join(Path(sys.argv[0]).name if i == 0 else a for i, a in enumerate(sys.argv))
        os.write(fd, f"pid {os.getpid()}: {command[:200]}\n".encode("utf-8", "replace"))

    def release(self) -> None:
        """Remove the lock file and release the lock (idempotent)."""
        import os

        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None

    def __enter__(self) -> _ExclusiveLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class FolderLock(_ExclusiveLock):
    """The lock on ``folder`` (``folder/.magrun-lock``), so that two magrun commands never
    write into one folder at once (two runs, a run and its ``--resume`` or ``--overwrite``)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        super().__init__(self.folder / LOCK_NAME, str(self.folder))


class OutputLock(_ExclusiveLock):
    """The lock on one output file ``path`` (``.NAME.magrun-lock`` beside it), so that two
    commands writing the same file (two ``replay`` or ``recover`` into one output) never
    interleave: the second is refused while the first writes."""

    def __init__(self, path: str | Path) -> None:
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        super().__init__(target.parent / f".{target.name}{LOCK_NAME}", str(target))
