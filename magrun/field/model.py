"""The interface every planar field model shares, and the stack geometry they all apply.

A model knows one thing of its own: the unit-current field and gradient of each coil *type*
in the base stack's frame (:meth:`PlanarFieldModel.type_field` in NumPy,
:meth:`PlanarFieldModel.type_field_casadi` as CasADi expressions). This class places the
types in their stacks by rotation and superposes the coils' currents::

    B(p, I) = Σ_c I_c R_c B_type(c)(R_cᵀ p)
    ∇B(p, I) = Σ_c I_c R_c ∇B_type(c)(R_cᵀ p) R_cᵀ

so the Zernike model, the lookup-table model and any future one differ only where they must.

A map system (:class:`~magrun.field.coils.MapSystemSpec`) may add a background field, present
at every current: :meth:`PlanarFieldModel.field_and_gradient` and the CasADi form include it,
the unit-current maps do not.

Conventions: positions are (x, y) in metres in the workspace frame; fields are (Bx, By) in
tesla; a gradient ``G`` has ``G[..., k, l] = ∂B_k/∂x_l`` in tesla per metre; currents are in
amperes, one per driven channel in :attr:`CoilSystem.channels` order.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.coils import CoilSystem

Expr = Any  # a CasADi SX or MX expression, or a number
#: the name under which a model holds a map system's background field (T, not T/A)
BACKGROUND = "background"
FloatArray = NDArray[np.float64]


class PlanarFieldModel(ABC):
    """In-plane magnetic field of the driven coils of a :class:`CoilSystem`."""

    def __init__(self, coils: CoilSystem) -> None:
        self.coils = coils
        # channels grouped by coil type, so each type's map is evaluated once per call
        by_type: dict[str, list[int]] = {}
        for i, ch in enumerate(coils.channels):
            by_type.setdefault(ch.coil_type, []).append(i)
        self._groups = [
            (coil_type, idx, np.stack([coils.channels[i].rotation for i in idx]))
            for coil_type, idx in by_type.items()
        ]

    # -- what a concrete model provides ------------------------------------------------------

    @abstractmethod
    def type_field(self, coil_type: str, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Unit-current field of one coil type in the base-stack frame.

        Parameters
        ----------
        coil_type : str
            A key of ``coils.coil_types``.
        q : ndarray, shape (n, 2)
            Positions in metres, base-stack frame.

        Returns
        -------
        B : ndarray, shape (n, 2)
            Field, T/A.
        G : ndarray, shape (n, 2, 2)
            Gradient ``G[i, k, l] = ∂B_k/∂q_l``, T/(m A).
        """

    @abstractmethod
    def type_field_casadi(
        self, coil_type: str, qx: Expr, qy: Expr
    ) -> tuple[list[Expr], list[list[Expr]]]:
        """CasADi version of :meth:`type_field` at one symbolic point.

        Returns ``[Bx, By]`` and ``[[∂Bx/∂x, ∂Bx/∂y], [∂By/∂x, ∂By/∂y]]`` as expressions.
        """

    # -- the shared API ----------------------------------------------------------------------

    @property
    def channel_names(self) -> tuple[str, ...]:
        return self.coils.channel_names

    def unit_field_and_gradient(self, positions: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Field and gradient of every channel at 1 A (the actuation maps).

        Parameters
        ----------
        positions : array_like, shape (..., 2)
            Positions in metres.

        Returns
        -------
        B : ndarray, shape (..., n_channels, 2)
            T/A.
        G : ndarray, shape (..., n_channels, 2, 2)
            T/(m A), ``G[..., c, k, l] = ∂B_k/∂x_l`` of channel c.
        """
        p = np.asarray(positions, dtype=np.float64)
        if p.shape[-1:] != (2,):
            raise ValueError(f"positions must have shape (..., 2), got {p.shape}")
        lead = p.shape[:-1]
        flat = p.reshape(-1, 2)
        n, n_ch = flat.shape[0], self.coils.n_channels
        B = np.empty((n, n_ch, 2))
        G = np.empty((n, n_ch, 2, 2))
        for coil_type, idx, rots in self._groups:
            q = np.einsum("nj,kji->kni", flat, rots)  # R_cᵀ p for every channel of this type
            Bl, Gl = self.type_field(coil_type, q.reshape(-1, 2))
            Bl = Bl.reshape(len(idx), n, 2)
            Gl = Gl.reshape(len(idx), n, 2, 2)
            B[:, idx] = np.einsum("kij,knj->nki", rots, Bl)
            G[:, idx] = np.einsum("kia,knab,kjb->nkij", rots, Gl, rots)
        return B.reshape(*lead, n_ch, 2), G.reshape(*lead, n_ch, 2, 2)

    def background_field_and_gradient(self, positions: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """The field (..., 2) in T and gradient (..., 2, 2) in T/m present at every current
        (a map system's ``background``); zeros where the system has none."""
        p = np.asarray(positions, dtype=np.float64)
        if not self.coils.has_background:
            return np.zeros(p.shape), np.zeros((*p.shape, 2))
        B, G = self.type_field(BACKGROUND, p.reshape(-1, 2))
        return B.reshape(p.shape), G.reshape(*p.shape, 2)

    def unit_field(self, positions: ArrayLike) -> FloatArray:
        """Field of every channel at 1 A, shape (..., n_channels, 2), T/A."""
        return self.unit_field_and_gradient(positions)[0]

    def unit_gradient(self, positions: ArrayLike) -> FloatArray:
        """Gradient of every channel at 1 A, shape (..., n_channels, 2, 2), T/(m A)."""
        return self.unit_field_and_gradient(positions)[1]

    def field_and_gradient(
        self, positions: ArrayLike, currents: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Total field (..., 2) in T and gradient (..., 2, 2) in T/m for the given currents.

        ``currents`` has shape (n_channels,) or (..., n_channels) matching ``positions``.
        """
        I = np.asarray(currents, dtype=np.float64)
        if I.shape[-1:] != (self.coils.n_channels,):
            raise ValueError(
                f"currents must end in {self.coils.n_channels} channels, got shape {I.shape}"
            )
        B, G = self.unit_field_and_gradient(positions)
        total = np.einsum("...ck,...c->...k", B, I), np.einsum("...ckl,...c->...kl", G, I)
        if not self.coils.has_background:
            return total
        B0, G0 = self.background_field_and_gradient(positions)
        return B0 + total[0], G0 + total[1]

    def casadi_field_and_gradient(self, position: Expr, currents: Expr) -> tuple[Expr, Expr]:
        """Field (2×1) and gradient (2×2) as CasADi expressions of a position and currents,
        the background included.

        ``position`` is a 2-vector and ``currents`` an n_channels-vector, both SX or MX.
        """
        px, py = position[0], position[1]
        Bsum, Gsum = self.casadi_background(px, py)
        for c, ch in enumerate(self.coils.channels):
            R = ch.rotation
            # q = Rᵀ p, dropping the exact zeros of 90° rotations from the expression graph
            qx = weighted_sum((R[0, 0], R[1, 0]), (px, py))
            qy = weighted_sum((R[0, 1], R[1, 1]), (px, py))
            Bl, Gl = self.type_field_casadi(ch.coil_type, qx, qy)
            for k in range(2):
                Bsum[k] = Bsum[k] + currents[c] * weighted_sum(R[k], Bl)
                for l in range(2):
                    # (R G Rᵀ)[k, l] = Σ_ab R[k, a] G[a, b] R[l, b]
                    g = weighted_sum(R[k], [weighted_sum(R[l], Gl[a]) for a in range(2)])
                    Gsum[k][l] = Gsum[k][l] + currents[c] * g
        return ca.vertcat(*Bsum), ca.blockcat(Gsum)

    def casadi_background(self, px: Expr, py: Expr) -> tuple[list[Expr], list[list[Expr]]]:
        """The background field and gradient as expressions (zeros where there is none)."""
        if not self.coils.has_background:
            return [0, 0], [[0, 0], [0, 0]]
        B, G = self.type_field_casadi(BACKGROUND, px, py)
        return list(B), [list(row) for row in G]

    def casadi_function(self, name: str = "field") -> ca.Function:
        """``name(p[2], I[n]) -> (B[2], G[2x2])`` built from SX expressions."""
        p = ca.SX.sym("p", 2)
        I = ca.SX.sym("I", self.coils.n_channels)
        B, G = self.casadi_field_and_gradient(p, I)
        return ca.Function(name, [p, I], [B, G], ["p", "I"], ["B", "G"])


def weighted_sum(weights: Any, terms: Any) -> Expr:
    """Σ w·t over pairs with w ≠ 0, so exact zeros add nothing to a CasADi graph."""
    acc: Expr = 0
    for w, t in zip(weights, terms, strict=True):
        if w == 1:
            acc = acc + t
        elif w == -1:
            acc = acc - t
        elif w != 0:
            acc = acc + float(w) * t
    return acc


class CalibratedFieldModel(PlanarFieldModel):
    """A model with each channel's field per ampere scaled by a measured gain.

    A real coil's field per ampere differs from its model's by a few percent (winding count,
    geometry, the amplifier's current calibration). Fields are linear in the currents, so a
    channel's gain scales its unit-current field and gradient::

        B(p, I) = Σ_c g_c I_c B_c(p)

    ``gains`` come from a calibration (``magrun identify --gains``), one per channel in
    :attr:`CoilSystem.channels` order. The base model is evaluated unchanged: the NumPy maps
    are scaled after, and the CasADi expressions are the base's with the currents scaled
    before, so a compiled controller's code changes only in those constants.
    """

    def __init__(self, base: PlanarFieldModel, gains: ArrayLike) -> None:
        g = np.asarray(gains, dtype=np.float64)
        if g.shape != (base.coils.n_channels,):
            raise ValueError(
                f"{base.coils.n_channels} coil gains expected (one per channel), got {g.shape}"
            )
        if not np.all(np.isfinite(g) & (g > 0)):
            raise ValueError(f"coil gains must be finite and positive, got {g.tolist()}")
        super().__init__(base.coils)
        self.base = base
        self.gains = g

    def type_field(self, coil_type: str, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The base model's unscaled type map (gains are per channel, not per type)."""
        return self.base.type_field(coil_type, q)

    def type_field_casadi(
        self, coil_type: str, qx: Expr, qy: Expr
    ) -> tuple[list[Expr], list[list[Expr]]]:
        return self.base.type_field_casadi(coil_type, qx, qy)

    def unit_field_and_gradient(self, positions: ArrayLike) -> tuple[FloatArray, FloatArray]:
        B, G = self.base.unit_field_and_gradient(positions)
        return B * self.gains[:, None], G * self.gains[:, None, None]

    def casadi_field_and_gradient(self, position: Expr, currents: Expr) -> tuple[Expr, Expr]:
        scaled = ca.vertcat(*(float(g) * currents[c] for c, g in enumerate(self.gains)))
        return self.base.casadi_field_and_gradient(position, scaled)
