"""Phantom workspaces as data: boundary polylines read from a documented YAML file.

A phantom file (``protocols/phantoms/spine_l3l4.yaml`` is the paper's spine phantom) lists
named boundaries, each a chain of pieces, ``arc`` (centre, radius, from/to angle in degrees)
or ``points`` (a polyline), in mm; the boundaries in file order must close the outline (each
ends within 0.01 mm of where the next begins, the last of the first). ``critical`` names the
boundary whose clearance matters (the spine's anterior wall, next to the spinal cord), and
``path`` is a route through the phantom for trajectories to follow.

A file is refused (with the line and field) where a coordinate or radius is beyond
:data:`MAX_EXTENT_MM`, an arc sweeps more than a turn, the outline is not a simple closed
curve (boundaries that cross or touch each other, checked with Shapely) or encloses no area,
or the path leaves the outline.

    >>> from magrun.phantom import load_phantom
    >>> phantom = load_phantom("protocols/phantoms/spine_l3l4.yaml")   # doctest: +SKIP
    >>> phantom.walls()                      # magrun.scene.Walls, m: what the simulator stops at
    >>> phantom.clearance(pose, robot)       # m from the robot's body to the critical boundary
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, model_validator

from magrun.scene import Walls
from magrun.yamlio import load_yaml_model

FloatArray = NDArray[np.float64]

#: longest chord an arc is cut into, mm (the sagitta at 4.5 mm radius is under 2 µm)
ARC_CHORD_MM = 0.25
#: how far consecutive boundaries may be apart and still join, mm
JOIN_TOLERANCE_MM = 0.01
#: the largest coordinate and radius a phantom may have, mm (a protocol's workspace is at
#: most a metre across); with arcs of at most a turn it bounds the outline's points
MAX_EXTENT_MM = 1000.0

Coordinate = Annotated[float, Field(ge=-MAX_EXTENT_MM, le=MAX_EXTENT_MM, allow_inf_nan=False)]
Point = tuple[Coordinate, Coordinate]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Arc(_Strict):
    center: Point
    radius: float = Field(gt=0, le=MAX_EXTENT_MM, allow_inf_nan=False)
    from_deg: float = Field(ge=-720, le=720, allow_inf_nan=False)
    to_deg: float = Field(ge=-720, le=720, allow_inf_nan=False)

    @model_validator(mode="after")
    def _one_turn(self) -> Arc:
        if abs(self.to_deg - self.from_deg) > 360:
            raise ValueError("an arc sweeps at most 360 degrees")
        return self

    def points(self) -> FloatArray:
        sweep = math.radians(self.to_deg - self.from_deg)
        n = max(2, math.ceil(abs(sweep) * self.radius / ARC_CHORD_MM) + 1)
        a = np.linspace(math.radians(self.from_deg), math.radians(self.to_deg), n)
        return np.column_stack([np.cos(a), np.sin(a)]) * self.radius + np.asarray(self.center)


class ArcPiece(_Strict):
    arc: Arc


class PointsPiece(_Strict):
    points: Annotated[list[Point], Field(min_length=1)]


def _piece_kind(value: Any) -> str:
    """A piece's kind by its one key (so that errors speak of that kind only)."""
    if isinstance(value, dict):
        return "arc" if "arc" in value else "points"
    return "arc" if isinstance(value, ArcPiece) else "points"


Piece = Annotated[
    Annotated[ArcPiece, Tag("arc")] | Annotated[PointsPiece, Tag("points")],
    Discriminator(_piece_kind),
]
Chain = Annotated[list[Piece], Field(min_length=1)]


def chain_points(pieces: list[Piece]) -> FloatArray:
    """The polyline of a chain of pieces, mm, shape (n, 2).

    A point repeating the one before (where one piece ends and the next begins) is dropped:
    a zero-length wall segment has no direction, and its NaN distances hid every wall from
    the simulated plant's contact test."""
    out = [p.arc.points() if isinstance(p, ArcPiece) else np.asarray(p.points) for p in pieces]
    pts = np.concatenate(out).astype(np.float64)
    keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
    return pts[keep]


class PhantomSpec(_Strict):
    """The YAML document, validated."""

    name: str
    description: str = ""
    critical: str = Field(description="The boundary whose clearance is reported.")
    boundaries: Annotated[dict[str, Chain], Field(min_length=1)]
    path: Chain | None = None

    @model_validator(mode="after")
    def _closed(self) -> PhantomSpec:
        if self.critical not in self.boundaries:
            raise ValueError(f"critical boundary {self.critical!r} is not in boundaries")
        lines = [(k, chain_points(v)) for k, v in self.boundaries.items()]
        for (name, a), (nxt, b) in zip(lines, lines[1:] + lines[:1], strict=True):
            gap = float(np.hypot(*(a[-1] - b[0])))
            if gap > JOIN_TOLERANCE_MM:
                raise ValueError(
                    f"boundary {name!r} ends {gap:.3f} mm from where {nxt!r} begins; "
                    "the boundaries must close the outline"
                )
        # each boundary's first point is the previous one's last, within the tolerance: one
        # point per join, or the join's two points can make a sliver that crosses itself
        outline = _outline(np.concatenate([lines[0][1]] + [p[1:] for _, p in lines[1:]]))
        if self.path is not None:
            import shapely

            path = chain_points(self.path)
            out = [p for p in path if not outline.covers(shapely.Point(p))]
            if out:
                raise ValueError(
                    f"the path leaves the outline: ({out[0][0]:g}, {out[0][1]:g}) mm is outside"
                )
        return self


