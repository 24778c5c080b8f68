"""Current allocation for the two-layer baselines: desired force and torque → the currents.

At the robot's pose the wrench is affine in the currents, ``w = A(p, θ) I + w₀`` (w₀: a
background field's, zero for most systems) with, per channel c
(unit-current field B_c and gradient G_c of the allocation's field model)::

    F_c = G_cᵀ m            τ_c = m × B_c            m = |m| (cos θ, sin θ)

The allocation is a bounded, regularised least-squares problem
(:class:`magrun.control.qp.BoxLeastSquares`: DAQP, with scipy's BVLS as reference)::

    min_I  ‖(A_F I − F_d) / F_ref‖² + ‖(A_τ I − τ_d) / τ_ref‖² + w_b ‖(m̂ᵀ B(I) − B_align) / B_ref‖²
           + λ ‖I / I_max‖²
    s.t.   max(−I_max, I_prev − slew Δt) ≤ I ≤ min(I_max, I_prev + slew Δt)

The B_align row asks for a modest field along the robot's axis: torque fixes only the field
across the axis, and without this row the least-norm answer leaves the orientation
statically unstable whenever the field happens to point backwards. λ keeps the currents
small where the wrench leaves them free.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from magrun.control.qp import BoxLeastSquares
from magrun.field.model import PlanarFieldModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class AllocationConfig:
    """Weights of the allocation's least squares (SI)."""

    force_ref: float = 1e-5  # N
    torque_ref: float = 1e-7  # N m
    align_field: float = 2e-3  # T, wanted along the robot's axis
    align_ref: float = 1e-3  # T
    align_weight: float = 0.01
    regularisation: float = 1e-4


def wrench_matrix(
    model: PlanarFieldModel, position: FloatArray, theta: float, moment: float
) -> tuple[FloatArray, FloatArray]:
    """``(A, b_axis)``: wrench per ampere (3, n) as (Fx, Fy, τ), and field along the axis (n,).

    Units: N/A, N m/A and T/A. The background field's share is :func:`background_wrench`.
    """
    B, G = model.unit_field_and_gradient(np.asarray(position, dtype=np.float64))
    u = np.array([np.cos(theta), np.sin(theta)])
    m = moment * u
    F = np.einsum("ckl,k->cl", G, m)  # F_l = Σ_k m_k ∂B_k/∂x_l
    tau = m[0] * B[:, 1] - m[1] * B[:, 0]
    return np.vstack([F.T, tau]), B @ u


def background_wrench(
    model: PlanarFieldModel, position: FloatArray, theta: float, moment: float
) -> tuple[FloatArray, float]:
    """The wrench (3,) the background field exerts at every current (N, N m), and its field
    along the robot's axis (T); zeros where the system has none."""
    if not model.coils.has_background:
        return np.zeros(3), 0.0
    B, G = model.background_field_and_gradient(np.asarray(position, dtype=np.float64))
    u = np.array([np.cos(theta), np.sin(theta)])
    m = moment * u
    return np.array([*(G.T @ m), m[0] * B[1] - m[1] * B[0]]), float(B @ u)


def allocate(
    model: PlanarFieldModel,
    position: FloatArray,
    theta: float,
    moment: float,
    wrench: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    config: AllocationConfig,
    max_current: float | FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Currents (n,) in A for the desired ``wrench`` (Fx, Fy, τ), and the wrench they give
    (the background's share included)."""
    A, b_axis = wrench_matrix(model, position, theta, moment)
    w0, b0 = background_wrench(model, position, theta, moment)
    n = A.shape[1]
    row_scale = np.array([config.force_ref, config.force_ref, config.torque_ref])
    align_w = np.sqrt(config.align_weight) / config.align_ref
    M = np.vstack(
        [
            A / row_scale[:, None],
            align_w * b_axis[None, :],
            np.diag(np.broadcast_to(np.sqrt(config.regularisation) / max_current, (n,))),
        ]
    )
    rhs = np.concatenate(
        [(wrench - w0) / row_scale, [align_w * (config.align_field - b0)], np.zeros(n)]
    )
    lo = np.minimum(lower, upper - 1e-12)
    currents = _box_lsq(n)(M, rhs, lo, upper)
    return currents, A @ currents + w0


@lru_cache(maxsize=4)
def _box_lsq(n: int) -> BoxLeastSquares:
    """One solver per channel count and process (a CasADi function is built once)."""
    return BoxLeastSquares(n)
