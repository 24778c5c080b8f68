"""Benchmarks behind ``magrun bench``: each returns one JSON-ready dict of measured figures
(the JSON is a contract: keys are only ever added) and, for a terminal, its summary lines.

Every figure in a result comes from the same run on the same machine (described under
``machine``), so ratios between variants are side by side; timings on these shared machines
vary from run to run, ratios much less. Nothing here asserts a speed: the test suite checks
correctness, these functions measure.

========================  ===========================================================
:mod:`~.nmpc`             NMPC solve times and closed-loop tracking, RTI vs IPOPT
:mod:`~.tick`             time per control tick of each stage of a camera trial
:mod:`~.recorder`         camera frames into MCAP; what logging adds to a tick
:mod:`~.sigkill`          recordings after SIGKILL of the recording process
:mod:`~.campaign`         the protocols run with recordings, timed
:mod:`~.rig`              the hardware path on the rig emulator; the watchdog
:mod:`~.cluster`          a protocol's trials on local Ray clusters of 1, 2, … nodes
========================  ===========================================================

They use magrun's public interfaces only: a trial is assembled by :mod:`magrun.trial` and a
run is :func:`magrun.runner.run_protocol`, as for ``magrun run``.
"""
