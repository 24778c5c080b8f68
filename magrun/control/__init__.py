"""The control methods: an estimator and a planner behind one :class:`~magrun.control.base.
Controller` (:mod:`magrun.control.methods` builds them). This package face stays light (no
CasADi): the protocol schema reads :data:`METHODS` from it."""

#: the paper's proposed method and its five baselines, as protocols and recordings name them
METHODS = ("proposed", "baseline1", "baseline2", "baseline3", "baseline4", "baseline5")
#: the methods whose planner is the NMPC on the coil currents (:mod:`magrun.control.methods`)
NMPC_METHODS = ("proposed", "baseline1", "baseline5")
