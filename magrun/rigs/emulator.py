"""``magrun rig-emulator``: the simulated plant and camera behind the rig's line protocol.

It is an amplifier controller as :mod:`magrun.rigs.wire` describes one, run on loopback, so
that the hardware path (driver, camera over the wire, real-time pacing, latency, dropped
frames, the watchdog, a connection that breaks mid-run) is exercised end to end without
coils::

    magrun rig-emulator --port 5555 &
    magrun run protocols/noise.yaml --quick --rig hardware --driver tcp://127.0.0.1:5555

The plant is a :class:`~magrun.rigs.sim.SimRig` advanced in real time: a clock thread
brings it up to the wall clock every ``step_s`` (2 ms) and enforces the watchdog there, so
a stalled client is caught within ``step_s`` of the timeout whether or not it sends
anything. The watchdog is armed from a client's first byte (:data:`DEFAULT_WATCHDOG_S`) and
cannot be switched off: ``WATCHDOG`` takes 0 < ms ≤ :data:`MAX_WATCHDOG_S` · 1000, anything else
is answered ``ERR``. One client at a time (a second one gets ``ERR busy``); a client that
sends nothing for ``idle_timeout_s`` is disconnected, which trips the watchdog. A malformed
request is answered ``ERR``; it never ends the serving thread. With a shared ``secret``
every client must authenticate first (:mod:`magrun.rigs.wire`, "Security model"); without
one the emulator listens on loopback only.

Faults for tests: ``drop_every`` makes every n-th ``GRAB`` fail (``ERR frame dropped``), as
a camera that misses frames; :meth:`RigEmulator.disconnect_client` breaks the connection.
"""

from __future__ import annotations

import contextlib
import hmac
import math
import socket
import threading
import time
from typing import Any

import numpy as np

from magrun.rigs.sim import SimRig
from magrun.rigs.wire import (
    VERSION,
    LineConnection,
    NotAscii,
    WireError,
    format_floats,
    is_loopback,
    is_nonce,
    limits_text,
    new_nonce,
    parse_floats,
    proof,
)

#: the watchdog's timeout from a client's first byte until it sends ``WATCHDOG``, s
DEFAULT_WATCHDOG_S = 0.5
#: the longest timeout ``WATCHDOG`` may set, s
MAX_WATCHDOG_S = 10.0


