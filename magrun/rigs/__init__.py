"""Coil rigs behind one interface: the simulated plant (default) and, later, the hardware rig."""

from magrun.rigs.base import Observation, Rig

__all__ = ["Observation", "Rig"]
