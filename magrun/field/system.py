"""One home for a coil system and what magrun builds from it.

A protocol's ``system:`` (a folder that ``magrun field import-mpem`` or ``import-comsol
--out`` writes, or none: the paper's rig shipped with magrun) decides the coils, their
limits, the models the controllers plan with and the maps the simulated plant runs on. Every
part of magrun asks :func:`load_system` for them, so a trial, a replay, ``identify``,
``field check`` and the benchmarks all see the same system::

    >>> from magrun.field.system import load_system
    >>> system = load_system(None)                  # the paper's rig
    >>> system.coils.n_channels, float(system.coils.max_current)
    (8, 30.0)
    >>> zernike, lut = system.models                # the controllers' models
    >>> grid = system.plant_maps                    # the simulated plant's maps

The models carry the system's own coils and so its limits: a folder's fit, never the
shipped rig's, also for a folder of the paper's kind. Each system is loaded once per process
and per version of its folder's files (a file rewritten in place is read again).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property, lru_cache
from pathlib import Path

from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid
from magrun.field.lut import LookupTableFieldModel
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel

__all__ = ["System", "load_system", "shipped_models"]


@dataclass(frozen=True, eq=False)
class System:
    """A coil system (:class:`~magrun.field.coils.CoilSystem`: channels, workspace, limits)
    and, built on first use, its controllers' models and its plant's maps."""

    coils: CoilSystem

    @property
    def folder(self) -> Path | None:
        """The system folder (None: the paper's rig shipped with magrun)."""
        return self.coils.folder

    @cached_property
    def models(self) -> tuple[ZernikeFieldModel, LookupTableFieldModel]:
        """The Zernike and lookup-table models the controllers plan with: the folder's fit and
        maps, with this system's coils (a ``ValueError`` names a missing or foreign fit)."""
        if self.coils.folder is None:
            return shipped_models()
        zernike = ZernikeFieldModel.of_system(self.coils)
        return zernike, LookupTableFieldModel(self.coils, ReferenceMaps.load(self.coils.maps_path))

    @cached_property
    def plant_maps(self) -> ChannelGrid:
        """The reference maps gridded for the simulated plant (:class:`ChannelGrid`)."""
        return ChannelGrid.load(self.coils)


@cache
def shipped_models() -> tuple[ZernikeFieldModel, LookupTableFieldModel]:
    """The paper rig's shipped Zernike and lookup-table models (loaded once per process)."""
    zernike = ZernikeFieldModel.load()
    return zernike, LookupTableFieldModel(zernike.coils, LookupTableFieldModel.load().reference)


def load_system(folder: str | Path | None) -> System:
    """The coil system of a system folder (or a coil-system YAML of the paper's kind; None:
    the paper's rig), loaded once per process and version of the folder's files.

    Raises
    ------
    magrun.field.coils.CoilFileError
        If the folder's description cannot be read or does not match the schema.
    """
    if folder is None:
        return _loaded(None, ())
    path = Path(folder)
    return _loaded(path, _fingerprint(path))


def _fingerprint(path: Path) -> tuple[tuple[str, int, int], ...]:
    """Name, modification time and size of the folder's files, or of the file (a coil-system
    YAML of the paper's kind): the cache's key."""
    if not path.is_dir():
        return _fingerprint_of([path]) if path.is_file() else ()
    return _fingerprint_of(sorted(path.iterdir()))


def _fingerprint_of(paths: list[Path]) -> tuple[tuple[str, int, int], ...]:
    stats = []
    for child in paths:
        try:
            st = child.stat()
        except OSError:
            continue
        stats.append((child.name, st.st_mtime_ns, st.st_size))
    return tuple(stats)


@lru_cache(maxsize=32)
def _loaded(path: Path | None, fingerprint: tuple[tuple[str, int, int], ...]) -> System:
    return System(CoilSystem.load(path))
