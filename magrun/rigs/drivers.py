"""Coil drivers: how :class:`~magrun.rigs.hardware.HardwareRig` reaches the amplifiers.

A driver is a small class with the :class:`CoilDriver` interface. Drivers are plugins: a
package registers one under the entry-point group ``magrun.drivers`` with the URL scheme it
serves, and ``--driver SCHEME://…`` picks it::

    # pyproject.toml of a lab's package
    [project.entry-points."magrun.drivers"]
    mylab = "mylab.coils:MyLabDriver"          # magrun run … --rig hardware --driver mylab://…

magrun ships one, :class:`TcpLineDriver` (``tcp://host:port``), which speaks the documented
line protocol (:mod:`magrun.rigs.wire`) to the amplifier controller, or to
``magrun rig-emulator``.
"""

from __future__ import annotations

import hmac
import socket
from abc import ABC, abstractmethod
from importlib.metadata import entry_points
from urllib.parse import urlsplit

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.rigs.wire import (
    SECRET_VARIABLE,
    VERSION,
    LineConnection,
    WireError,
    format_floats,
    is_loopback,
    is_nonce,
    new_nonce,
    parse_floats,
    parse_limits,
    proof,
)

FloatArray = NDArray[np.float64]
ENTRY_POINT_GROUP = "magrun.drivers"


class DriverError(RuntimeError):
    """The driver cannot reach the amplifiers, or they refused a command."""


class RigRefused(DriverError):
    """The rig's handshake is not one magrun drives: a channel or a limit that contradicts the
    protocol's coil system, or a limit that is not a finite positive number. Raised before
    any current is sent."""


