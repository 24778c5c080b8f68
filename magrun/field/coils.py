"""Coil system geometry and limits, loaded from a documented YAML file.

The default file, ``magrun/field/data/coils.yaml``, describes the paper's rig (Section II-A,
Table II): four stacks of small/medium/large coils around a 100 mm workspace, of which the
small and large coils of each stack are driven (8 channels, 30 A each).

The YAML uses millimetres for readability; every attribute of the loaded objects is SI (m, A).

    >>> from magrun.field.coils import CoilSystem
    >>> coils = CoilSystem.load()
    >>> coils.channel_names
    ('small_N', 'large_N', 'small_W', 'large_W', 'small_S', 'large_S', 'small_E', 'large_E')

Every field model takes a position in the workspace frame, rotates it into the frame of the
base ("N") stack, evaluates the coil type's map there and rotates the result back. For a stack
at angle α: ``B(p) = R(α) B_type(R(α)ᵀ p)`` and ``∇B(p) = R(α) ∇B_type(R(α)ᵀ p) R(α)ᵀ``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Self

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from magrun.yamlio import YamlModelError, parse_yaml_model

COIL_TYPES = ("small", "medium", "large")
DEFAULT_COILS_FILE = "coils.yaml"


class CoilTypeSpec(BaseModel):
    """Winding of one coil type in the base stack, whose axis is the +y axis (YAML units: mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    center_mm: float = Field(gt=0, description="Distance of the winding centre from the origin.")
    disk_radius_mm: float = Field(gt=0, description="Radius of the Zernike fitting disk.")
    length_mm: float = Field(gt=0, description="Axial length of the winding.")
    inner_radius_mm: float = Field(gt=0)
    outer_radius_mm: float = Field(gt=0)
    turns: int = Field(gt=0)

    @model_validator(mode="after")
    def _radii_ordered(self) -> Self:
        if self.outer_radius_mm <= self.inner_radius_mm:
            raise ValueError("outer_radius_mm must exceed inner_radius_mm")
        return self

    @property
    def center(self) -> float:
        """Axial position of the winding centre, m (the coil centre is (0, center))."""
        return self.center_mm * 1e-3

    @property
    def disk_radius(self) -> float:
        """Zernike normalisation radius ρ_max, m."""
        return self.disk_radius_mm * 1e-3

    @property
    def length(self) -> float:
        return self.length_mm * 1e-3

    @property
    def inner_radius(self) -> float:
        return self.inner_radius_mm * 1e-3

    @property
    def outer_radius(self) -> float:
        return self.outer_radius_mm * 1e-3

    @property
    def front_face(self) -> float:
        """Axial position of the face toward the workspace, m."""
        return self.center - self.length / 2


class StackSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=r"^[A-Za-z0-9]+$")
    angle_deg: float


class CoilSystemSpec(BaseModel):
    """The YAML document, validated (unknown keys are errors)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    workspace_half_width_mm: float = Field(gt=0)
    max_current_a: float = Field(gt=0)
    max_slew_rate_a_per_s: float = Field(gt=0)
    stacks: tuple[StackSpec, ...] = Field(min_length=1)
    driven_types: tuple[str, ...] = Field(min_length=1)
    coil_types: dict[str, CoilTypeSpec]

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        unknown = [t for t in self.driven_types if t not in self.coil_types]
        if unknown:
            raise ValueError(f"driven_types {unknown} are not in coil_types")
        names = [s.name for s in self.stacks]
        if len(set(names)) != len(names):
            raise ValueError(f"stack names must be unique, got {names}")
        half = self.workspace_half_width_mm
        for name, ct in self.coil_types.items():
            if ct.center_mm - ct.length_mm / 2 <= half:
                raise ValueError(f"coil type {name!r} reaches into the workspace")
        return self

    def geometry(self) -> dict[str, object]:
        """The document without the drive limits: what a field map depends on (JSON types)."""
        return self.model_dump(mode="json", exclude={"max_current_a", "max_slew_rate_a_per_s"})


def rotation_matrix(angle: float) -> NDArray[np.float64]:
    """Counter-clockwise rotation by ``angle`` (rad) about +z, shape (2, 2).

    Multiples of 90° are returned exactly (no 6e-17 residues), so that the four stacks of the
    paper's rig map the square workspace grid onto itself without rounding.
    """
    quarter = angle / (math.pi / 2)
    if abs(quarter - round(quarter)) < 1e-12:
        c, s = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][round(quarter) % 4]
    else:
        c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]], dtype=np.float64)


@dataclass(frozen=True)
class Channel:
    """One driven coil: a coil type placed in one stack."""

    name: str
    coil_type: str
    stack: str
    angle: float  # rad, counter-clockwise rotation of the base stack
    rotation: NDArray[np.float64]  # (2, 2), rotation_matrix(angle)


@dataclass(frozen=True)
class CoilSystem:
    """The coil rig: geometry per coil type, stacks, driven channels and limits (SI units)."""

    spec: CoilSystemSpec
    source: str = "<memory>"

    @classmethod
    def load(cls, path: str | Path | None = None) -> CoilSystem:
        """Load a coil-system YAML file; ``None`` loads the paper's rig shipped with magrun.

        Raises
        ------
        magrun.field.coils.CoilFileError
            If the file cannot be read or does not match the schema.
        """
        if path is None:
            ref = resources.files("magrun.field") / "data" / DEFAULT_COILS_FILE
            text, source = (
                ref.read_text(encoding="utf-8"),
                f"magrun:field/data/{DEFAULT_COILS_FILE}",
            )
        else:
            try:
                text, source = Path(path).read_text(encoding="utf-8"), str(path)
            except (OSError, UnicodeDecodeError) as exc:
                raise CoilFileError(f"{path}: cannot read coil file: {exc}") from exc
        try:
            spec = parse_yaml_model(text, CoilSystemSpec, source)
        except YamlModelError as exc:
            raise CoilFileError(str(exc)) from exc
        return cls(spec=spec, source=source)

    @property
    def coil_types(self) -> dict[str, CoilTypeSpec]:
        return self.spec.coil_types

    @property
    def workspace_half_width(self) -> float:
        """Half the workspace edge, m; the workspace is the square |x|, |y| ≤ this."""
        return self.spec.workspace_half_width_mm * 1e-3

    @property
    def max_current(self) -> float:
        """Per-coil current limit, A."""
        return self.spec.max_current_a

    @property
    def max_slew_rate(self) -> float:
        """Per-coil current slew limit of the amplifiers, A/s."""
        return self.spec.max_slew_rate_a_per_s

    @cached_property
    def channels(self) -> tuple[Channel, ...]:
        """Driven coils, grouped by stack in stack order, then by ``driven_types`` order."""
        out = []
        for stack in self.spec.stacks:
            angle = math.radians(stack.angle_deg)
            for ctype in self.spec.driven_types:
                out.append(
                    Channel(
                        name=f"{ctype}_{stack.name}",
                        coil_type=ctype,
                        stack=stack.name,
                        angle=angle,
                        rotation=rotation_matrix(angle),
                    )
                )
        return tuple(out)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    @property
    def n_channels(self) -> int:
        return len(self.channels)


class CoilFileError(ValueError):
    """A coil-system file that cannot be read or validated; the message names the file."""
