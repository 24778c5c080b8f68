"""CasADi functions compiled to C once, and kept in an on-disk cache.

The NMPC's stage functions (one step of the dynamics, its Jacobians, the cost residuals) and
the IPOPT reference's NLP callbacks are small SX functions evaluated hundreds of times per
tick; CasADi's virtual machine runs them several times slower than compiled C. Compiling
takes seconds to a minute, so the shared library is cached::

    <cache>/casadi/<name>-<key>.so       key: SHA-256 of the generated C source, the compiler
                                         command and the CasADi version

``<cache>`` is ``$MAGRUN_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/magrun``, else
``~/.cache/magrun``. Keying on the generated source means a changed model, horizon, weight
or option gives new code and a new library, and an unchanged one is never rebuilt: a campaign
or a test session compiles each variant once. Deleting the folder is always safe.

Generating the source to learn its key costs more than loading the library: the RTI's
functions with their Jacobians and common subexpressions take 0.1–1.3 s to build and 0.05–0.25
s to write out, every time a controller is made. So a library is also found by what it is made
from, without generating anything::

    <cache>/casadi/known/<name>-<key>     the library's file name; key: SHA-256 of the
                                          caller's fingerprint, magrun's own source
                                          (:func:`package_digest`), the compiler command
                                          and the CasADi version

The fingerprint is the serialised CasADi graph of what the code is generated from (CasADi's
``Function.serialize``: every operation and every constant to the last bit), so an entry
names the library that graph's code compiled to; what magrun does between the graph and the
code (derivatives, options, the C driver) is magrun's source, in the key too. An entry that
names no library in the folder is ignored and written again after the source is generated.

Processes that need the same library at once (``magrun run --jobs 2``) take a file lock, so
one compiles and the others wait and load it. Without a C compiler, or with
``MAGRUN_COMPILE=0``, the functions run uncompiled in CasADi's virtual machine (same results,
slower) after one warning.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import os
import re
import shlex
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

import casadi as ca

CC = os.environ.get("CC", "cc")
CFLAGS = ("-fPIC", "-shared", "-fno-math-errno")
PACKAGE = Path(__file__).resolve().parent


class CompileWarning(UserWarning):
    """Compilation was unavailable or failed; the uncompiled function is used."""


def cache_dir() -> Path:
    """Where compiled libraries live (see the module doc)."""
    if env := os.environ.get("MAGRUN_CACHE_DIR"):
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "magrun"


def tree_digest(root: Path, paths: Iterable[Path]) -> str:
    """SHA-256 of the files ``paths`` (under ``root``): each one's path relative to ``root``
    and its content."""
    h = hashlib.sha256()
    for path in paths:
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def package_digest() -> str:
    """SHA-256 of every file of the installed magrun package (its code and its shipped data:
    the paper rig's maps, the robots; compiled caches left out)."""
    files = (p for p in PACKAGE.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    return tree_digest(PACKAGE, sorted(files))


def compilation_enabled() -> bool:
    return os.environ.get("MAGRUN_COMPILE", "1") != "0" and shutil.which(CC) is not None


_warned = False


def _warn_once(message: str) -> None:
    global _warned
    if not _warned:
        warnings.warn(message, CompileWarning, stacklevel=3)
        _warned = True


def shared_library(
    name: str,
    write_source: Callable[[Path], Path],
    optimisation: str = "-O2",
    link: tuple[str, ...] = (),
    without: str = "CasADi functions run uncompiled",
    fingerprint: bytes | None = None,
) -> Path | None:
    """Compile the C file that ``write_source(folder)`` writes; the cached ``.so`` or None.

    ``write_source`` generates the code into a scratch folder and returns the file's path; the
    library is keyed on that file's content (see the module doc). ``optimisation`` is the
    compiler's -O flag: -O1 compiles large generated files (an NLP's Hessian) several times
    faster than -O2. ``link``: further compiler arguments after the source (include folders,
    libraries), part of the key. ``without``: what happens instead, for the warning.
    ``fingerprint``: what the source is generated from, everything but magrun's own code
    (module doc); where the cache knows it, its library is returned without calling
    ``write_source``.
    """
    if not compilation_enabled():
        _warn_once(f"no C compiler ({CC}) or MAGRUN_COMPILE=0: CasADi functions run uncompiled")
        return None
    command = [CC, optimisation, *CFLAGS]
    folder = cache_dir() / "casadi"
    known = None
    if fingerprint is not None:
        known = _known_entry(folder, name, fingerprint, [*command, *link])
        if (found := _known_library(folder, name, known)) is not None:
            return found
    with tempfile.TemporaryDirectory(prefix="magrun-cg-") as tmp:
        source = write_source(Path(tmp))
        code = source.read_bytes()
        key = hashlib.sha256(
            code + " ".join([*command, *link]).encode() + ca.CasadiMeta.version().encode()
        ).hexdigest()[:20]
        target = folder / f"{name}-{key}.so"
        if target.exists():
            _remember(known, target)
            return target
        folder.mkdir(parents=True, exist_ok=True)
        with open(folder / f".{name}-{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be compiling it
            if target.exists():
                return target
            partial = folder / f".{name}-{key}.{os.getpid()}.so"
            cmd = [*command, str(source), "-o", str(partial), *link, "-lm"]
            done = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                partial.unlink(missing_ok=True)
                _warn_once(
                    f"compiling {name} failed ({shlex.join(cmd)}): {done.stderr.strip()[:500]};"
                    f" {without}"
                )
                return None
            os.replace(partial, target)
    _remember(known, target)
    return target


def _known_entry(folder: Path, name: str, fingerprint: bytes, command: list[str]) -> Path:
    """Where the cache says which library ``fingerprint`` compiles to (module doc)."""
    h = hashlib.sha256()
    for part in (package_digest().encode(), ca.CasadiMeta.version().encode(),
                 " ".join(command).encode(), name.encode(), fingerprint):  # fmt: skip
        h.update(hashlib.sha256(part).digest())
    return folder / "known" / f"{name}-{h.hexdigest()[:24]}"


def _known_library(folder: Path, name: str, entry: Path) -> Path | None:
    """The library ``entry`` names, where it is one of this folder's libraries of ``name``."""
    try:
        text = entry.read_text(encoding="ascii").strip()
    except (OSError, ValueError):  # none kept, or not one of these entries
        return None
    if re.fullmatch(re.escape(name) + r"-[0-9a-f]{20}\.so", text) is None:
        return None
    library = folder / text
    return library if library.is_file() else None


def _remember(entry: Path | None, library: Path) -> None:
    if entry is not None:
        write_cache_file(entry, library.name + "\n")


def write_cache_file(path: Path, text: str) -> None:
    """``text`` into ``path`` through a temporary file of its own renamed into place (two
    processes writing the same file at once each rename a whole one); where the cache cannot
    be written nothing is kept, and what it would have kept is computed again next time."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, part = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    except OSError:
        return
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(part, path)
    except OSError:
        Path(part).unlink(missing_ok=True)


def compiled(function: ca.Function) -> ca.Function:
    """``function`` compiled to C (cached), or itself when compilation is unavailable."""
    name = function.name()

    def write(folder: Path) -> Path:
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        cg.add(function)
        return Path(cg.generate(str(folder) + os.sep))

    path = shared_library(name, write, fingerprint=fingerprint(function))
    return function if path is None else ca.external(name, str(path))


def fingerprint(*functions: ca.Function) -> bytes | None:
    """The functions' serialised graphs (module doc), or None where one cannot be serialised
    (a callback into Python)."""
    try:
        return b"\0".join(f.serialize().encode() for f in functions)
    except RuntimeError:
        return None
