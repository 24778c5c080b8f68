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
import re
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, Literal, Self

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from magrun.yamlio import YamlModelError, parse_yaml_model, read_text_file

FloatArray = NDArray[np.float64]

COIL_TYPES = ("small", "medium", "large")
DEFAULT_COILS_FILE = "coils.yaml"
#: a system folder's description and maps (magrun field import-mpem writes them)
SYSTEM_FILE = "system.yaml"
MAPS_FILE = "reference_maps.npz"
#: the drive limits of a coil-system document: what a field map does not depend on
LIMIT_KEYS = frozenset({"max_current_a", "max_slew_rate_a_per_s", "channel_limits"})
#: the fewest driven channels a coil system may have
MIN_CHANNELS = 3
_CHANNEL_NAME = re.compile(r"[A-Za-z0-9_]+")
#: the Zernike disk of a map system: the workspace's circumscribed circle, this much larger
DISK_MARGIN = 1e-3


class CoilTypeSpec(BaseModel):
    """Winding of one coil type in the base stack, whose axis is the +y axis (YAML units: mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

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
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(pattern=r"^[A-Za-z0-9]+$")
    angle_deg: float


class CoilSystemSpec(BaseModel):
    """The YAML document, validated (unknown keys are errors)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

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
        return self.model_dump(mode="json", exclude=set(LIMIT_KEYS))


