"""The line protocol between magrun and a coil rig's amplifier controller (version 1).

One TCP connection; ASCII lines ending in ``\\n``; numbers in SI units (A, A/s, s, m, rad)
as Python writes floats; one reply per request, in order. The controller may be real
hardware or ``magrun rig-emulator``, which serves the simulated plant and camera::

    request                          reply
    HELLO 1                          OK magrun-rig 1 <n> <max A> <max slew A/s> <name,name,…>
                                     (a limit: one number, or n of them joined by commas,
                                      one per channel, where the channels' limits differ)
    WATCHDOG <ms>                    OK                       set the stall watchdog's timeout
    SET <seq> <I1> … <In>            ACK <seq> <t> <I1> … <In>
    ZERO                             ACK 0 <t> <I1> … <In>    ramp every current to 0 A
    ARM                              OK                       accept SET again after a trip
    STATUS                           STATUS <state> <t> <I1> … <In>   currents driven now
    RESET <x> <y> <θ>                OK                       place the robot (emulator only)
    GRAB                             FRAME <t> <h> <w> <c> <nbytes>, then nbytes of uint8 RGB
    POSE                             POSE <t> <x> <y> <θ>     the true pose (emulator only)
    BYE                              OK, then the controller closes the connection
    anything it cannot do            ERR <message>

``<t>`` is the controller's clock, s. ``ACK`` returns the currents the amplifiers are driving
toward (``STATUS``: driving now, on their way there at the slew limit) after the controller's
own limits (|I| ≤ max, slew ≤ max slew: a controller enforces
them whatever it is sent). ``<state>`` is ``running``, ``zero`` (after ZERO) or ``watchdog``.

The watchdog is armed from a connection's first byte with the controller's default timeout;
``WATCHDOG <ms>`` sets another, a finite number of milliseconds above 0 and at most the
controller's maximum (anything else is answered ``ERR`` and the timeout stays): it cannot be
switched off. If no ``SET`` arrives for the timeout while currents are commanded (state
``running``), the controller ramps every current to zero at the slew limit, enters state
``watchdog``, and answers every ``SET`` with ``ERR watchdog: …`` until ``ARM``. A closed
connection trips it at once; so does a client that sends nothing for the controller's idle
timeout, which is then disconnected (one client at a time: an idle one must not hold the
slot). That is what keeps the coils safe when magrun's loop stalls or
dies: nothing on magrun's side has to work for it.
"""

from __future__ import annotations

import contextlib
import socket

import numpy as np
from numpy.typing import NDArray

VERSION = 1
FloatArray = NDArray[np.float64]


class WireError(ConnectionError):
    """The controller answered ``ERR``, answered nonsense, or the connection broke."""


class NotAscii(WireError):
    """A line arrived whole but is not ASCII: the connection itself is fine."""


def format_floats(values: NDArray[np.float64] | list[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def limits_text(limit: float | FloatArray) -> str:
    """A limit in HELLO's reply: one number, or one per channel joined by commas."""
    if np.ndim(limit) == 0:
        return repr(float(limit))
    return ",".join(repr(float(v)) for v in np.asarray(limit))


def parse_limits(text: str, n: int) -> float | FloatArray:
    """A limit of HELLO's reply (:func:`limits_text`): a float, or an array of ``n``."""
    parts = text.split(",")
    if len(parts) == 1:
        return float(parts[0])
    if len(parts) != n:
        raise WireError(f"a limit for each of {n} channels expected, got {text!r}")
    return parse_floats(parts, "the limits")


def parse_floats(fields: list[str], what: str) -> FloatArray:
    try:
        out = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError as exc:
        raise WireError(f"bad number in {what}: {' '.join(fields)!r}") from exc
    return out


class LineConnection:
    """A socket read as lines and byte blocks, written as lines (a small buffered wrapper)."""

    def __init__(self, sock: socket.socket, timeout: float | None = 2.0) -> None:
        self.sock = sock
        sock.settimeout(timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = bytearray()

    def send_line(self, line: str) -> None:
        try:  # ASCII on the wire whatever the text (a message may quote a θ)
            self.sock.sendall(line.encode("ascii", "replace") + b"\n")
        except OSError as exc:
            raise WireError(f"connection lost while sending: {exc}") from exc

    def send_bytes(self, data: bytes | memoryview) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise WireError(f"connection lost while sending: {exc}") from exc

    def _fill(self) -> None:
        try:
            chunk = self.sock.recv(1 << 16)
        except TimeoutError as exc:
            raise WireError("no reply within the timeout") from exc
        except OSError as exc:
            raise WireError(f"connection lost: {exc}") from exc
        if not chunk:
            raise WireError("the other side closed the connection")
        self._buf += chunk

    def read_line(self) -> str:
        while b"\n" not in self._buf:
            if len(self._buf) > 1 << 16:
                raise WireError("line too long")
            self._fill()
        i = self._buf.index(b"\n")
        line = bytes(self._buf[:i])
        del self._buf[: i + 1]
        try:
            return line.decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise NotAscii("a line that is not ASCII") from exc

    def read_bytes(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill()
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def request(self, line: str, expect: str) -> list[str]:
        """Send ``line``; the reply's fields after ``expect``; ``ERR`` raises WireError."""
        self.send_line(line)
        reply = self.read_line().split()
        if not reply:
            raise WireError(f"empty reply to {line.split()[0]}")
        if reply[0] == "ERR":
            raise WireError(" ".join(reply[1:]) or "ERR")
        if reply[0] != expect:
            raise WireError(f"expected {expect} to {line.split()[0]}, got {' '.join(reply)!r}")
        return reply[1:]

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()
