"""Answers that take seconds to compute, kept in the machine's cache between processes.

Before its first trial a process tunes the baselines to the coils (their typical wrench over
the workspace), plans the headings the coils can hold along the reference and checks that
they can move the robot along it: each about a thousand small linear programs, most of a
second. Every ``magrun run``, every campaign worker and every test process asks them again
for the same system, robot and reference, so the answers are kept on disk beside the
compiled code (:mod:`magrun.trial` says what each keeps)::

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

import hashlib
import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path

from magrun.compiled import PACKAGE, cache_dir, package_digest, tree_digest, write_cache_file


def files_digest(path: str | Path | None) -> str:
    """SHA-256 of the files under folder ``path``, or of file ``path`` (a coil system's YAML
    of the paper's kind); of nothing for None (the paper's rig: the package's own data)."""
    if path is None:
        return tree_digest(PACKAGE, [])
    p = Path(path)
    if p.is_dir():
        return tree_digest(p, sorted(f for f in p.rglob("*") if f.is_file()))
    return tree_digest(p.parent, [p])


def remembered(
    kind: str, inputs: Iterable[bytes], compute: Callable[[], tuple[float, ...]], length: int
) -> tuple[float, ...]:
    """``compute()``'s ``length`` numbers for ``inputs``, from the cache where it holds them,
    else computed and kept there (module doc). ``kind`` names the answer (a file name's
    start); a file that is not a list of ``length`` finite numbers is computed again."""
    h = hashlib.sha256(package_digest().encode())
    for part in inputs:
        h.update(hashlib.sha256(part).digest())
    path = cache_dir() / "answers" / f"{kind}-{h.hexdigest()[:24]}.json"
    try:
        numbers = json.loads(path.read_text())
        if (
            isinstance(numbers, list)
            and len(numbers) == length
            and all(isinstance(x, float) and math.isfinite(x) for x in numbers)
        ):
            return tuple(numbers)
    except (OSError, ValueError, RecursionError):  # none kept, or not one of these files
        pass
    answer = tuple(float(x) for x in compute())
    if len(answer) != length:
        raise ValueError(f"{kind}: {len(answer)} numbers computed where {length} are kept")
    if all(math.isfinite(x) for x in answer):
        _write(path, answer)
    return answer


def _write(path: Path, answer: tuple[float, ...]) -> None:
    write_cache_file(path, json.dumps(list(answer)))  # each float's repr: read back exactly