class RigEmulator:
    """Serve ``rig`` (with its camera, if any) on ``host:port`` (port 0: any free port)."""

    def __init__(
        self,
        rig: SimRig,
        host: str = "127.0.0.1",
        port: int = 0,
        step_s: float = 0.002,
        drop_every: int = 0,
        idle_timeout_s: float = 30.0,
        secret: bytes | None = None,
    ) -> None:
        if secret is None and not is_loopback(host):
            raise ValueError(
                f"listening on {host} (not loopback) needs a shared secret (--secret FILE): "
                "anyone who can reach the port could drive the coils"
            )
        self.secret = secret
        self._authenticated = secret is None
        self._nonce: str | None = None
        self.rig = rig
        self.step_s = step_s
        self.idle_timeout_s = idle_timeout_s
        self.drop_every = drop_every
        self._server = socket.create_server((host, port))
        self.address: tuple[str, int] = self._server.getsockname()[:2]
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._client: LineConnection | None = None
        self.state = "running"
        self.watchdog_s = DEFAULT_WATCHDOG_S
        self.last_set: float | None = None  # wall clock of the last SET
        self.tripped_at: float | None = None  # wall clock of the last watchdog trip
        self.grabs = 0
        self._t0 = time.perf_counter()
        self._sim_t = 0.0
        self._threads: list[threading.Thread] = []

    # ---- lifecycle ---------------------------------------------------------------------

    def start(self) -> RigEmulator:
        self.rig.reset(np.zeros(3))
        self._t0 = time.perf_counter()
        for target, name in ((self._clock, "emulator clock"), (self._accept, "emulator accept")):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def close(self) -> None:
        self._stop.set()
        self.disconnect_client()
        self._server.close()
        for th in self._threads:
            th.join(2.0)

    def __enter__(self) -> RigEmulator:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def serve_forever(self) -> None:
        """Block until interrupted (the CLI)."""
        self.start()
        try:
            while not self._stop.wait(0.5):
                pass
        finally:
            self.close()

    def disconnect_client(self) -> None:
        """Break the client's connection (a cable pulled): the watchdog trips at once."""
        client = self._client
        if client is not None:
            with contextlib.suppress(OSError):
                client.sock.shutdown(socket.SHUT_RDWR)
            client.close()

    # ---- the plant's clock and the watchdog --------------------------------------------

    def now(self) -> float:
        """Rig time, s since start."""
        return time.perf_counter() - self._t0

    def _catch_up(self) -> None:
        """Advance the plant to the wall clock; trip the watchdog if a SET is overdue."""
        now = self.now()
        if (
            self.state == "running"
            and self.last_set is not None
            and now - self.last_set > self.watchdog_s
            and np.any(self.rig.target)  # currents commanded: 0 A needs no ramp (nor ARM)
        ):
            self._trip(self.last_set + self.watchdog_s)
        if now > self._sim_t:
            self.rig.advance(now - self._sim_t)
            self._sim_t = now

    def _trip(self, at: float) -> None:
        # the currents first: whoever sees the state "watchdog" sees them commanded to zero
        self.rig.apply(np.zeros(len(self.rig.channel_names)))  # the amplifiers ramp down
        self.tripped_at = at
        self.state = "watchdog"

    def _clock(self) -> None:
        while not self._stop.wait(self.step_s):
            with self._lock:
                self._catch_up()

    # ---- the protocol ------------------------------------------------------------------

    def _accept(self) -> None:
        self._server.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, _ = self._server.accept()
            except (TimeoutError, OSError):
                continue
            with self._lock:
                busy = self._client is not None
                if not busy:
                    # a client that sends nothing for idle_timeout_s is let go (it would hold
                    # the slot); the watchdog is armed from the first byte, default timeout
                    client = self._client = LineConnection(sock, timeout=self.idle_timeout_s)
                    self.watchdog_s, self.last_set = DEFAULT_WATCHDOG_S, self.now()
                    self._authenticated, self._nonce = self.secret is None, None
            if busy:
                with contextlib.suppress(WireError):
                    LineConnection(sock).send_line("ERR busy: one client at a time")
                sock.close()
                continue
            th = threading.Thread(target=self._serve, args=(client,), daemon=True)
            th.start()

    def _serve(self, conn: LineConnection) -> None:
        try:
            while not self._stop.is_set():
                try:
                    line = conn.read_line()
                except NotAscii as exc:
                    conn.send_line(f"ERR {exc}")
                    continue
                if not line:
                    continue
                if line.split()[0] == "BYE":
                    self._release(conn)  # free before the reply: a client may reconnect at once
                    conn.send_line("OK")
                    break
                if not self._authenticated:
                    if not self._authenticate(conn, line):
                        break  # a wrong proof: the connection is closed
                    continue
                self._handle(conn, line)
        except WireError:
            pass  # the client went away, or sent nothing for idle_timeout_s
        finally:
            self._release(conn)
            conn.close()

    def _release(self, conn: LineConnection) -> None:
        """Free the slot ``conn`` holds; no client, no commands: ramp down now where
        currents are commanded (0 A needs no ramp)."""
        with self._lock:
            if self._client is conn:
                if self.state == "running" and np.any(self.rig.target):
                    self._trip(self.now())
                self._client = None

    def _authenticate(self, conn: LineConnection, line: str) -> bool:
        """Handle a request before authentication (wire, "Security model"): ``CHALLENGE``
        and ``AUTH``; anything else is answered ``ERR auth required``. False: close."""
        cmd, *args = line.split()
        if cmd == "CHALLENGE":
            self._nonce = new_nonce()
            conn.send_line(f"NONCE {self._nonce}")
            return True
        if cmd != "AUTH":
            conn.send_line("ERR auth required: CHALLENGE, then AUTH (this rig has a secret)")
            return True
        assert self.secret is not None
        server = self._nonce
        self._nonce = None  # one AUTH per challenge
        if server is None or len(args) != 2 or not is_nonce(args[0]):
            self._release(conn)
            conn.send_line("ERR AUTH needs a CHALLENGE first, then AUTH <nonce> <proof>")
            return False
        expected = proof(self.secret, "client", server, args[0])
        if not hmac.compare_digest(expected, args[1]):
            self._release(conn)
            conn.send_line("ERR auth failed")
            return False
        self._authenticated = True
        conn.send_line(f"OK {proof(self.secret, 'server', server, args[0])}")
        return True

    def _currents(self) -> str:
        return format_floats(self.rig.target)

    def _handle(self, conn: LineConnection, line: str) -> None:
        cmd, *args = line.split()
        with self._lock:
            self._catch_up()
            t = self.now()
            try:
                reply = self._reply(cmd, args, t)
            except (ValueError, IndexError, WireError) as exc:  # a malformed request
                reply = f"ERR {cmd}: {exc}"
            except Exception as exc:  # never a dead thread: answer and go on
                reply = f"ERR {cmd}: {type(exc).__name__}: {exc}"
        if isinstance(reply, tuple):  # a frame: header line, then the pixels
            header, pixels = reply
            conn.send_line(header)
            conn.send_bytes(pixels)
        else:
            conn.send_line(reply)

    def _reply(self, cmd: str, args: list[str], t: float) -> str | tuple[str, memoryview]:
        rig = self.rig
        n = len(rig.channel_names)
        if cmd == "HELLO":
            return (
                f"OK magrun-rig {VERSION} {n} {limits_text(rig.max_current)} "
                f"{limits_text(rig.max_slew_rate)} " + ",".join(rig.channel_names)
            )
        if cmd == "WATCHDOG":
            ms = float(args[0]) if len(args) == 1 else math.nan
            if not 0 < ms <= MAX_WATCHDOG_S * 1e3:  # NaN too: the watchdog stays armed
                return (
                    f"ERR WATCHDOG needs one timeout, 0 < ms <= {MAX_WATCHDOG_S * 1e3:g}; "
                    f"it stays at {self.watchdog_s * 1e3:g} ms"
                )
            self.watchdog_s = ms * 1e-3
            self.last_set = t
            return "OK"
        if cmd == "ARM":
            self.state, self.last_set = "running", t
            return "OK"
        if cmd == "SET":
            seq, values = args[0], parse_floats(args[1:], "SET")
            if len(values) != n:
                return f"ERR SET needs {n} currents, got {len(values)}"
            if not np.all(np.isfinite(values)):
                self._trip(t)  # a controller never drives a NaN: it stops
                return "ERR SET with a non-finite current: ramping to zero"
            if self.state == "watchdog":
                return f"ERR watchdog: no command for {self.watchdog_s * 1e3:g} ms at t = " + (
                    f"{self.tripped_at:.3f} s; currents ramped to zero; send ARM"
                )
            self.state = "running"
            self.last_set = t
            rig.apply(values)
            return f"ACK {seq} {t!r} {self._currents()}"
        if cmd == "ZERO":
            self.state = "zero"
            rig.apply(np.zeros(n))
            return f"ACK 0 {t!r} {self._currents()}"
        if cmd == "STATUS":
            return f"STATUS {self.state} {t!r} {format_floats(rig.driven)}"
        if cmd == "RESET":
            pose = parse_floats(args, "RESET")
            half = rig.coils.workspace_half_width
            if len(pose) != 3 or not np.all(np.isfinite(pose)):
                return "ERR RESET needs a finite pose: x y theta (m, m, rad)"
            if max(abs(pose[0]), abs(pose[1])) > half or abs(pose[2]) > 1e3:
                return (
                    f"ERR RESET needs a pose in the workspace: |x|, |y| <= {half!r} m, "
                    "|theta| <= 1000 rad"
                )
            rig.reset(pose)
            self._sim_t = t
            self.state, self.last_set = "running", t
            return "OK"
        if cmd == "POSE":
            p = rig.state[:3]
            return f"POSE {t!r} {format_floats(p)}"
        if cmd == "GRAB":
            if rig.camera is None:
                return "ERR the emulated rig has no camera"
            self.grabs += 1
            if self.drop_every and self.grabs % self.drop_every == 0:
                return "ERR frame dropped"
            obs = rig.observe(frame=True)
            frame = obs.frame
            assert frame is not None
            h, w, c = frame.shape
            header = f"FRAME {t!r} {h} {w} {c} {frame.nbytes}"
            return header, memoryview(np.ascontiguousarray(frame).tobytes())
        return f"ERR unknown command {cmd!r}"
