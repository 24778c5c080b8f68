"""A trial's recording: the MCAP file and its Rerun view, written, read back and mended.

The only part of magrun that imports the recording libraries (mcap, mcap_protobuf,
foxglove_schemas_protobuf, rerun); the command line may also start a Rerun viewer. The
format itself (topics, messages, metadata records) is the contract docs/recordings.md
states.

- :mod:`~magrun.recordings.writer`: :class:`~magrun.recordings.writer.TrialRecorder`, a
  trial's ticks to MCAP (protobuf messages, Foxglove schemas) and, beside it, its ``.rrd``;
  a recording copied with poses added (:func:`~magrun.recordings.writer.copy_with_poses`).
- :mod:`~magrun.recordings.process`: the same recorder in a writer process of its own, so
  that encoding never holds up the control loop.
- :mod:`~magrun.recordings.rerun_log`: the ``.rrd`` side: entities, styles, the viewer's
  blueprint, and an ``.rrd`` made from an MCAP file.
- :mod:`~magrun.recordings.reader`: a recording read back tick by tick, and its summary's
  message counts.
- :mod:`~magrun.recordings.recover`: a complete, indexed MCAP file rebuilt from a truncated
  or damaged one.

What the loop hands the recorder (ticks, controller status) is :mod:`magrun.records`, which
needs none of these libraries.
"""
