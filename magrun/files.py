"""Opening the files magrun reads: regular files only.

A path given where a file is read may name a folder, a socket, a device or a FIFO (where
reading waits for a writer for ever); every reader of bytes opens through
:func:`open_binary`, which refuses all of those before a byte is read.
"""

from __future__ import annotations

import os
import stat
import typing
from pathlib import Path


class NotRegularFileError(OSError):
    """A path that names a folder, a FIFO, a socket or a device where a file is read."""


def open_binary(path: str | Path) -> typing.BinaryIO:
    """``path`` opened for reading bytes if it is a regular file; otherwise
    :class:`NotRegularFileError` (an ``OSError``, so a reader's "cannot read" handling
    reports it). Opened without blocking and checked on the open descriptor: a FIFO would
    otherwise wait for a writer for ever, and a path swapped after a check is still caught."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NotRegularFileError(f"{path}: not a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
