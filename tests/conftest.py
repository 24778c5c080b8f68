"""Shared fixtures: the shipped coil system, reference maps and models (loaded once)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.linalg  # noqa: F401  (SciPy's own BLAS, loaded here to be limited below)
from hypothesis import settings
from threadpoolctl import threadpool_limits

from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid
from magrun.field.lut import LookupTableFieldModel
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel
from magrun.robot import RobotParams, load_robot
from magrun.runner import THREAD_ENV

# One BLAS thread in each test process and in the commands the tests start: the tests already
# run one process per core (pytest-xdist), and OpenBLAS's own threads spin on the other core
# between small products, taking it from the other tests. Trials limit themselves the same
# way (magrun.trial.trial_threads), and the run's pool starts its workers so (THREAD_ENV).
for _name in THREAD_ENV:
    os.environ.setdefault(_name, "1")
threadpool_limits(limits=1, user_api="blas")

# The fuzz tests draw the same examples on every run (a run passes or fails by the code
# alone, on any machine); MAGRUN_FUZZ_EXPLORE=1 draws new ones (docs/development.md). No
# deadline per example: a first example that imports or compiles, or a loaded machine, takes
# longer than hypothesis's 200 ms, and a test passes or fails by what it computes, not its time.
settings.register_profile("repeatable", derandomize=True, deadline=None)
settings.register_profile("explore", derandomize=False, deadline=None)
settings.load_profile("explore" if os.environ.get("MAGRUN_FUZZ_EXPLORE") == "1" else "repeatable")


@pytest.fixture(scope="session", autouse=True)
def compiled_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Compiled CasADi libraries and the plant's Numba code: the machine's cache
    (magrun.compiled), so a second test session, or one after `magrun build`, reuses what an
    earlier one compiled. A library is keyed by its generated source, the compiler command and
    the CasADi version, so it is reused only where it is the same. MAGRUN_TEST_FRESH_CACHE=1
    gives the session a cache of its own (the tests that compile on purpose make their own)."""
    if os.environ.get("MAGRUN_TEST_FRESH_CACHE") == "1":
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


@pytest.fixture
def uncompiled(monkeypatch: pytest.MonkeyPatch) -> None:
    """No C compilation in this test (``MAGRUN_COMPILE=0``, without its one-time warning):
    for tests that build controllers only to check what they were built from (a model, a
    limit, a setting), so a fresh cache does not compile a kernel that no tick runs. The
    NMPC then holds CasADi's QP instead of the compiled kernel (magrun.control.nmpc.rti)."""
    import magrun.compiled

    monkeypatch.setenv("MAGRUN_COMPILE", "0")
    monkeypatch.setattr(magrun.compiled, "_warned", True)
