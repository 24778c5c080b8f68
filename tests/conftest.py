"""Shared fixtures: the shipped coil system, reference maps and models (loaded once)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid
from magrun.field.lut import LookupTableFieldModel
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel
from magrun.robot import RobotParams, load_robot


@pytest.fixture(scope="session", autouse=True)
def compiled_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Compiled CasADi libraries go to this session's own cache (magrun.compiled)."""
    os.environ["MAGRUN_CACHE_DIR"] = str(tmp_path_factory.mktemp("magrun-cache"))


@pytest.fixture(scope="session")
def coils() -> CoilSystem:
    return CoilSystem.load()


@pytest.fixture(scope="session")
def reference() -> ReferenceMaps:
    return ReferenceMaps.load()


@pytest.fixture(scope="session")
def zernike_model() -> ZernikeFieldModel:
    return ZernikeFieldModel.load()


@pytest.fixture(scope="session")
def lut_model(coils: CoilSystem, reference: ReferenceMaps) -> LookupTableFieldModel:
    return LookupTableFieldModel(coils, reference)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def channel_grid(coils: CoilSystem, reference: ReferenceMaps) -> ChannelGrid:
    return ChannelGrid.from_reference(coils, reference)


@pytest.fixture(scope="session")
def magnet_robot() -> RobotParams:
    return load_robot("magnet")
