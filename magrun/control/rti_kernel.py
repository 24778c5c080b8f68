"""The RTI's per-tick work compiled to C around HPIPM (``rti_hpipm.c``).

One shared library holds the CasADi-generated stage functions and a small C driver that
linearises every stage, fills HPIPM's stage-wise QP directly (no global sparse matrix) and
solves it, with HPIPM's structures allocated once. Python calls it twice a tick through
ctypes: :meth:`RTIKernel.prepare` (linearise around the shifted plan) and
:meth:`RTIKernel.feedback` (embed the measured start, solve, step). HPIPM and BLASFEO are the
builds that ship inside the CasADi wheel (its ``include`` folder and shared libraries).

:func:`build_kernel` returns None where that cannot be built (no compiler, headers or
libraries missing, ``MAGRUN_COMPILE=0``); the NMPC then uses CasADi's HPIPM interface on the
same QP (:class:`magrun.control.nmpc.RTISolver`), slower and the same to the solver's
tolerance.

The wheel's BLASFEO is its generic (portable C) build. ``MAGRUN_HPIPM_DIR`` names another
HPIPM / BLASFEO build instead, e.g. an acados install whose BLASFEO was built for the CPU
(``X64_INTEL_HASWELL`` and the like): the same QPs, solved about twice as fast
(docs/benchmarks.md). The kernel is linked with an RPATH to that build (not a RUNPATH), so
``LD_LIBRARY_PATH`` cannot swap in libraries the headers do not describe. HPIPM and BLASFEO
are loaded once per process by their names: use one build per process.
"""

from __future__ import annotations

import ctypes
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.compiled import CompileWarning, fingerprint, shared_library

FloatArray = NDArray[np.float64]

_DRIVER = Path(__file__).with_name("rti_hpipm.c")
_double_p = ctypes.POINTER(ctypes.c_double)
_int_p = ctypes.POINTER(ctypes.c_int)


#: an HPIPM / BLASFEO build to link the kernel against instead of the CasADi wheel's
HPIPM_DIR_VARIABLE = "MAGRUN_HPIPM_DIR"
FALLBACK = "the NMPC's QPs go through CasADi's HPIPM interface (the same optimum, slower)"


def casadi_folder() -> Path:
    """Where the CasADi wheel keeps its headers and HPIPM / BLASFEO libraries."""
    return Path(ca.__file__).parent


def hpipm_build() -> tuple[list[Path], Path] | None:
    """(header folders, library folder) of the HPIPM and BLASFEO the kernel links: those of
    ``$MAGRUN_HPIPM_DIR`` where set (a prefix with ``lib/`` and the headers under
    ``include/``, ``include/hpipm/include`` or ``include/blasfeo/include``, as an acados
    install lays them out), else the CasADi wheel's; None where headers or libraries are
    missing."""
    prefix = os.environ.get(HPIPM_DIR_VARIABLE)
    if prefix:
        root = Path(prefix)
        candidates = [root / "include", root / "include" / "hpipm" / "include",
                      root / "include" / "blasfeo" / "include"]  # fmt: skip
        lib = root / "lib"
    else:
        candidates, lib = [casadi_folder() / "include"], casadi_folder()
    includes = [c for c in candidates if c.is_dir()]
    needed = ("hpipm_d_ocp_qp_ipm.h", "blasfeo_target.h")
    if not all(any((c / h).exists() for c in includes) for h in needed):
        return None
    if not (lib / "libhpipm.so").exists() or not (lib / "libblasfeo.so").exists():
        return None
    return includes, lib


def _link_args() -> tuple[str, ...] | None:
    build = hpipm_build()
    if build is None:
        return None
    includes, lib = build
    # RPATH, not RUNPATH: the libraries the headers belong to, whatever LD_LIBRARY_PATH says
    return (*(f"-I{c}" for c in includes), f"-L{lib}", f"-Wl,-rpath,{lib}",
            "-Wl,--disable-new-dtags", "-Wl,-Bsymbolic", "-lhpipm", "-lblasfeo")  # fmt: skip


