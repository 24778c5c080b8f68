"""A rig that lies about its limits: magrun drives the protocol's coil system's limits, never
the rig's, and refuses a rig whose handshake it cannot trust before any current is sent.

The rig here is a fake in the test: a TCP server that answers HELLO as told and records
every line it receives, so "no current was sent" is checked on the wire itself.
"""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from magrun.field.coils import CoilSystem
from magrun.protocol import load_protocol
from magrun.rigs.cameras import CameraSource
from magrun.rigs.drivers import DriverError, RigRefused, TcpLineDriver
from magrun.rigs.hardware import HardwareRig, agreed_limits
from magrun.robot import load_robot
from magrun.runner import run_protocol
from magrun.tracking.camera import Camera
from magrun.trial import HardwareSpec, RunError

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "protocols" / "tiny.yaml"
PAPER = CoilSystem.load()  # 8 channels, 30 A, the paper's rig


class FakeRig:
    """Answers ``HELLO`` with ``max_a`` and ``slew`` (text, as a rig would send them) for
    ``names``, every other command with OK or an ACK of what it was sent; keeps every line."""

    def __init__(self, max_a: str, slew: str, names: tuple[str, ...] = PAPER.channel_names):
        self.hello = f"OK magrun-rig 1 {len(names)} {max_a} {slew} {','.join(names)}"
        self.lines: list[str] = []
        self._server = socket.create_server(("127.0.0.1", 0))
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._stopped = threading.Event()

    @property
    def url(self) -> str:
        host, port = self._server.getsockname()
        return f"tcp://{host}:{port}"

    def __enter__(self) -> FakeRig:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        # closing a listening socket does not wake a thread blocked in accept() on Linux:
        # the server polls, and stops at its next poll
        self._stopped.set()
        self._thread.join(5)
        self._server.close()

    def _serve(self) -> None:
        self._server.settimeout(0.05)
        while not self._stopped.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            conn.settimeout(None)
            with conn, conn.makefile("rw", encoding="ascii", newline="\n") as f:
                for line in f:
                    line = line.strip()
                    self.lines.append(line)
                    word, *rest = line.split()
                    if word == "HELLO":
                        f.write(self.hello + "\n")
                    elif word == "SET":
                        f.write(f"ACK {rest[0]} 0.0 {' '.join(rest[1:])}\n")
                    elif word == "ZERO":
                        f.write("ACK 0 0.0 " + " ".join(["0.0"] * len(PAPER.channel_names)) + "\n")
                    else:
                        f.write("OK\n")
                    f.flush()
                    if word == "BYE":
                        break

    @property
    def sets(self) -> list[str]:
        return [line for line in self.lines if line.startswith("SET")]


class NoCamera(CameraSource):
    def read(self) -> None:
        return None


def _driver(rig: FakeRig) -> TcpLineDriver:
    host, port = rig.url.removeprefix("tcp://").split(":")
    return TcpLineDriver(host, int(port), timeout_s=10.0)


@pytest.mark.parametrize(
    ("max_a", "slew", "message"),
    [
        ("-30", "-300", r"current limit of -30\.0 A on channel"),  # once driven to 345.8 A
        ("nan", "inf", "current limit of nan A"),
        ("30", "inf", "slew limit of inf A/s"),
        ("0", "300", "current limit of 0.0 A"),
        ("30,30,30,30,30,30,30,-1", "300", "current limit of -1.0 A on channel large_E"),
    ],
)
def test_a_rig_announcing_a_limit_that_is_not_finite_and_positive_gets_no_current(
    max_a: str, slew: str, message: str
) -> None:
    with FakeRig(max_a, slew) as rig, pytest.raises(RigRefused, match=message):
        _driver(rig).open(0.1)
    assert rig.sets == []
    assert rig.lines[-1] == "BYE"  # the driver hung up cleanly


def test_a_rig_announcing_looser_limits_than_the_system_is_refused() -> None:
    """300 A announced on a 30 A system: refused at the handshake, no SET on the wire."""
    with FakeRig("300", "300") as rig:
        driver = _driver(rig)
        driver.open(0.1)
        try:
            with pytest.raises(RigRefused, match=r"300.0 A on channel small_N: looser than "
                               r"the system's 30.0 A"):  # fmt: skip
                agreed_limits(driver, PAPER)
        finally:
            driver.close()
        hw = HardwareRig(_driver(rig), NoCamera(), Camera(), load_robot("magnet"), PAPER)
        with pytest.raises(RigRefused, match="looser"):
            hw.connect()
        assert not hw.connected
    assert rig.sets == []


def test_a_rig_with_tighter_limits_keeps_them_and_the_clamp_is_the_tighter() -> None:
    """A rig that announces 10 A and 100 A/s on a 30 A, ... system: the tighter limits are the
    ones the currents are clamped to before they are sent."""
    with FakeRig("10", "100") as rig:
        hw = HardwareRig(_driver(rig), NoCamera(), Camera(), load_robot("magnet"), PAPER)
        hw.reset([0.0, 0.0, 0.0])  # connects, as before a trial
        try:
            assert hw.max_current == 10.0
            assert hw.max_slew_rate == 100.0
            sent = hw.apply(np.r_[1e3, -1e3, np.nan, np.zeros(5)])
        finally:
            hw.disconnect()
    (line,) = rig.sets
    values = np.array([float(v) for v in line.split()[2:]])
    assert np.all(np.isfinite(values))
    # the first command's slew allowance is one watchdog period: 100 A/s x 0.1 s = 10 A
    assert np.abs(values).max() <= 10.0
    assert values[0] == pytest.approx(10.0)
    assert values[1] == pytest.approx(-10.0)
    assert values[2] == 0.0  # non-finite: 0 A
    np.testing.assert_allclose(sent, values)


def test_per_channel_limits_are_compared_channel_by_channel() -> None:
    tighter_on_one = ",".join(["30"] * 7 + ["5"])
    with FakeRig(tighter_on_one, "300") as rig:
        driver = _driver(rig)
        driver.open(0.1)
        try:
            _, current, slew = agreed_limits(driver, PAPER)
        finally:
            driver.close()
    np.testing.assert_array_equal(current, [30.0] * 7 + [5.0])
    assert slew == min(300.0, float(PAPER.max_slew_rate))


def test_the_driver_never_puts_a_non_finite_current_on_the_wire() -> None:
    with FakeRig("30", "300") as rig:
        driver = _driver(rig)
        driver.open(0.1)
        try:
            with pytest.raises(DriverError, match="non-finite"):
                driver.send(np.r_[np.nan, np.zeros(7)])
        finally:
            driver.close()
    assert rig.sets == []


def test_a_run_on_a_lying_rig_is_refused_before_a_folder_or_a_current(tmp_path: Path) -> None:
    """The runner's handshake: exit 2's RunError, no run folder, no SET."""
    with (
        FakeRig("300", "5000") as rig,
        pytest.raises(RunError, match=r"looser than the system's 30\.0 A"),
    ):
        run_protocol(load_protocol(TINY), tmp_path / "out", rig=HardwareSpec(rig.url))
    assert not (tmp_path / "out").exists()
    assert rig.sets == []


def test_the_command_line_exits_2_on_a_lying_rig(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from magrun.cli import cli

    with FakeRig("nan", "inf") as rig:
        result = CliRunner().invoke(
            cli,
            ["run", str(TINY), "--rig", "hardware", "--driver", rig.url,
             "--out", str(tmp_path / "out")],
        )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "current limit of nan A" in result.output
    assert "Traceback" not in result.output
    assert rig.sets == []
