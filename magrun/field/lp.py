"""Small dense linear programs through the HiGHS that scipy ships, without scipy's per-call
wrapper.

:func:`solve_lp` solves::

    min cᵀx   s.t.  lower ≤ A x ≤ upper,   lb ≤ x ≤ ub

as :func:`scipy.optimize.milp` does with every variable continuous, and returns the same
``x``, bit for bit (``tests/test_lp.py`` checks this on random LPs and on the
capability's own). The capability's LPs have four rows and a handful of columns; on those,
milp's input checks, its sparse conversion and its option parsing are about two thirds of a
call. Here the LP goes straight to the HiGHS solver object scipy builds on
(``scipy.optimize._highspy._core``), one per thread, reused from call to call, with the
options milp gives it (no log on the console).

That module is private to scipy: where it is missing or has another shape (another scipy
than the ones tested), :func:`solve_lp` falls back to milp itself, with the same answers,
about three times slower.
"""

from __future__ import annotations

import functools
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_local = threading.local()


@functools.cache
def _highs() -> Any:
    """scipy's HiGHS bindings, where they are where this module expects them and solve a
    probe LP as milp does; else None (milp then solves every LP). Loaded on the first LP:
    scipy.optimize is a large part of a fresh process's start-up, and a process whose
    answers are in the machine's cache (:mod:`magrun.answers`) solves none."""
    try:  # scipy >= 1.15 builds its HiGHS bindings here
        import scipy.optimize._highspy._core as core

        cost, a, lower, upper, lb, ub = _PROBE
        probe = _solve_direct(core, cost, a, lower, upper, lb, ub)
    except (ImportError, AttributeError, TypeError):  # pragma: no cover - another scipy
        return None
    reference = solve_lp(cost, a, lower, upper, lb, ub, through_milp=True)
    if probe is None or reference is None or not np.array_equal(probe, reference):
        return None  # pragma: no cover - another scipy
    return core


#: a small LP with zeros in its matrix, an inequality, equalities and both kinds of bounds
_PROBE = (
    np.array([0.0, 0.0, -1.0]),
    np.array([[-1.0, 0.5, 0.0], [1.0, 2.0, -1.0], [0.0, 1.0, 0.25]]),
    np.array([-np.inf, 0.5, 0.25]),
    np.array([0.3, 0.5, 0.25]),
    np.array([-1.0, -1.0, 0.0]),
    np.array([1.0, 1.0, 1e6]),
)


def direct() -> bool:
    """Whether :func:`solve_lp` talks to HiGHS directly (else through milp)."""
    return _highs() is not None


def _solver(core: Any) -> Any:
    """This thread's HiGHS object, its log off the console (milp's options)."""
    solver = getattr(_local, "solver", None)
    if solver is None:
        solver = core._Highs()
        options = core.HighsOptions()
        options.log_to_console = False
        solver.passOptions(options)
        _local.solver = solver
    return solver


def _columns(a: FloatArray) -> tuple[NDArray[np.int32], NDArray[np.int32], FloatArray]:
    """``a`` in compressed sparse columns, its zeros dropped (as scipy's csc_array has it):
    the columns' starts, the entries' rows and their values."""
    cols, rows = np.nonzero(a.T)  # column by column, rows ascending within each
    starts = np.zeros(a.shape[1] + 1, dtype=np.int32)
    np.cumsum(np.bincount(cols, minlength=a.shape[1]), out=starts[1:])
    return starts, rows.astype(np.int32), a[rows, cols]


def solve_lp(
    cost: FloatArray,
    a: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    lb: FloatArray,
    ub: FloatArray,
    *,
    through_milp: bool = False,
) -> FloatArray | None:
    """The module doc's LP: its optimal ``x``, or None where it has none (infeasible,
    unbounded or not solved). Every array float64; ``a`` dense, (rows, columns);
    ``through_milp`` solves it with :func:`scipy.optimize.milp` instead."""
    core = None if through_milp else _highs()
    if core is None:
        from scipy.optimize import Bounds, LinearConstraint, milp

        result = milp(cost, constraints=LinearConstraint(a, lower, upper), bounds=Bounds(lb, ub))
        return None if result.status != 0 else np.asarray(result.x, dtype=np.float64)
    return _solve_direct(core, cost, a, lower, upper, lb, ub)


def _solve_direct(
    core: Any,
    cost: FloatArray,
    a: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    lb: FloatArray,
    ub: FloatArray,
) -> FloatArray | None:
    """:func:`solve_lp` through ``core``'s HiGHS object for this thread."""
    lp = core.HighsLp()
    n_rows, n_cols = a.shape
    lp.num_col_, lp.num_row_ = n_cols, n_rows
    matrix = lp.a_matrix_
    matrix.num_col_, matrix.num_row_ = n_cols, n_rows
    matrix.format_ = core.MatrixFormat.kColwise
    matrix.start_, matrix.index_, matrix.value_ = _columns(a)
    lp.col_cost_, lp.col_lower_, lp.col_upper_ = cost, lb, ub
    lp.row_lower_, lp.row_upper_ = lower, upper
    solver = _solver(core)
    # a model HiGHS refuses (a NaN bound, say) must not leave the previous one to be solved
    error = core.HighsStatus.kError
    if solver.passModel(lp) == error or solver.run() == error:
        solver.clearModel()
        return None
    if solver.getModelStatus() != core.HighsModelStatus.kOptimal:
        return None
    return np.array(solver.getSolution().col_value, dtype=np.float64)
