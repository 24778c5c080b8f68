"""Rebuild a complete, indexed MCAP file from a truncated or damaged one (``magrun recover``).

A recorder killed mid-trial (SIGKILL, power loss) leaves an MCAP file without its summary and
index, ending inside a chunk. The recorder closes a chunk at least every second of trial time
(:class:`magrun.recordings.writer.TrialRecorder`, ``flush_s``) and hands it to the operating system,
so everything up to the last closed chunk is on disk. :func:`recover` reads the file record by
record (CRCs checked) until the first record that is cut off or damaged, and writes every
schema, channel, message and metadata record it read, in order, to a new file that readers
can index; a ``recovery`` metadata record says what happened.

    >>> report = recover("trial-0.mcap", "trial-0.recovered.mcap")   # doctest: +SKIP
    >>> report.messages, report.complete
    (12040, False)

The Rerun side is regenerated from the recovered MCAP (``magrun recover --rrd``: the
``rerun mcap convert`` that ``magrun view --save`` runs).
"""

from __future__ import annotations

import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from magrun.files import open_binary

#: the bytes every MCAP file starts (and a finished one ends) with
MCAP_MAGIC = b"\x89MCAP0\r\n"


def not_mcap(path: str | Path) -> str | None:
    """Why ``path`` is not an MCAP file ("empty (0 bytes) …", "not an MCAP file …"), or None
    where it starts like one."""
    if is_mcap(path):
        return None
    try:
        if Path(path).stat().st_size == 0:
            return "empty (0 bytes): nothing was recorded in it"
    except OSError:
        pass
    return "not an MCAP file (it does not start with MCAP's magic bytes)"


def is_mcap(path: str | Path) -> bool:
    """Whether ``path`` starts like an MCAP file (its magic bytes); False if unreadable."""
    try:
        with open_binary(path) as fh:
            return fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


@dataclass
class RecoveryReport:
    """What :func:`recover` read and wrote.

    Attributes
    ----------
    messages : int
        Messages recovered (all written to the output).
    per_topic : Counter
        Messages recovered per topic.
    metadata : int
        Metadata records recovered.
    complete : bool
        The input ended with its footer: nothing was lost (the output is a re-indexed copy).
    bytes_read, bytes_total : int
        How far into the input the last good record ended, and the input's size: the
        difference is what was lost (at most one open chunk, i.e. ``flush_s`` of the trial).
    last_time_ns : int or None
        Log time of the last recovered message.
    problem : str
        Why reading stopped early ("" when complete).
    """

    messages: int = 0
    per_topic: Counter[str] = field(default_factory=Counter)
    metadata: int = 0
    complete: bool = False
    bytes_read: int = 0
    bytes_total: int = 0
    last_time_ns: int | None = None
    problem: str = ""

    @property
    def bytes_lost(self) -> int:
        return self.bytes_total - self.bytes_read

    def summary(self) -> str:
        end = "complete" if self.complete else f"cut off ({self.problem})"
        last = "none" if self.last_time_ns is None else f"{self.last_time_ns / 1e9:.3f} s"
        return (
            f"{self.messages} messages recovered ({len(self.per_topic)} topics, last at {last}), "
            f"{self.metadata} metadata records; input {end}; "
            f"{self.bytes_lost} of {self.bytes_total} bytes not recoverable"
        )


def copy_channel(
    writer: Writer,
    channel: Channel,
    schema: Schema | None,
    channel_ids: dict[int, int],
    schema_ids: dict[int, int],
) -> int:
    """The id in ``writer`` of an input file's ``channel`` (and its ``schema``), registered
    on first use; ``channel_ids`` and ``schema_ids`` map input ids to output ids."""
    if channel.id not in channel_ids:
        sid = 0
        if schema is not None:
            if schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            sid = schema_ids[schema.id]
        channel_ids[channel.id] = writer.register_channel(
            channel.topic, channel.message_encoding, sid, dict(channel.metadata)
        )
    return channel_ids[channel.id]


class NothingRecovered(ValueError):
    """An MCAP file of which not one message survives (:func:`recover` writes nothing)."""


def recover(src: str | Path, dst: str | Path) -> RecoveryReport:
    """Copy every intact record of ``src`` into a new, indexed MCAP file ``dst``.

    Raises ``ValueError`` if ``src`` is not an MCAP file at all (no magic / header),
    :class:`NothingRecovered` (a ``ValueError``) if not one message of it is intact, and
    refuses to overwrite ``src`` itself.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise ValueError(f"{src}: write the recovered file elsewhere, never over the original")
    if (why := not_mcap(src)) is not None:
        raise ValueError(f"{src}: {why}")
    report = RecoveryReport(bytes_total=src.stat().st_size)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open_binary(src) as fh:
        reader = StreamReader(fh, validate_crcs=True)
        records = reader.records
        try:
            first = next(records)
        except (McapError, StopIteration, ValueError, EOFError, struct.error) as exc:
            raise ValueError(f"{src}: not an MCAP file ({type(exc).__name__}: {exc})") from exc
        if not isinstance(first, Header):
            raise ValueError(f"{src}: not an MCAP file (no header record)")
        tmp = dst.with_name(dst.name + ".tmp")
        with tmp.open("wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            writer.start(profile=first.profile, library=first.library)
            ids: dict[int, int] = {}  # input channel id -> output channel id
            schema_ids: dict[int, int] = {}
            try:
                for record in records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message):
                        ch = channels.get(record.channel_id)
                        if ch is None:
                            continue  # a message whose channel record was lost
                        schema = schemas[ch.schema_id] if ch.schema_id else None
                        out_id = copy_channel(writer, ch, schema, ids, schema_ids)
                        writer.add_message(
                            out_id, record.log_time, record.data, record.publish_time,
                            record.sequence,
                        )  # fmt: skip
                        report.messages += 1
                        report.per_topic[ch.topic] += 1
                        report.last_time_ns = record.log_time
                    elif isinstance(record, Metadata):
                        writer.add_metadata(record.name, dict(record.metadata))
                        report.metadata += 1
                    elif isinstance(record, Footer):
                        report.complete = True
                    report.bytes_read = fh.tell()
            except Exception as exc:  # a cut or damaged record: mcap, zstd, lz4 or struct raise
                report.problem = f"{type(exc).__name__}: {exc}".strip(": ")
            if report.complete:
                report.bytes_read = report.bytes_total
            else:
                report.problem = report.problem or "the file ends before its footer"
            writer.add_metadata(
                "recovery",
                {
                    "source": src.name,
                    "complete": str(report.complete).lower(),
                    "messages": str(report.messages),
                    "bytes_lost": str(report.bytes_lost),
                    "problem": report.problem,
                },
            )
            writer.finish()
        if report.messages == 0:
            # nothing a reader could use: no copy that looks like a recording, and an
            # existing dst is left as it was
            tmp.unlink()
            raise NothingRecovered(
                f"{src}: no message could be recovered from its {report.bytes_total:,} bytes "
                f"({report.problem or 'it holds none'}); {dst} was not written"
            )
        tmp.replace(dst)
    return report
