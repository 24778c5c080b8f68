"""The rig a trial runs on, described by a typed configuration and made by :func:`make_rig`.

:class:`SimRigConfig` describes the simulated rig (its robot, walls, seed, camera, coil
system, plant and flow), :class:`HardwareRigConfig` a real one (the coil driver's URL, the
camera source, the coil system whose limits are magrun's own); ``make_rig`` returns a
:class:`~magrun.rigs.base.Rig` either way, the real one not yet connected. The trial's
assembly (:func:`magrun.trial.assemble`) builds the configuration from a protocol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from magrun.rigs.base import Rig

if TYPE_CHECKING:
    from magrun.field.system import System
    from magrun.rigs.plant import Imperfections
    from magrun.rigs.sim import Perturbation
    from magrun.robot import RobotParams
    from magrun.scene import Walls

__all__ = ["HardwareRigConfig", "HardwareSpec", "SimRigConfig", "make_rig"]


@dataclass(frozen=True)
class HardwareSpec:
    """The real rig (``--rig hardware``): a coil driver URL and a camera source.

    ``driver``: ``tcp://host:port`` (the line protocol, :mod:`magrun.rigs.wire`) or a
    plugin's scheme (:mod:`magrun.rigs.drivers`). ``camera``: ``driver`` (frames over the
    driver's connection, as ``magrun rig-emulator`` serves them) or an OpenCV source (device
    index, video file, GStreamer pipeline). Trials run one at a time, in real time.
    """

    driver: str
    camera: str = "driver"
    #: the rig's shared secret (magrun.rigs.wire, "Security model"), or None
    secret: bytes | None = field(default=None, repr=False)

    def __str__(self) -> str:
        return "hardware"


@dataclass(frozen=True)
class SimRigConfig:
    """The simulated rig of one trial: the plant drawn around ``robot`` (``perturbation``,
    ``imperfections``, seeded by ``seed`` and ``plant_seed``), on ``system``'s coils and maps,
    inside ``walls`` (None: the workspace box), a camera rendering frames if ``camera``, the
    flow along ``flow_path`` (m, (n, 2)) where given."""

    robot: RobotParams
    system: System
    seed: int
    walls: Walls | None = None
    camera: bool = False
    perturbation: Perturbation | None = None
    imperfections: Imperfections | None = None
    plant_seed: int | None = None
    flow_path: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class HardwareRigConfig:
    """A real rig: ``spec``'s driver and camera, ``robot`` as magrun knows it, and
    ``system``, whose limits are the currents' (never the rig's own); a watchdog of
    ``watchdog_s`` seconds on the driver's link."""

    spec: HardwareSpec
    robot: RobotParams
    system: System
    watchdog_s: float = 0.1


def make_rig(config: SimRigConfig | HardwareRigConfig) -> Rig:
    """The rig ``config`` describes (a real one not yet connected)."""
    if isinstance(config, HardwareRigConfig):
        from magrun.rigs.cameras import camera_source
        from magrun.rigs.drivers import load_driver
        from magrun.rigs.hardware import HardwareRig
        from magrun.tracking.camera import Camera

        driver = load_driver(config.spec.driver, config.spec.secret)
        source = camera_source(config.spec.camera, driver)
        # the currents' limits are the system's, never the rig's (HardwareRig.connect)
        return HardwareRig(
            driver, source, Camera(), config.robot, config.system.coils, config.watchdog_s
        )
    from magrun.rigs.plant import IDEAL
    from magrun.rigs.sim import DEFAULT_PERTURBATION, SimRig
    from magrun.tracking.camera import CameraConfig

    system = config.system
    perturbation = DEFAULT_PERTURBATION if config.perturbation is None else config.perturbation
    imperfections = IDEAL if config.imperfections is None else config.imperfections
    return SimRig.default(
        robot=config.robot, walls=config.walls, perturbation=perturbation, seed=config.seed,
        camera=CameraConfig() if config.camera else None, coils=system.coils,
        grid=system.plant_maps, plant_seed=config.plant_seed, imperfections=imperfections,
        flow_path=config.flow_path,
    )  # fmt: skip
