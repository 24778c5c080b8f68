"""The line protocol's shared-secret handshake (magrun.rigs.wire, "Security model"), over a
real socket: a rig with a secret serves only a client that proves it holds it, the client
checks the rig's proof in turn, and nothing off loopback runs without one."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magrun.cli import cli
from magrun.rigs.drivers import DriverError, TcpLineDriver
from magrun.rigs.emulator import RigEmulator
from magrun.rigs.sim import SimRig
from magrun.rigs.wire import (
    MIN_SECRET_BYTES,
    LineConnection,
    is_loopback,
    proof,
    read_secret,
)

SECRET = b"0123456789abcdef-a-lab-secret"


def _emulator(secret: bytes | None) -> RigEmulator:
    return RigEmulator(SimRig.default(robot="magnet", seed=0), "127.0.0.1", 0, secret=secret)


@contextlib.contextmanager
def _client(emu: RigEmulator) -> Iterator[LineConnection]:
    conn = LineConnection(socket.create_connection(emu.address, timeout=10), timeout=10)
    try:
        yield conn
    finally:
        conn.close()


def test_a_rig_with_a_secret_serves_only_who_proves_it() -> None:
    with _emulator(SECRET) as emu:
        host, port = emu.address
        # no secret: every request but CHALLENGE, AUTH and BYE is refused; nothing is driven
        with _client(emu) as conn:
            for request in ("HELLO 1", "SET 1 1 1 1 1 1 1 1 1", "WATCHDOG 0", "STATUS"):
                conn.send_line(request)
                assert conn.read_line().startswith("ERR auth required"), request
            assert not np.any(emu.rig.target)
            conn.send_line("BYE")
            assert conn.read_line() == "OK"
        # a wrong proof: refused, and the connection closed
        client = "ab" * 16
        with _client(emu) as conn:
            conn.send_line("CHALLENGE")
            nonce = conn.read_line().split()[1]
            wrong = proof(b"another secret of 16+", "client", nonce, client)
            conn.send_line(f"AUTH {client} {wrong}")
            assert conn.read_line() == "ERR auth failed"
            with pytest.raises(ConnectionError):
                conn.read_line()
        # a replayed proof: each CHALLENGE draws a fresh nonce, so an old AUTH fails
        with _client(emu) as conn:
            conn.send_line("CHALLENGE")
            first = conn.read_line().split()[1]
            conn.send_line("CHALLENGE")
            second = conn.read_line().split()[1]
            assert first != second
            conn.send_line(f"AUTH {client} {proof(SECRET, 'client', first, client)}")
            assert conn.read_line() == "ERR auth failed"
        # the driver with the secret: authenticated both ways, then the usual session
        driver = TcpLineDriver(host, port, timeout_s=10, secret=SECRET)
        driver.open(1.0)
        acked = driver.send(np.full(8, 1.0))
        assert np.all(acked > 0)
        driver.close()
        # the driver without it: told why
        with pytest.raises(DriverError, match=r"auth required.*--rig-secret"):
            TcpLineDriver(host, port, timeout_s=10).open(1.0)


def test_the_driver_checks_the_rigs_proof() -> None:
    """A rig that does not hold the secret (it answers AUTH with a made-up proof) is not
    driven: the driver checks the server's proof before HELLO."""
    server = socket.create_server(("127.0.0.1", 0))
    host, port = server.getsockname()[:2]

    def impostor() -> None:
        sock, _ = server.accept()
        conn = LineConnection(sock, timeout=10)
        conn.read_line()  # CHALLENGE
        conn.send_line("NONCE " + "cd" * 16)
        conn.read_line()  # AUTH
        conn.send_line("OK " + "00" * 32)
        try:
            while line := conn.read_line():
                conn.send_line("ACK 0 0.0" if line.startswith(("ZERO", "SET")) else "OK")
        except ConnectionError:
            pass
        conn.close()

    thread = threading.Thread(target=impostor, daemon=True)
    thread.start()
    with pytest.raises(DriverError, match="did not prove"):
        TcpLineDriver(host, port, timeout_s=10, secret=SECRET).open(1.0)
    thread.join(10)
    server.close()


def test_nothing_off_loopback_runs_without_a_secret(tmp_path: Path) -> None:
    assert is_loopback("127.0.0.1")
    assert is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("192.0.2.1")
    assert not is_loopback("0.0.0.0")
    with pytest.raises(ValueError, match="needs a shared secret"):
        RigEmulator(SimRig.default(robot="magnet", seed=0), "0.0.0.0", 0)
    with pytest.raises(DriverError, match="not on this machine: give its shared secret"):
        TcpLineDriver("192.0.2.1", 5555).open(1.0)  # refused before any connection
    result = CliRunner().invoke(cli, ["rig-emulator", "--host", "0.0.0.0", "--port", "0"])
    assert result.exit_code == 2, result.output
    assert "not loopback" in result.output, result.output


def test_secret_files_are_checked(tmp_path: Path) -> None:
    good = tmp_path / "secret"
    good.write_bytes(SECRET + b"\n")
    good.chmod(0o600)
    assert read_secret(good) == SECRET
    cases = {
        "open to others": (SECRET, 0o644, "readable by others"),
        "short": (b"x" * (MIN_SECRET_BYTES - 1), 0o600, "a rig secret has 16"),
        "blank": (b"   \n", 0o600, "this one 0"),
    }
    for name, (data, mode, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        path.chmod(mode)
        with pytest.raises(ValueError, match=message):
            read_secret(path)
        result = CliRunner().invoke(cli, ["rig-emulator", "--secret", str(path), "--port", "0"])
        assert result.exit_code == 2, (name, result.output)
        assert message in result.output, (name, result.output)
    with pytest.raises(ValueError, match="not a regular file"):
        read_secret(tmp_path)