class ChannelLimits(BaseModel):
    """One channel's own limits (unset: the system's)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    max_current_a: float | None = Field(default=None, gt=0)
    max_slew_rate_a_per_s: float | None = Field(default=None, gt=0)


class MapSystemSpec(BaseModel):
    """A coil system given by its maps: N driven channels, each with its own unit-current
    map in the system folder's ``reference_maps.npz`` (no symmetry assumed), and optionally
    a background field present at every current (YAML units: mm, A, A/s)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    kind: Literal["maps"] = Field(description="A system given by one map per channel.")
    name: str = Field(min_length=1, description="The system's name, for reports.")
    description: str = ""
    workspace_half_width_mm: float = Field(
        gt=0, description="The workspace is the square |x|, |y| <= this around the origin."
    )
    max_current_a: float = Field(gt=0, description="Current limit of every channel.")
    max_slew_rate_a_per_s: float = Field(gt=0, description="Slew limit of every channel.")
    channels: tuple[str, ...] = Field(
        min_length=MIN_CHANNELS, description="The driven channels, in current-vector order."
    )
    channel_limits: dict[str, ChannelLimits] = Field(
        default_factory=dict,
        description="Per channel, limits other than the system's (either or both).",
    )
    background: bool = Field(
        default=False, description="The maps hold a 'background' field, present at 0 A."
    )
    zernike_disk_radius_mm: float | None = Field(
        default=None, gt=0,
        description="Radius of the Zernike fitting disk, centred on the workspace "
        "(default: the square's circumscribed circle, 0.1 % larger).",
    )  # fmt: skip
    source: dict[str, Any] = Field(default_factory=dict, description="Provenance.")

    @field_validator("channels")
    @classmethod
    def _names(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [n for n in v if not _CHANNEL_NAME.fullmatch(n)]
        if bad:
            raise ValueError(f"channel names are letters, digits and '_': {bad}")
        if len(set(v)) != len(v):
            raise ValueError(f"channel names must be unique, got {list(v)}")
        if "background" in v:
            raise ValueError("'background' names the background field, not a channel")
        return v

    @field_validator("channel_limits")
    @classmethod
    def _limits_of_channels(
        cls, v: dict[str, ChannelLimits], info: ValidationInfo
    ) -> dict[str, ChannelLimits]:
        unknown = sorted(set(v) - set(info.data.get("channels", ())))
        if unknown:
            raise ValueError(f"names {unknown}, which are not channels")
        return v

    def geometry(self) -> dict[str, object]:
        """The document without the drive limits: what a field map depends on (JSON types)."""
        return self.model_dump(mode="json", exclude=set(LIMIT_KEYS))


def _kind(text: str) -> object:
    """The document's ``kind`` (None where it has none or is not YAML: the schema of the
    paper's kind then says what is wrong)."""
    from magrun.yamlio import safe_yaml

    try:
        _, doc = safe_yaml(text, "")
    except YamlModelError:
        return None  # parse_yaml_model then names the file and line
    return doc.get("kind") if isinstance(doc, dict) else None


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
    """The coil rig: its driven channels, workspace and limits (SI units).

    Two kinds of description:

    - the paper's rig and rigs like it (:class:`CoilSystemSpec`): coil types placed in
      stacks rotated about the workspace centre; a channel's map is its type's, rotated;
    - any other system (:class:`MapSystemSpec`, a *system folder* that ``magrun field
      import-mpem`` writes): N channels, each with its own map, and an optional background
      field; every channel's rotation is the identity.
    """

    spec: CoilSystemSpec | MapSystemSpec
    source: str = "<memory>"
    folder: Path | None = None  # a system folder's path (its maps are there)

    @classmethod
    def load(cls, path: str | Path | None = None) -> CoilSystem:
        """Load a coil-system YAML file or a system folder (its ``system.yaml``); ``None``
        loads the paper's rig shipped with magrun.

        Raises
        ------
        magrun.field.coils.CoilFileError
            If the file cannot be read or does not match the schema.
        """
        folder = None
        if path is None:
            ref = resources.files("magrun.field") / "data" / DEFAULT_COILS_FILE
            text, source = (
                ref.read_text(encoding="utf-8"),
                f"magrun:field/data/{DEFAULT_COILS_FILE}",
            )
        else:
            path = Path(path)
            if path.is_dir():
                folder, path = path, path / SYSTEM_FILE
            try:
                text, source = read_text_file(path), str(path)
            except YamlModelError as exc:
                raise CoilFileError(str(exc)) from exc
        kind: type[CoilSystemSpec] | type[MapSystemSpec] = (
            MapSystemSpec if _kind(text) == "maps" else CoilSystemSpec
        )
        try:
            spec = parse_yaml_model(text, kind, source)
        except YamlModelError as exc:
            raise CoilFileError(str(exc)) from exc
        if isinstance(spec, MapSystemSpec) and folder is None:
            folder = Path(source).parent  # a system.yaml named directly
        return cls(spec=spec, source=source, folder=folder)

    @property
    def is_map_system(self) -> bool:
        return isinstance(self.spec, MapSystemSpec)

    @property
    def name(self) -> str:
        """The map system's name; of the paper kind, its folder's or file's name (the
        shipped one: "paper rig")."""
        if isinstance(self.spec, MapSystemSpec):
            return self.spec.name
        if self.source.startswith("magrun:"):
            return "paper rig"
        return self.folder.name if self.folder is not None else Path(self.source).stem

    @property
    def maps_path(self) -> Path | None:
        """The system folder's reference maps (None: the shipped maps of the paper's rig)."""
        return self.folder / MAPS_FILE if self.folder is not None else None

    @property
    def has_background(self) -> bool:
        """Whether a background field acts at every current (its map: ``background``)."""
        return isinstance(self.spec, MapSystemSpec) and self.spec.background

    @property
    def coil_types(self) -> dict[str, CoilTypeSpec]:
        """The paper kind's winding geometry per coil type (none for a map system)."""
        return self.spec.coil_types if isinstance(self.spec, CoilSystemSpec) else {}

    @property
    def fit_types(self) -> tuple[str, ...]:
        """The maps a field model is fitted to: every coil type of the paper kind; every
        channel of a map system, and its background."""
        if isinstance(self.spec, CoilSystemSpec):
            return tuple(self.spec.coil_types)
        return (*self.spec.channels, *(("background",) if self.spec.background else ()))

    def zernike_disk(self, name: str) -> tuple[tuple[float, float], float]:
        """Centre (m, base-stack frame) and radius (m) of the Zernike disk of a map
        :attr:`fit_types` names: Table II's for the paper's coil types; for a map system the
        disk around the workspace (``zernike_disk_radius_mm``, or the square's circumscribed
        circle plus :data:`DISK_MARGIN`)."""
        if isinstance(self.spec, CoilSystemSpec):
            ct = self.spec.coil_types[name]
            return (0.0, ct.center), ct.disk_radius
        r = self.spec.zernike_disk_radius_mm
        radius = r * 1e-3 if r is not None else self.workspace_half_width * math.sqrt(2)
        return (0.0, 0.0), radius * (1 + DISK_MARGIN) if r is None else radius

    @property
    def workspace_half_width(self) -> float:
        """Half the workspace edge, m; the workspace is the square |x|, |y| ≤ this."""
        return self.spec.workspace_half_width_mm * 1e-3

    @property
    def max_current(self) -> float | FloatArray:
        """Current limit, A: one value for every channel, or one per channel (n,) where a
        map system's ``channel_limits`` set some."""
        return self._limits("max_current_a")

    @property
    def max_slew_rate(self) -> float | FloatArray:
        """Slew limit of the amplifiers, A/s: one value, or one per channel (n,)."""
        return self._limits("max_slew_rate_a_per_s")

    def _limits(self, key: str) -> float | FloatArray:
        common = float(getattr(self.spec, key))
        own = self.spec.channel_limits if isinstance(self.spec, MapSystemSpec) else {}
        values = [
            getattr(own[c], key) if c in own and getattr(own[c], key) is not None else common
            for c in self.channel_names
        ]
        return common if all(v == common for v in values) else np.array(values, dtype=float)

    @cached_property
    def channels(self) -> tuple[Channel, ...]:
        """Driven coils: of the paper kind grouped by stack in stack order, then by
        ``driven_types`` order; of a map system in its ``channels`` order."""
        spec = self.spec
        if isinstance(spec, MapSystemSpec):
            eye = rotation_matrix(0.0)
            return tuple(Channel(n, n, "", 0.0, eye) for n in spec.channels)
        out = []
        for stack in spec.stacks:
            angle = math.radians(stack.angle_deg)
            for ctype in spec.driven_types:
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
