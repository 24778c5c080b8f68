"""Answers that take seconds to compute, kept in the machine's cache between processes.

Before its first trial a process tunes the baselines to the coils: their typical wrench over
the workspace takes about a thousand small linear programs, most of a second. Every
``magrun run``, every campaign worker and every test process asks it again for the same
system and robot, so the answer is kept on disk beside the compiled code::

    <cache>/answers/<kind>-<key>.json     key: SHA-256 of what the answer is computed from
                                          and of magrun's own source

``<cache>`` is :func:`magrun.compiled.cache_dir`. The key covers the inputs as the caller
names them (the system folder's files, by content, the limits, the robot) and every file of
the installed magrun package (its code and its shipped data), so a changed system file or a
changed line of magrun makes a new answer, never a stale one. An answer is a JSON list of finite
numbers, written to a temporary file and renamed into place (two processes computing it at
once write the same file); a file that is not such a list is computed again and replaced.
Deleting the folder is always safe.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

from magrun.compiled import cache_dir

PACKAGE = Path(__file__).resolve().parent


def _digest(root: Path, paths: Iterable[Path]) -> str:
    h = hashlib.sha256()
    for path in paths:
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def package_digest() -> str:
    """SHA-256 of every file of the installed magrun package (its code and its shipped data:
    the paper rig's maps, the robots; compiled caches left out)."""
    files = (p for p in PACKAGE.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    return _digest(PACKAGE, sorted(files))


def files_digest(path: str | Path | None) -> str:
    """SHA-256 of the files under folder ``path``, or of file ``path`` (a coil system's YAML
    of the paper's kind); of nothing for None (the paper's rig: the package's own data)."""
    if path is None:
        return _digest(PACKAGE, [])
    p = Path(path)
    if p.is_dir():
        return _digest(p, sorted(f for f in p.rglob("*") if f.is_file()))
    return _digest(p.parent, [p])


def remembered(
    kind: str, inputs: Iterable[bytes], compute: Callable[[], tuple[float, ...]]
) -> tuple[float, ...]:
    """``compute()``'s numbers for ``inputs``, from the cache where it holds them, else
    computed and kept there (module doc). ``kind`` names the answer (a file name's start)."""
    h = hashlib.sha256(package_digest().encode())
    for part in inputs:
        h.update(hashlib.sha256(part).digest())
    path = cache_dir() / "answers" / f"{kind}-{h.hexdigest()[:24]}.json"
    try:
        numbers = json.loads(path.read_text())
        if isinstance(numbers, list) and all(
            isinstance(x, float) and math.isfinite(x) for x in numbers
        ):
            return tuple(numbers)
    except (OSError, ValueError, RecursionError):  # none kept, or not one of these files
        pass
    answer = tuple(float(x) for x in compute())
    if all(math.isfinite(x) for x in answer):
        _write(path, answer)
    return answer


def _write(path: Path, answer: tuple[float, ...]) -> None:
    """``answer`` into ``path`` through a temporary file renamed into place; where the cache
    cannot be written the answer is still right, only not kept."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, part = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".part")
    except OSError:
        return
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(list(answer), fh)  # each float's repr: read back to the last bit
        os.replace(part, path)
    except OSError:
        Path(part).unlink(missing_ok=True)
