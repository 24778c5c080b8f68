"""Box-constrained linear least squares, the two-layer baselines' inner problem.

Both the linear MPC (Baselines 3 and 4, 3N = 60 normalised wrenches) and the current
allocation (8 currents) solve::

    min_x ‖M x − r‖²     s.t.  lo ≤ x ≤ hi

:class:`BoxLeastSquares` hands it to DAQP (Arnström et al. 2022, a dual active-set solver for
small dense QPs) as the strictly convex QP ``½ xᵀ(MᵀM)x − (Mᵀr)ᵀx``, through DAQP's own Python
interface (the ``daqp`` package: NumPy arrays in and out). scipy's BVLS
(``lsq_linear(method="bvls")``), which works on ``M`` itself, is the reference and the
fallback when DAQP does not report an optimum. Both give the unique optimum (``M`` has full
column rank in every caller: each has a regularising identity block); DAQP is several times
faster here (BENCHMARKS.md), with solutions equal to BVLS's to ~1e-8 relative (the
allocation's ``MᵀM`` squares a condition number of ~1e4) and objective values to ~1e-8.

The same solver is shipped with CasADi (``casadi.conic(..., "daqp")``), but a call through
CasADi's function interface cost 0.6–0.7 ms more than the solve itself on the linear MPC's
60 variables (BENCHMARKS.md), most of a Baseline 3 tick.

    >>> solve = BoxLeastSquares(8)
    >>> x = solve(M, r, lo, hi)                                            # doctest: +SKIP
"""

from __future__ import annotations

from ctypes import c_int

import daqp
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
#: DAQP's tolerance on the bounds' violation
PRIMAL_TOL = 1e-10
#: DAQP's exit flag for a solution that is optimal
_OPTIMAL = 1


def bvls(M: FloatArray, r: FloatArray, lo: ArrayLike, hi: ArrayLike) -> FloatArray:
    """The reference: scipy's bounded-variable least squares on ``M`` directly."""
    # imported here: scipy.optimize is most of a second of a fresh process's start-up, which
    # a process with no two-layer controller never needs (BoxLeastSquares imports it when
    # built, so that no control tick waits for the import)
    from scipy.optimize import lsq_linear

    return np.asarray(lsq_linear(M, r, bounds=(lo, hi), method="bvls").x, dtype=np.float64)


class BoxLeastSquares:
    """``min ‖M x − r‖² s.t. lo ≤ x ≤ hi`` for ``n`` unknowns, solved by DAQP.

    ``fallbacks`` counts the solves DAQP did not report as successful (BVLS answered those).
    """

    def __init__(self, n: int) -> None:
        self.n = n
        # DAQP's default primal tolerance (1e-6) lets it stop with bounds violated by up to
        # that much; clipped back into the box, such a point is not the optimum (KKT residual
        # ~1e-5 on 7 of 2000 random 60-variable problems); at 1e-10 every one was optimal to
        # 1e-11 at no measurable cost (tests/test_qp.py)
        self._no_rows = np.zeros((0, n))  # no general constraints: the bounds are simple ones
        import scipy.optimize  # noqa: F401  (the fallback's, in memory before any tick)

        self.fallbacks = 0

    def __call__(self, M: FloatArray, r: FloatArray, lo: ArrayLike, hi: ArrayLike) -> FloatArray:
        n = self.n
        if M.shape[1] != n:
            raise ValueError(f"M has {M.shape[1]} columns, this solver takes {n}")
        lower = np.array(np.broadcast_to(np.asarray(lo, dtype=np.float64), (n,)))
        upper = np.array(np.broadcast_to(np.asarray(hi, dtype=np.float64), (n,)))
        H = np.ascontiguousarray(M.T @ M)
        g = np.ascontiguousarray(-(M.T @ r))
        # a fresh constraint-type array each call: every bound an inequality, no warm start,
        # so a solve depends on its own problem alone
        sense = np.zeros(n, dtype=c_int)
        x, _, flag, _ = daqp.solve(H, g, self._no_rows, upper, lower, sense, primal_tol=PRIMAL_TOL)
        if flag != _OPTIMAL:
            self.fallbacks += 1
            return bvls(M, r, lower, upper)
        return np.clip(np.asarray(x, dtype=np.float64), lower, upper)
