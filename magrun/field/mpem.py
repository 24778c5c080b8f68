"""Calibrated coil systems in ETH's multipole electromagnet model (MPEM) format.

An MPEM calibration (the Tesla / mag_manip software's YAML) describes each coil of an
electromagnetic navigation system as a few *sources*: a position (m), a unit direction and
multipole coefficients ``B_Coeff`` (order 1: one value, a point dipole). The field of a coil
per ampere is the sum of its sources'. For order 1, at x with r = x − position, r̂ = r/|r|,
d the direction and b the coefficient::

    B(x) = b (3 r̂ (r̂ · d) − d) / |r|³                         (T/A)
    ∂B_i/∂x_j = 3b [δ_ij (r·d) + r_i d_j + d_i r_j − 5 r_i r_j (r·d)/|r|²] / |r|⁵

An entry of ``Coil_List`` named ``Offset`` is a background source: its field is present at
every current (T, not T/A). Higher orders (Petruska, Edelmann and Nelson, IEEE Trans. Magn.
2017) and ``A_Coeff`` are refused by name: this module implements order 1, what both shipped
calibrations (OctoMag, MiniMag) use.

:func:`import_mpem` samples a calibration on a plane of the calibration frame and writes a
coil-system folder (:mod:`magrun.field.coils`): ``system.yaml``, ``reference_maps.npz`` (one
unit-current map per coil and the background's map if there is one) and the Zernike model
fitted to them (``zernike_model.json``, with its report, as ``magrun field fit --system``),
its orders selected by the field's and the gradient's R² (:mod:`magrun.field.fitting`): the
calibration gives the gradient exactly, and the gradient is the force.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from magrun.yamlio import YamlModelError, parse_yaml_model, read_text_file

FloatArray = NDArray[np.float64]

#: the Coil_List entry that is a background field rather than a driven coil
BACKGROUND = "Offset"
#: the name of the background's map in a system folder's reference maps
BACKGROUND_MAP = "background"


#: the largest source position (m) and coefficient magnitude an MPEM file may hold. Real
#: calibrations fit far sources with huge coefficients to model a near-uniform field
#: (OctoMag's: 2e5 m, 4e12); these bounds keep |r|⁵ and b/|r|³ well inside floating point
MAX_SOURCE_POSITION_M = 1e9
MAX_COEFFICIENT = 1e30


class MpemError(ValueError):
    """An MPEM file that cannot be read or used; the message names the file (and line)."""


def _listed(
    data: dict[str, Any], key: str, words: tuple[str, str, str]
) -> tuple[Any, dict[str, Any]]:
    """``data[key]`` (a list of names, as written) and the entries it names; ``words``: who
    lists what, and what holds the entries, for the messages."""
    owner, items, holder = words
    if key not in data:
        raise ValueError(f"no {key}: {owner} lists its {items} under {key}")
    names = data[key]
    if not isinstance(names, list):
        return names, {}  # the field's own validation says what is wrong
    missing = [n for n in names if n not in data]
    if missing:
        raise ValueError(f"{key} names {missing}, which the {holder} does not define")
    return names, {n: data[n] for n in names}


class MpemSource(BaseModel):
    """One source of a coil: order 1 is a point dipole."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False
    )

    position: tuple[float, float, float] = Field(alias="Source_Position")
    direction: tuple[float, float, float] = Field(alias="Source_Direction")
    b_coeff: tuple[float, ...] = Field(alias="B_Coeff", min_length=1)
    a_coeff: Any = Field(default=None, alias="A_Coeff")

    @field_validator("position", "direction", "b_coeff")
    @classmethod
    def _finite(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(math.isfinite(x) for x in v):
            raise ValueError("must be finite numbers")
        return v

    @field_validator("position")
    @classmethod
    def _near(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if max(map(abs, v)) > MAX_SOURCE_POSITION_M:
            raise ValueError(f"a source more than {MAX_SOURCE_POSITION_M:g} m from the origin")
        return v

    @field_validator("b_coeff")
    @classmethod
    def _bounded(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if max(map(abs, v)) > MAX_COEFFICIENT:
            raise ValueError(f"a coefficient larger than {MAX_COEFFICIENT:g} in magnitude")
        return v

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        scale = max(map(abs, v))  # scaled first: the squares of huge components overflow
        if scale == 0 or not (norm := math.hypot(*(x / scale for x in v))) > 1e-12:
            raise ValueError("a source direction of zero length")
        return (v[0] / scale / norm, v[1] / scale / norm, v[2] / scale / norm)

    @field_validator("b_coeff")
    @classmethod
    def _order_one(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != 1:
            raise ValueError(
                f"an order-{len(v)} source ({len(v)} B coefficients): only order 1 (point "
                "dipoles) is implemented"
            )
        return v

    @field_validator("a_coeff")
    @classmethod
    def _no_a(cls, v: Any) -> Any:
        if v not in (None, [], ()):
            raise ValueError("A coefficients are not implemented (only B_Coeff sources)")
        return None


class MpemCoil(BaseModel):
    """A coil: its sources by name (``Source_List``)."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False
    )

    source_list: tuple[str, ...] = Field(alias="Source_List", min_length=1)
    sources: dict[str, MpemSource]

    @model_validator(mode="before")
    @classmethod
    def _gather(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        names, sources = _listed(data, "Source_List", ("a coil", "sources", "coil"))
        return {"Source_List": names, "sources": sources}


class MpemFile(BaseModel):
    """The document: ``Coil_List`` and one entry per listed coil; other keys are kept out."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False
    )

    coil_list: tuple[str, ...] = Field(alias="Coil_List", min_length=1)
    coils: dict[str, MpemCoil]
    system_name: str = ""
    workspace: tuple[tuple[float, float], ...] | None = None  # the calibrated box, m

    @model_validator(mode="before")
    @classmethod
    def _gather(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            raise ValueError("an MPEM calibration is a mapping with a Coil_List")
        names, coils = _listed(data, "Coil_List", ("an MPEM calibration", "coils", "file"))
        if isinstance(names, list) and len(set(map(str, names))) != len(names):
            raise ValueError(f"Coil_List names a coil twice: {names}")
        return {
            "Coil_List": names,
            "coils": coils,
            "system_name": str(data.get("System_Name") or ""),
            "workspace": data.get("Workspace_Dimensions"),
        }

    @property
    def driven(self) -> tuple[str, ...]:
        """The coils, in ``Coil_List`` order, without the background."""
        return tuple(n for n in self.coil_list if n != BACKGROUND)


class MpemModel:
    """The field of an MPEM calibration: per coil, in T/A, and the background, in T."""

    def __init__(self, doc: MpemFile, source: str = "<memory>") -> None:
        self.doc = doc
        self.source = source
        self.coil_names = doc.driven
        self.has_background = BACKGROUND in doc.coil_list

    @classmethod
    def load(cls, path: str | Path) -> Self:
        """Read and check a calibration (:class:`MpemError` naming the file and line)."""
        try:
            doc = parse_yaml_model(read_text_file(path), MpemFile, str(path))
        except YamlModelError as exc:
            raise MpemError(str(exc)) from exc
        if not doc.driven:
            raise MpemError(f"{path}: Coil_List names no coil besides {BACKGROUND}")
        return cls(doc, str(path))

    def _sources(self, coil: str) -> tuple[FloatArray, FloatArray, FloatArray]:
        srcs = list(self.doc.coils[coil].sources.values())
        pos = np.array([s.position for s in srcs], dtype=np.float64)
        dirs = np.array([s.direction for s in srcs], dtype=np.float64)
        b = np.array([s.b_coeff[0] for s in srcs], dtype=np.float64)
        return pos, dirs, b

    def coil_field(self, coil: str, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``coil``'s field (n, 3) and gradient (n, 3, 3), ``G[i, k, l] = ∂B_k/∂x_l``, at
        ``points`` (n, 3) m of the calibration frame: T/A (T for the background)."""
        pos, dirs, b = self._sources(coil)
        return dipole_field(points, pos, dirs, b)


def dipole_field(
    points: FloatArray, positions: FloatArray, directions: FloatArray, coeffs: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Summed order-1 MPEM sources (module doc): B (n, 3) and G (n, 3, 3) at ``points``."""
    x = np.asarray(points, dtype=np.float64)
    r = x[:, None, :] - positions[None, :, :]  # (n, s, 3)
    r2 = np.einsum("nsi,nsi->ns", r, r)
    inv = 1.0 / np.sqrt(r2)
    rd = np.einsum("nsi,si->ns", r, directions)  # r · d
    b = coeffs[None, :]
    inv3, inv5 = inv**3, inv**5
    B = b[..., None] * (3 * r * (rd * inv5)[..., None] - directions[None] * inv3[..., None])
    eye = np.eye(3)
    G = (3 * b * inv5)[..., None, None] * (
        eye * rd[..., None, None]
        + r[..., :, None] * directions[None, :, None, :]
        + directions[None, :, :, None] * r[..., None, :]
        - 5 * (rd / r2)[..., None, None] * r[..., :, None] * r[..., None, :]
    )
    return B.sum(axis=1), G.sum(axis=1)


def plane_maps(
    model: MpemModel,
    plane_z: float,
    center: tuple[float, float],
    half_width: float,
    pitch: float,
) -> dict[str, Any]:
    """Every coil's in-plane map (and the background's) on the square grid |x|, |y| ≤
    ``half_width`` around ``center`` on the plane z = ``plane_z`` (all m): FieldMaps by name."""
    from magrun.field.reference import FieldMap

    n = round(2 * half_width / pitch) + 1
    axis = np.linspace(-half_width, half_width, n)
    X, Y = np.meshgrid(axis, axis, indexing="ij")
    pts = np.stack([X.ravel() + center[0], Y.ravel() + center[1], np.full(X.size, plane_z)], axis=1)
    names = [*model.coil_names, *([BACKGROUND] if model.has_background else [])]
    maps = {}
    for name in names:
        B, G = model.coil_field(name, pts)
        key = BACKGROUND_MAP if name == BACKGROUND else name
        maps[key] = FieldMap(
            x=axis, y=axis.copy(), B=B[:, :2].reshape(n, n, 2),
            dB=G[:, :2, :2].reshape(n, n, 2, 2),
        )  # fmt: skip
    return maps


def _clear_of_sources(
    model: MpemModel,
    plane_z: float,
    center: tuple[float, float],
    half_width: float,
    pitch: float,
    source: str,
) -> None:
    """An :class:`MpemError` where a source lies within one grid pitch of the sampled square:
    a dipole's field grows as 1/r³ there and the maps could not hold it (the sources of a
    real system sit in its coils, outside the workspace)."""
    for coil in (*model.coil_names, *([BACKGROUND] if model.has_background else [])):
        for name, src in model.doc.coils[coil].sources.items():
            x, y, z = src.position
            dx = max(abs(x - center[0]) - half_width, 0.0)
            dy = max(abs(y - center[1]) - half_width, 0.0)
            d = math.hypot(dx, dy, z - plane_z)
            if d < pitch:
                raise MpemError(
                    f"{source}: {coil}.{name} lies {d * 1e3:.3g} mm from the workspace square "
                    f"on z = {plane_z * 1e3:g} mm (less than the {pitch * 1e3:g} mm pitch): "
                    "choose a plane or workspace clear of the coils' sources"
                )


def import_mpem(
    calibration: str | Path,
    out: str | Path,
    plane_z: float,
    center: tuple[float, float],
    half_width: float,
    pitch: float | None = None,
    max_current: float = 10.0,
    max_slew_rate: float = 200.0,
) -> Path:
    """Write a system folder ``out`` (``system.yaml``, ``reference_maps.npz``, the Zernike
    fit) from an MPEM calibration: the plane z = ``plane_z`` of its frame, centred at
    ``center``, becomes the workspace square of ``half_width`` (all m), sampled every
    ``pitch`` m (default: 40 intervals across). Returns the folder.

    Raises
    ------
    MpemError
        An unreadable or unusable calibration, or a sampling that does not fit.
    """
    import json

    import yaml

    from magrun.field.coils import MapSystemSpec
    from magrun.field.fitting import write_system_folder
    from magrun.field.reference import ReferenceMaps

    model = MpemModel.load(calibration)
    pitch = pitch if pitch is not None else 2 * half_width / 40
    intervals = 2 * half_width / pitch
    if pitch <= 0 or abs(intervals - round(intervals)) > 1e-6 * intervals or intervals < 2:
        raise MpemError(
            f"--pitch-mm {pitch * 1e3:g}: must divide the workspace's width "
            f"({2 * half_width * 1e3:g} mm) into 2 or more equal steps"
        )
    _clear_of_sources(model, plane_z, center, half_width, pitch, str(calibration))
    maps = plane_maps(model, plane_z, center, half_width, pitch)
    for name, fm in maps.items():
        if not (np.all(np.isfinite(fm.B)) and np.all(np.isfinite(fm.dB))):
            raise MpemError(f"{calibration}: {name}'s field on the plane is not finite")
    cal = Path(calibration)
    spec = MapSystemSpec(
        kind="maps",
        name=model.doc.system_name or cal.stem,
        description=f"imported from the MPEM calibration {cal.name}",
        workspace_half_width_mm=half_width * 1e3,
        max_current_a=max_current,
        max_slew_rate_a_per_s=max_slew_rate,
        channels=model.coil_names,
        background=model.has_background,
        source={
            "importer": "magrun field import-mpem (order-1 MPEM sources, point dipoles)",
            "calibration": cal.name,
            "plane_z_mm": plane_z * 1e3,
            "center_mm": [center[0] * 1e3, center[1] * 1e3],
            "pitch_mm": pitch * 1e3,
            "calibrated_box_m": [list(b) for b in model.doc.workspace or ()],
        },
    )
    meta = {
        "source": f"MPEM calibration {cal.name} (magrun.field.mpem)",
        "coils": spec.model_dump(mode="json"),
        "units": {"x": "m", "y": "m", "B": "T/A", "dB": "T/(m A)", "background": "T, T/m"},
    }
    header = (
        f"# The coil system {spec.name}, imported from {cal.name} by magrun field import-mpem.\n"
        "# Its maps are reference_maps.npz beside this file (one per channel; 'background'\n"
        "# if the calibration has an Offset). Limits are the importer's options: check them\n"
        "# against your amplifiers. Units: mm, A, A/s.\n"
    )
    body = yaml.safe_dump(spec.model_dump(mode="json"), sort_keys=False, allow_unicode=True)
    maps_doc = ReferenceMaps(maps=maps, meta=json.loads(json.dumps(meta)))
    # an MPEM gives the gradient exactly: the model's orders must follow it (the force)
    folder = write_system_folder(out, header + body, maps_doc, gradient=True)
    return folder
