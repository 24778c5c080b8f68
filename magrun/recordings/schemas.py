"""magrun's own message schemas, declared: the protobuf messages of the recording format.

The poses and images use Foxglove's published schemas (``foxglove.PoseInFrame``,
``foxglove.RawImage``, ``foxglove.CompressedImage``); the coils' currents and the controller's
status are magrun's own, declared here field by field in field-number order (proto3, package
``magrun``). :func:`proto_source` gives them as a ``.proto`` file for other tools (``protoc``,
Foxglove's and PlotJuggler's decoders read the schema from the MCAP file itself);
:func:`message_classes` registers them in protobuf's default pool and returns their classes,
built at import with no generated code to keep. Fields are only ever added, at the end, so
that every recording stays readable.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2
from google.protobuf.message import Message

__all__ = ["FILE_NAME", "MESSAGES", "PACKAGE", "message_classes", "proto_source"]

PACKAGE = "magrun"
FILE_NAME = "magrun/messages.proto"
TIMESTAMP = "google.protobuf.Timestamp"

#: every message: (field, type, repeated, unit or meaning), in field-number order from 1
MESSAGES: dict[str, tuple[tuple[str, str, bool, str], ...]] = {
    "CoilCurrents": (
        ("timestamp", TIMESTAMP, False, "trial time"),
        ("names", "string", True, "the channels, in the currents' order"),
        ("currents", "double", True, "A, the currents driven"),
    ),
    "ControllerStatus": (
        ("timestamp", TIMESTAMP, False, "trial time"),
        ("method", "string", False, "the control method"),
        ("solve_time", "double", False, "s, the controller's step after the measurement"),
        ("iterations", "uint32", False, "the solver's iterations"),
        ("success", "bool", False, "whether the solver succeeded"),
        ("fallback", "string", False, 'what the controller fell back to ("": none)'),
        ("message", "string", False, "the solver's message"),
        ("compute_time", "double", False, "s, tracking + feedback + controller"),
        ("measurement", "bool", False, "whether a fluoroscopy frame arrived"),
        ("tracking_lost", "bool", False, "whether the tracker lost the robot"),
        ("latency", "double", False, "s, frame to the rig's ack (hardware; else NaN)"),
        ("safety_stop", "string", False, 'why the safety layer stops ("": running)'),
        ("prepare_time", "double", False, "s, the preparation before the measurement"),
    ),
}

_T = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _T.TYPE_DOUBLE, "string": _T.TYPE_STRING, "uint32": _T.TYPE_UINT32,
    "bool": _T.TYPE_BOOL,
}  # fmt: skip


def file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """:data:`MESSAGES` as a protobuf file descriptor (what the MCAP schema records carry)."""
    fd = descriptor_pb2.FileDescriptorProto(
        name=FILE_NAME,
        package=PACKAGE,
        syntax="proto3",
        dependency=["google/protobuf/timestamp.proto"],
    )
    for name, fields in MESSAGES.items():
        m = fd.message_type.add(name=name)
        for number, (fname, ftype, repeated, _meaning) in enumerate(fields, start=1):
            label = _T.LABEL_REPEATED if repeated else _T.LABEL_OPTIONAL
            f = m.field.add(name=fname, number=number, label=label)
            if ftype in _SCALARS:
                f.type = _SCALARS[ftype]
            else:
                f.type_name, f.type = f".{ftype}", _T.TYPE_MESSAGE
    return fd


def proto_source() -> str:
    """:data:`MESSAGES` as the text of ``magrun/messages.proto``."""
    lines = [
        'syntax = "proto3";', "", f"package {PACKAGE};", "",
        'import "google/protobuf/timestamp.proto";',
    ]  # fmt: skip
    for name, fields in MESSAGES.items():
        lines += ["", f"message {name} {{"]
        for number, (fname, ftype, repeated, meaning) in enumerate(fields, start=1):
            prefix = "repeated " if repeated else ""
            lines.append(f"  {prefix}{ftype} {fname} = {number};  // {meaning}")
        lines.append("}")
    return "\n".join(lines) + "\n"


def message_classes() -> dict[str, type[Message]]:
    """The message classes of :data:`MESSAGES` by name, registered in protobuf's default pool
    (once per process)."""
    pool = descriptor_pool.Default()
    timestamp_pb2.Timestamp  # noqa: B018 - the import registers timestamp.proto in the pool
    fd = file_descriptor()
    try:
        pool.FindFileByName(fd.name)
    except KeyError:
        pool.Add(fd)
    out: dict[str, Any] = {}
    for name in MESSAGES:
        out[name] = message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}"))
    return out