def _outline(points: FloatArray) -> Any:
    """The outline as a Shapely polygon, or a ``ValueError`` where it is not a simple closed
    curve enclosing an area (boundaries that cross: a bow tie; a chain back over itself)."""
    import shapely
    from shapely.validation import explain_validity

    if len(np.unique(points, axis=0)) < 3:
        raise ValueError("the boundaries enclose no area (fewer than 3 distinct points)")
    polygon = shapely.Polygon(points)
    if not polygon.is_valid:
        why = explain_validity(polygon)  # e.g. "Self-intersection[0 0]"
        raise ValueError(
            f"the outline is not a simple closed curve ({why}, mm): boundaries may meet only "
            "end to end"
        )
    if polygon.area < 1e-6:  # mm²
        raise ValueError("the boundaries enclose no area")
    return polygon


@dataclass(frozen=True)
class Phantom:
    """A phantom's geometry in SI units (m)."""

    name: str
    boundaries: dict[str, FloatArray]  # name -> (n, 2) polyline, m
    critical: str
    path: FloatArray | None  # (n, 2), m

    @classmethod
    def from_spec(cls, spec: PhantomSpec) -> Phantom:
        return cls(
            name=spec.name,
            boundaries={k: chain_points(v) * 1e-3 for k, v in spec.boundaries.items()},
            critical=spec.critical,
            path=chain_points(spec.path) * 1e-3 if spec.path is not None else None,
        )

    def walls(self) -> Walls:
        """Every boundary as wall segments."""
        segs = [np.stack([p[:-1], p[1:]], axis=1) for p in self.boundaries.values()]
        return Walls(np.concatenate(segs))

    def outline(self) -> FloatArray:
        """The closed outline, m, shape (n, 2): every boundary joined in file order."""
        return np.concatenate(list(self.boundaries.values()))

    def contains(self, point: ArrayLike) -> bool:
        """Whether a point (m) lies inside the outline (even-odd rule)."""
        x, y = np.asarray(point, dtype=np.float64)
        poly = self.outline()
        a, b = poly, np.roll(poly, -1, axis=0)
        cross = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        return bool(np.count_nonzero(cross & (x < xi)) % 2)

    def clearance(self, pose: ArrayLike, length: float, diameter: float) -> float:
        """Distance, m, from a robot's body (a capsule) at ``pose`` to the critical boundary.

        Negative when the body overlaps it.
        """
        line = self.boundaries[self.critical]
        p = np.asarray(pose, dtype=np.float64)
        half = max(length / 2 - diameter / 2, 0.0)
        axis = np.array([math.cos(p[2]), math.sin(p[2])]) * half
        d = segment_distances(p[:2] - axis, p[:2] + axis, line[:-1], line[1:])
        return float(d.min() - diameter / 2)


def segment_distances(p0: FloatArray, p1: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances between segments ``p0``–``p1`` and segments ``a``–``b`` (points (..., 2),
    broadcast over leading axes): the least of each end's distance to the other segment, 0
    where they properly cross. A segment of zero length is a point (its terms for the other
    segment's ends are then those ends' distances to it, never below the point's own)."""
    d = np.minimum(point_to_segments(p0, a, b), point_to_segments(p1, a, b))
    d = np.minimum(d, point_to_segments(a, p0, p1))
    d = np.minimum(d, point_to_segments(b, p0, p1))
    return np.where(segments_cross(p0, p1, a, b), 0.0, d)  # proper crossings touch


def point_to_segments(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances from points ``p`` to segments ``a``–``b``, broadcast over leading axes."""
    ab = b - a
    den = np.maximum(np.sum(ab * ab, axis=-1), 1e-30)
    u = np.clip(np.sum((p - a) * ab, axis=-1) / den, 0.0, 1.0)
    return np.hypot(*np.moveaxis(p - (a + u[..., None] * ab), -1, 0))


def segments_cross(
    p0: FloatArray, p1: FloatArray, a: FloatArray, b: FloatArray
) -> NDArray[np.bool_]:
    """Whether segment ``p0``–``p1`` properly crosses each segment ``a``–``b`` (broadcast)."""

    def orient(p: FloatArray, q: FloatArray, r: FloatArray) -> FloatArray:
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                       - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))  # fmt: skip

    o1, o2 = orient(p0, p1, a), orient(p0, p1, b)
    o3, o4 = orient(a, b, p0), orient(a, b, p1)
    return (o1 * o2 < 0) & (o3 * o4 < 0)


def load_phantom(path: str | Path) -> Phantom:
    """Read and validate a phantom file (raises :class:`~magrun.yamlio.YamlModelError`)."""
    return Phantom.from_spec(load_yaml_model(path, PhantomSpec))
