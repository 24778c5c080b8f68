"""Recordings run again, offline: the estimator, the field models, the whole trial, and the
robot's and the bench's parameters fitted to them (``magrun replay``, ``magrun identify``).

- :mod:`~magrun.replay.estimator`: a trial's estimator re-run on its recorded measurements
  and currents, with other settings, and written beside the recording.
- :mod:`~magrun.replay.model`: a field model's open-loop k-step prediction error on a
  recording (``replay --model``), on the recording's own coil system.
- :mod:`~magrun.replay.resimulate`: the whole trial simulated again from its recorded
  protocol and seed (``replay --resimulate``); the only mode that uses the runner.
- :mod:`~magrun.replay.identify`: the robot's force factor and the coils' gains, and a
  bench's frame age, amplifier lag and floor friction, fitted to recordings.
- :mod:`~magrun.replay.common`: what they share: :class:`~magrun.replay.common.ReplayError`,
  the recorded trial rebuilt from its own protocol, RMS errors.
"""