def build_kernel(
    stage_functions: Callable[[], tuple[ca.Function, ca.Function]],
    problem: ca.Function,
    heading: ca.Function | None,
    step: ca.Function,
    dims: dict[str, int],
    name: str = "nmpc_rti",
) -> Path | None:
    """Generate and compile the kernel; the library's path, or None (module doc).

    ``stage_functions()`` → (stage, terminal): ``stage(s, v, par)`` → (s_next, A, B, r, Js,
    Jv, g, Gs, Gv), ``terminal(s, par)`` → (rN, JN, gN, GN), with g the soft constraints'
    weighted gaps (≥ 0 where kept; the heading's row first), all outputs dense; called only
    where the cache does not know the library already. ``problem``: what they differentiate,
    ``(s, v, par)`` → (s_next, r, g, rN, gN), the cache's fingerprint of them
    (:mod:`magrun.compiled`). ``heading(X, u)`` → the heading residual (one row); ``step(X,
    u)`` → the next state (the planner's prediction); ``dims``: N, NS, NU, NR, NRT, NG, NGT,
    NGH (stage 0's soft rows: the heading's), NP, NB.
    """
    link = _link_args()
    if link is None:
        if os.environ.get(HPIPM_DIR_VARIABLE):
            warnings.warn(
                f"{HPIPM_DIR_VARIABLE}={os.environ[HPIPM_DIR_VARIABLE]} holds no HPIPM and"
                " BLASFEO build (lib/libhpipm.so, lib/libblasfeo.so and their headers under"
                f" include/): {FALLBACK}",
                CompileWarning,
                stacklevel=2,
            )
        return None
    X = ca.SX.sym("X", dims["NS"] - dims["NU"])
    u = ca.SX.sym("u", dims["NU"])
    if heading is None:
        heading_fn = ca.Function("rti_heading", [X, u], [ca.SX.zeros(1)])
    else:
        heading_fn = ca.Function("rti_heading", [X, u], [heading(X, u)])
    layout = repr(sorted(dims.items())).encode()
    graphs = fingerprint(problem, heading_fn, step)

    def write(folder: Path) -> Path:
        stage, terminal = stage_functions()
        cg = ca.CodeGenerator("rti_generated.c", {"with_header": False})
        for f in (_dense("rti_stage", stage), _dense("rti_terminal", terminal), heading_fn,
                  _dense("rti_step", step)):  # fmt: skip
            cg.add(f)
        generated = Path(cg.generate(str(folder) + os.sep)).read_text()
        defines = "".join(f"#define RTI_{k} {v}\n" for k, v in sorted(dims.items()))
        defines += f"#define RTI_HEADING {int(heading is not None)}\n"
        target = folder / f"{name}.c"
        target.write_text(generated + "\n" + defines + _DRIVER.read_text())
        return target

    # -O1: gcc spends 2.1 s on the spine's kernel where -O2 spends 3.4 s; the feedback phase
    # runs as fast (HPIPM and BLASFEO, where it goes, are compiled on their own), the
    # preparation 1-1.5 % slower, and the recordings are the same bit for bit
    # (docs/benchmarks.md, "Compiling the kernel")
    return shared_library(
        name, write, optimisation="-O1", link=link, without=FALLBACK,
        fingerprint=None if graphs is None else layout + b"\0" + graphs,
    )  # fmt: skip


class Feedback(NamedTuple):
    """What one :meth:`RTIKernel.feedback` did: the C driver's status and its ``info``
    array (``rti_feedback`` in ``rti_hpipm.c``) by name."""

    status: int  # 0: solved, the iterate moved; -2: the defect exceeded max_defect; else HPIPM's
    step: float  # max |step| over the plan, scaled units (0 where nothing was solved)
    qp_iterations: int  # HPIPM's iterations, the robust retry's included
    robust: bool  # whether the fast mode failed and the robust mode solved again
    heading_residual: float  # the heading term's residual at stage 0 after the step
    defect: float  # stage 0 linearised at the prepared point against the stage at s0, ∞-norm

    @classmethod
    def read(cls, status: int, info: FloatArray) -> Feedback:
        return cls(
            status=int(status), step=float(info[0]), qp_iterations=int(info[1]),
            robust=bool(info[4]), heading_residual=float(info[3]), defect=float(info[5]),
        )  # fmt: skip


