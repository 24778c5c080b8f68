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

Processes that need the same library at once (``magrun run --jobs 2``) take a file lock, so
one compiles and the others wait and load it. Without a C compiler, or with
``MAGRUN_COMPILE=0``, the functions run uncompiled in CasADi's virtual machine (same results,
slower) after one warning.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import casadi as ca

CC = os.environ.get("CC", "cc")
CFLAGS = ("-fPIC", "-shared", "-fno-math-errno")


class CompileWarning(UserWarning):
    """Compilation was unavailable or failed; the uncompiled function is used."""


def cache_dir() -> Path:
    """Where compiled libraries live (see the module doc)."""
    if env := os.environ.get("MAGRUN_CACHE_DIR"):
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "magrun"


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
) -> Path | None:
    """Compile the C file that ``write_source(folder)`` writes; the cached ``.so`` or None.

    ``write_source`` generates the code into a scratch folder and returns the file's path; the
    library is keyed on that file's content (see the module doc). ``optimisation`` is the
    compiler's -O flag: -O1 compiles large generated files (an NLP's Hessian) several times
    faster than -O2. ``link``: further compiler arguments after the source (include folders,
    libraries), part of the key. ``without``: what happens instead, for the warning.
    """
    if not compilation_enabled():
        _warn_once(f"no C compiler ({CC}) or MAGRUN_COMPILE=0: CasADi functions run uncompiled")
        return None
    with tempfile.TemporaryDirectory(prefix="magrun-cg-") as tmp:
        source = write_source(Path(tmp))
        code = source.read_bytes()
        command = [CC, optimisation, *CFLAGS]
        key = hashlib.sha256(
            code + " ".join([*command, *link]).encode() + ca.CasadiMeta.version().encode()
        ).hexdigest()[:20]
        folder = cache_dir() / "casadi"
        target = folder / f"{name}-{key}.so"
        if target.exists():
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
    return target


def compiled(function: ca.Function) -> ca.Function:
    """``function`` compiled to C (cached), or itself when compilation is unavailable."""
    name = function.name()

    def write(folder: Path) -> Path:
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        cg.add(function)
        return Path(cg.generate(str(folder) + os.sep))

    path = shared_library(name, write)
    return function if path is None else ca.external(name, str(path))