def check_announced(
    what: str, unit: str, limit: float | FloatArray, names: tuple[str, ...]
) -> None:
    """Refuse (:class:`RigRefused`) an announced limit that is not finite and positive on
    every channel: a rig that announces ``nan``, ``inf``, 0 or a negative limit is not
    trusted with a current."""
    values = np.broadcast_to(np.asarray(limit, dtype=np.float64), (len(names),))
    bad = ~(np.isfinite(values) & (values > 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise RigRefused(
            f"the rig announces a {what} of {float(values[i])!r} {unit} on channel "
            f"{names[i]}: not a finite positive limit; no current was sent"
        )


class CoilDriver(ABC):
    """The amplifiers of one rig.

    After :meth:`open`, ``channel_names``, ``max_current`` (A) and ``max_slew_rate`` (A/s)
    describe the rig. Every method raises :class:`DriverError` when the rig cannot be
    reached or refuses; the rig's own watchdog must make the coils safe then.
    """

    channel_names: tuple[str, ...]
    max_current: float | FloatArray  # one per channel where they differ
    max_slew_rate: float | FloatArray

    @classmethod
    @abstractmethod
    def from_url(cls, url: str) -> CoilDriver:
        """The driver for ``url`` (``scheme://…``, the part after the scheme is the driver's)."""

    @abstractmethod
    def open(self, watchdog_s: float) -> None:
        """Connect, learn the channels and limits, and arm the rig's stall watchdog."""

    @abstractmethod
    def send(self, currents: ArrayLike) -> FloatArray:
        """Command currents (A); returns the currents the amplifiers now drive toward."""

    @abstractmethod
    def zero(self) -> FloatArray:
        """Ramp every current to 0 A (at the slew limit)."""

    @abstractmethod
    def close(self) -> None:
        """Zero the currents if still possible, and disconnect."""

    def place(self, pose: ArrayLike) -> bool:
        """Put the robot at ``pose`` if the rig can (an emulator can; a real rig cannot)."""
        return False

    def grab(self) -> tuple[float, NDArray[np.uint8]] | None:
        """A camera frame through the driver's connection, if the rig serves one."""
        return None


#: the largest camera frame a rig may announce, bytes (a 4K RGB frame is 25 MB)
MAX_FRAME_BYTES = 64 << 20


class TcpLineDriver(CoilDriver):
    """The line protocol of :mod:`magrun.rigs.wire` over TCP: ``tcp://host:port``.

    With a shared ``secret`` it authenticates first, both ways (wire, "Security model");
    without one it drives a rig on loopback only."""

    def __init__(
        self, host: str, port: int, timeout_s: float = 2.0, secret: bytes | None = None
    ) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.secret = secret
        self._conn: LineConnection | None = None
        self._seq = 0

    @classmethod
    def from_url(cls, url: str, secret: bytes | None = None) -> TcpLineDriver:
        parts = urlsplit(url)
        if parts.scheme != "tcp" or not parts.hostname or parts.port is None:
            raise DriverError(f"{url!r}: expected tcp://host:port")
        return cls(parts.hostname, parts.port, secret=secret)

    @property
    def conn(self) -> LineConnection:
        if self._conn is None:
            raise DriverError("the driver is not connected")
        return self._conn

    def open(self, watchdog_s: float) -> None:
        if self.secret is None and not is_loopback(self.host):
            raise DriverError(
                f"the rig at {self.host}:{self.port} is not on this machine: give its shared "
                f"secret (--rig-secret FILE, or {SECRET_VARIABLE}); magrun drives a rig "
                "elsewhere only once both sides have proved they hold it"
            )
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except OSError as exc:
            raise DriverError(f"cannot reach the rig at {self.host}:{self.port}: {exc}") from exc
        self._conn = LineConnection(sock, self.timeout_s)
        try:
            if self.secret is not None:
                self._authenticate(self.secret)
            hello = self.conn.request(f"HELLO {VERSION}", "OK")
            if len(hello) != 6 or hello[0] != "magrun-rig" or int(hello[1]) != VERSION:
                raise DriverError(f"the rig speaks {' '.join(hello)!r}, not magrun-rig {VERSION}")
            n = int(hello[2])
            self.max_current, self.max_slew_rate = (
                parse_limits(hello[3], n),
                parse_limits(hello[4], n),
            )
            self.channel_names = tuple(hello[5].split(","))
            if len(self.channel_names) != n:
                raise DriverError(f"the rig announced {n} channels but named {hello[5]!r}")
            check_announced("current limit", "A", self.max_current, self.channel_names)
            check_announced("slew limit", "A/s", self.max_slew_rate, self.channel_names)
            self.conn.request(f"WATCHDOG {watchdog_s * 1e3!r}", "OK")
        except (WireError, ValueError) as exc:
            self.close()
            hint = (
                f" (give its shared secret: --rig-secret FILE, or {SECRET_VARIABLE})"
                if "auth required" in str(exc) else ""
            )  # fmt: skip
            raise DriverError(f"rig at {self.host}:{self.port}: {exc}{hint}") from exc
        except DriverError as exc:
            self.close()
            raise type(exc)(f"rig at {self.host}:{self.port}: {exc}") from exc

    def _authenticate(self, secret: bytes) -> None:
        """Mutual challenge–response (wire, "Security model"); DriverError if the rig's
        proof is wrong (a rig that does not hold the secret)."""
        fields = self.conn.request("CHALLENGE", "NONCE")
        if len(fields) != 1 or not is_nonce(fields[0]):
            raise WireError(f"NONCE {' '.join(fields)!r} is not a 128-bit hex nonce")
        server, client = fields[0], new_nonce()
        reply = self.conn.request(f"AUTH {client} {proof(secret, 'client', server, client)}", "OK")
        expected = proof(secret, "server", server, client)
        if len(reply) != 1 or not hmac.compare_digest(reply[0], expected):
            raise DriverError("the rig did not prove that it holds the shared secret")

    def _error(self, what: str, exc: Exception) -> DriverError:
        return DriverError(f"rig at {self.host}:{self.port}: {what}: {exc}")

    def _ack(self, fields: list[str]) -> FloatArray:
        return parse_floats(fields[2:], "ACK")

    def send(self, currents: ArrayLike) -> FloatArray:
        values = np.asarray(currents, dtype=np.float64)
        if not np.all(np.isfinite(values)):  # the rig layer clamps first; never on the wire
            raise DriverError(f"refusing to send non-finite currents {format_floats(values)}")
        self._seq += 1
        try:
            fields = self.conn.request(f"SET {self._seq} {format_floats(values)}", "ACK")
        except WireError as exc:
            raise self._error("SET refused or lost", exc) from exc
        if int(fields[0]) != self._seq:
            raise DriverError(
                f"rig at {self.host}:{self.port}: ACK {fields[0]} for SET {self._seq}"
            )
        return self._ack(fields)

    def zero(self) -> FloatArray:
        try:
            return self._ack(self.conn.request("ZERO", "ACK"))
        except WireError as exc:
            raise self._error("ZERO failed", exc) from exc

    def place(self, pose: ArrayLike) -> bool:
        try:
            self.conn.request(f"RESET {format_floats(np.asarray(pose, dtype=float))}", "OK")
        except WireError:
            return False
        return True

    def grab(self) -> tuple[float, NDArray[np.uint8]] | None:
        """A frame from ``GRAB``; ``None`` when the rig dropped it."""
        try:
            header = self.conn.request("GRAB", "FRAME")
        except WireError as exc:
            if "dropped" in str(exc):
                return None
            raise self._error("GRAB failed", exc) from exc
        try:
            t, h, w, c, n = float(header[0]), *(int(v) for v in header[1:5])
        except (ValueError, IndexError) as exc:
            raise self._error("GRAB answered", ValueError(" ".join(header))) from exc
        if not (0 < n <= MAX_FRAME_BYTES and n == h * w * c and c in (1, 3, 4)):
            raise self._error(
                "GRAB", ValueError(f"a frame of {h}x{w}x{c} in {n} bytes is not one magrun takes")
            )
        try:
            data = self.conn.read_bytes(n)
        except WireError as exc:
            raise self._error("GRAB failed", exc) from exc
        return t, np.frombuffer(data, np.uint8).reshape(h, w, c)

    def close(self) -> None:
        if self._conn is None:
            return
        try:
            self.conn.request("ZERO", "ACK")
            self.conn.request("BYE", "OK")
        except WireError:
            pass  # gone already: the rig's watchdog zeroes the currents
        self._conn.close()
        self._conn = None


def load_driver(url: str, secret: bytes | None = None) -> CoilDriver:
    """The driver for ``url``: ``tcp://…`` is magrun's own (authenticating with ``secret``
    where given); other schemes are plugins."""
    scheme = urlsplit(url).scheme
    if scheme == "tcp":
        return TcpLineDriver.from_url(url, secret)
    found = {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
    if scheme not in found:
        known = ", ".join(sorted({"tcp", *found})) or "tcp"
        raise DriverError(f"no coil driver for {url!r}; installed schemes: {known}")
    cls = found[scheme].load()
    if not (isinstance(cls, type) and issubclass(cls, CoilDriver)):
        raise DriverError(f"entry point {scheme!r} is not a CoilDriver subclass")
    return cls.from_url(url)