class RTIKernel:
    """The compiled kernel's state for one controller: HPIPM's structures and the iterate."""

    def __init__(
        self,
        library: Path,
        dims: dict[str, int],
        du_max: FloatArray,
        bounded: FloatArray,
        lower: FloatArray,
        upper: FloatArray,
        tolerances: tuple[float, ...],
        iter_max: int,
    ) -> None:
        """``tolerances``: HPIPM's stationarity, equality, inequality and complementarity
        tolerances and the fast mode's initial barrier parameter mu0."""
        if len(tolerances) != 5:
            raise ValueError("tolerances: four residual tolerances and mu0")
        self.N, self.ns, self.nu = dims["N"], dims["NS"], dims["NU"]
        lib = ctypes.CDLL(str(library))
        lib.rti_create.restype = ctypes.c_void_p
        lib.rti_create.argtypes = [_double_p, _int_p, _double_p, _double_p, _double_p,
                                   ctypes.c_int]  # fmt: skip
        lib.rti_free.argtypes = [ctypes.c_void_p]
        for f in ("rti_set_iterate", "rti_get_iterate"):
            getattr(lib, f).argtypes = [ctypes.c_void_p, _double_p, _double_p]
        lib.rti_shift.argtypes = [ctypes.c_void_p]
        lib.rti_prepare.argtypes = [ctypes.c_void_p, _double_p, _double_p]
        lib.rti_feedback.argtypes = [ctypes.c_void_p, _double_p, _double_p, ctypes.c_double]
        lib.rti_retries.argtypes = [ctypes.c_void_p]
        lib.rti_set_fast_iter_max.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.rti_predict.argtypes = [ctypes.c_void_p, _double_p, _double_p, _double_p]
        lib.rti_set_damping.argtypes = [ctypes.c_void_p, ctypes.c_double]
        self._lib = lib
        arrays: list[np.ndarray] = [
            np.ascontiguousarray(np.broadcast_to(du_max, (self.nu,)), dtype=np.float64),
            np.ascontiguousarray(bounded, dtype=np.intc),
            np.ascontiguousarray(lower, dtype=np.float64),
            np.ascontiguousarray(upper, dtype=np.float64),
            np.ascontiguousarray(tolerances, dtype=np.float64),
        ]
        handle = lib.rti_create(*(_ptr(a) for a in arrays), int(iter_max))
        if not handle:
            raise MemoryError("the NMPC's QP kernel could not allocate its memory")
        self._handle: ctypes.c_void_p | None = ctypes.c_void_p(handle)
        self._info = np.zeros(6)
        self._info_p = _ptr(self._info)

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None:
            self._lib.rti_free(handle)
            self._handle = None

    def set_iterate(self, S: FloatArray, V: FloatArray) -> None:
        S = np.ascontiguousarray(S, dtype=np.float64)
        V = np.ascontiguousarray(V, dtype=np.float64)
        assert S.shape == (self.N, self.ns)
        assert V.shape == (self.N, self.nu)
        self._lib.rti_set_iterate(self._handle, _ptr(S), _ptr(V))

    def iterate(self) -> tuple[FloatArray, FloatArray]:
        """The plan: states s₁ … s_N (N, ns) and steps v₀ … v_{N−1} (N, nu)."""
        S, V = np.empty((self.N, self.ns)), np.empty((self.N, self.nu))
        self._lib.rti_get_iterate(self._handle, _ptr(S), _ptr(V))
        return S, V

    def shift(self) -> None:
        self._lib.rti_shift(self._handle)

    def prepare(self, par: FloatArray, s_lin: FloatArray) -> bool:
        """Linearise around the iterate, stage 0 at ``s_lin``; False where not finite.
        ``par``: the (NP, N+1) stage parameters."""
        p = np.asfortranarray(par, dtype=np.float64)
        s = np.ascontiguousarray(s_lin, dtype=np.float64)
        return self._lib.rti_prepare(self._handle, _ptr(p), _ptr(s)) == 0

    def feedback(self, s0: FloatArray, max_defect: float = np.inf) -> Feedback:
        """Embed the start ``s0``, solve, step (:class:`Feedback`): status 0 where solved
        and the iterate moved, -2 where the embedding's defect (how far stage 0 linearised
        at the prepared point is from the stage at ``s0``) exceeded ``max_defect`` and
        nothing was solved, else HPIPM's."""
        s = np.ascontiguousarray(s0, dtype=np.float64)
        self._info[:] = 0.0
        status = self._lib.rti_feedback(self._handle, _ptr(s), self._info_p, float(max_defect))
        return Feedback.read(status, self._info)

    def predict(self, X: FloatArray, u: FloatArray) -> FloatArray:
        """One step of the model from the scaled state ``X`` under currents ``u`` (scaled)."""
        X = np.ascontiguousarray(X, dtype=np.float64)
        u = np.ascontiguousarray(u, dtype=np.float64)
        out = np.empty(X.size)
        self._lib.rti_predict(self._handle, _ptr(X), _ptr(u), _ptr(out))
        return out

    def set_damping(self, mu: float) -> None:
        """The step damping μ ≥ 0: μ/2 |step|² in every QP from the next preparation on
        (:class:`magrun.control.nmpc.NMPCConfig` ``step_damping``)."""
        self._lib.rti_set_damping(self._handle, float(mu))

    def limit_fast_iterations(self, iter_max: int) -> None:
        """HPIPM's fast mode stops after ``iter_max`` iterations (tests of the robust retry)."""
        self._lib.rti_set_fast_iter_max(self._handle, int(iter_max))

    @property
    def retries(self) -> int:
        return int(self._lib.rti_retries(self._handle))


def _dense(name: str, f: ca.Function) -> ca.Function:
    """``f`` renamed, with dense outputs (the C driver reads them column-major)."""
    args = f.sx_in()
    return ca.Function(name, args, [ca.densify(o) for o in f.call(args)], {"cse": True})


def _ptr(a: np.ndarray) -> Any:
    return a.ctypes.data_as(_int_p if a.dtype == np.intc else _double_p)
