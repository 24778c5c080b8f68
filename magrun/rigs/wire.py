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
    CHALLENGE                        NONCE <server nonce>     (a rig with a shared secret)
    AUTH <client nonce> <proof>      OK <its proof>           (ERR, then closed, if wrong)
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

Security model
--------------
The protocol carries no encryption: it is for a lab's own network, and on one machine
(loopback) it needs nothing else. A controller given a shared secret (a file of at least
:data:`MIN_SECRET_BYTES` bytes, readable by its owner only) answers every request but
``CHALLENGE``, ``AUTH`` and ``BYE`` with ``ERR auth required`` until the client proves it
holds the secret, and the client checks the controller's proof in turn (mutual
challenge–response, HMAC-SHA256, :func:`proof`; fresh 128-bit nonces on both sides, so a
recorded exchange cannot be replayed)::

    CHALLENGE                 →  NONCE <sn>
    AUTH <cn> <proof(client)> →  OK <proof(server)>
    proof(role) = HMAC-SHA256(secret, "magrun-rig <version> <role> <sn> <cn>"), hex

A wrong proof is answered ``ERR`` and the connection closed. ``magrun rig-emulator`` refuses
to listen on anything but loopback without a secret, and magrun's driver refuses to drive a
rig that is not on loopback without one. The secret authenticates the peers, not the
traffic: on a network others can write to, run the protocol inside a VPN or SSH tunnel.
Whatever the peer, magrun's limits are its own (:mod:`magrun.rigs.hardware`).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import ipaddress
import os
import socket
import stat
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

VERSION = 1
FloatArray = NDArray[np.float64]


#: the shortest shared secret a rig or driver takes, bytes (128 bits)
MIN_SECRET_BYTES = 16
#: the longest secret file read, bytes
MAX_SECRET_BYTES = 4096
#: the environment variable naming the secret file (the CLI's --secret / --rig-secret)
SECRET_VARIABLE = "MAGRUN_RIG_SECRET_FILE"


def read_secret(path: str | Path) -> bytes:
    """The shared secret in the file ``path`` (surrounding whitespace stripped), or a
    ``ValueError`` saying why not: not a regular file, readable by group or others (like an
    SSH key: chmod 600), shorter than :data:`MIN_SECRET_BYTES` or longer than
    :data:`MAX_SECRET_BYTES`."""
    p = Path(path)
    try:
        info = p.stat()
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{p}: the rig secret is not a regular file")
        if info.st_mode & 0o077:
            raise ValueError(
                f"{p}: the rig secret is readable by others (mode {stat.S_IMODE(info.st_mode):o}); "
                "chmod 600 it"
            )
        with p.open("rb") as fh:
            data = fh.read(MAX_SECRET_BYTES + 1).strip()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the rig secret: {exc}") from exc
    if not MIN_SECRET_BYTES <= len(data) <= MAX_SECRET_BYTES:
        raise ValueError(
            f"{p}: a rig secret has {MIN_SECRET_BYTES} to {MAX_SECRET_BYTES} bytes, this one "
            f"{len(data)} (make one with: head -c 32 /dev/urandom | base64 > FILE)"
        )
    return data


def proof(secret: bytes, role: str, server_nonce: str, client_nonce: str) -> str:
    """The HMAC-SHA256 proof that ``role`` (``client`` or ``server``) holds ``secret``, for
    this pair of nonces, in hex (module doc, "Security model")."""
    message = f"magrun-rig {VERSION} {role} {server_nonce} {client_nonce}".encode("ascii")
    return hmac.new(secret, message, hashlib.sha256).hexdigest()


def new_nonce() -> str:
    """128 random bits, hex."""
    return os.urandom(16).hex()


def is_nonce(text: str) -> bool:
    return len(text) == 32 and all(c in "0123456789abcdef" for c in text)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine only: every address it
    resolves to is a loopback address. A name that does not resolve is not."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(i[4][0]).is_loopback for i in infos)


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
