"""Fuzzing the readers of recordings, manifests, calibrations and coil-system folders, and the
rig's line protocol.

Hypothesis draws the inputs: a real recording cut anywhere or with bytes overwritten,
manifests of any JSON shape, MPEM calibrations of any YAML shape and number, an imported
system folder whose description, maps and fitted models are drawn or damaged, and request
lines of any bytes to the rig emulator. Each reader either returns or raises its one
documented error, naming the file; the emulator answers every line and keeps serving, and
drives no current nobody commanded. Bounded: a few hundred examples each, no deadline.
"""

from __future__ import annotations

import json
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from synthetic import record_tiny

from analysis.load import RecordingError, find_recordings, read_recording
from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid
from magrun.field.lut import LookupTableFieldModel
from magrun.field.mpem import MAX_COEFFICIENT, MAX_SOURCE_POSITION_M, MpemError, MpemModel
from magrun.field.zernike import ZernikeFieldModel
from magrun.recordings.recover import recover
from magrun.rigs.emulator import RigEmulator
from magrun.rigs.sim import SimRig
from magrun.rigs.wire import LineConnection

FUZZ = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    root = tmp_path_factory.mktemp("fuzz")
    path = record_tiny(root, ["methods=[baseline3]", "sweep.tracking_rate_hz=[25.5]"])
    return path["baseline3"].read_bytes()


@st.composite
def damaged(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` cut at a drawn length, with up to 4 drawn runs of bytes overwritten."""
    cut = draw(st.integers(0, len(data)))
    out = bytearray(data[:cut])
    for _ in range(draw(st.integers(0, 4))):
        if not out:
            break
        at = draw(st.integers(0, len(out) - 1))
        patch = draw(st.binary(min_size=1, max_size=16))
        out[at : at + len(patch)] = patch
    return bytes(out)


@FUZZ
@given(data=st.data())
def test_damaged_recordings_are_recovered_or_refused(
    recording: bytes, tmp_path: Path, data: st.DataObject
) -> None:
    src, dst = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    dst.unlink(missing_ok=True)
    src.write_bytes(data.draw(damaged(recording)))
    message = None
    try:
        report = recover(src, dst)
    except ValueError as exc:  # not an MCAP file, or not one message intact: nothing written
        message = str(exc)
    if message is not None:
        assert message.startswith(str(src))
        assert not dst.exists()
        return
    assert report.messages >= 0
    assert report.complete or report.problem
    # whatever was recovered is a whole, readable MCAP file again
    try:
        read_recording(dst)
    except RecordingError as exc:  # e.g. the metadata records were cut away
        message = str(exc)
    assert message is None or message.startswith(str(dst))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=20,
)
manifests = st.one_of(
    json_values.map(json.dumps),
    st.fixed_dictionaries(
        {"protocol": st.text(max_size=6)},
        optional={"trials": st.lists(st.dictionaries(
            st.sampled_from(["mcap", "status", "method", "trial", "conditions", "error"]),
            json_values | st.sampled_from(["../../etc/passwd", "/abs.mcap", "x/trial-0.mcap"]),
            max_size=6,
        ), max_size=3)},
    ).map(json.dumps),
    st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
)  # fmt: skip


@FUZZ
@given(text=manifests)
def test_manifests_of_anything_are_read_or_named(tmp_path: Path, text: str) -> None:
    folder = tmp_path / "run"
    folder.mkdir(exist_ok=True)
    (folder / "manifest.json").write_text(text, encoding="latin-1")
    try:
        found = find_recordings(folder)
    except RecordingError as exc:  # the one allowed failure, naming the manifest
        found, message = [], str(exc)
    else:
        message = None
    assert message is None or message.startswith(str(folder / "manifest.json"))
    for path, _ in found:  # nothing outside the run's folder is ever listed
        assert path.resolve().is_relative_to(folder.resolve())


numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["1e999", "-0", ".nan", ".inf", "0x10", "~", "[]", "{}", "a"]),
)


@st.composite
def mpem_files(draw: st.DrawFn) -> str:
    coils = draw(st.lists(st.sampled_from(["Coil_0", "Coil_1", "Offset"]), max_size=3))
    lines = [f"Coil_List: [{', '.join(coils)}]"]
    for coil in dict.fromkeys(coils):
        lines += [f"{coil}:", "  Source_List: [Src_0]", "  Src_0:"]
        for key, n in (("Source_Position", 3), ("Source_Direction", 3), ("B_Coeff", 1)):
            values = draw(st.lists(numbers, min_size=0, max_size=n + 1))
            lines.append(f"    {key}: [{', '.join(values)}]")
    return "\n".join(lines) + "\n"


@FUZZ
@given(text=st.one_of(mpem_files(), st.text(max_size=200)))
def test_mpem_files_of_anything_are_read_or_named(tmp_path: Path, text: str) -> None:
    path = tmp_path / "cal.yaml"
    path.write_text(text)
    try:
        model = MpemModel.load(path)
    except MpemError as exc:  # the one allowed failure, naming the file
        message = str(exc)
    else:
        message = None
    if message is not None:
        assert message.startswith(str(path))
        return
    for coil in model.coil_names:  # what it accepts is finite, bounded and unit-length
        for src in model.doc.coils[coil].sources.values():
            assert np.all(np.abs(src.position) <= MAX_SOURCE_POSITION_M)
            assert np.all(np.abs(src.b_coeff) <= MAX_COEFFICIENT)
            assert abs(np.linalg.norm(src.direction) - 1) < 1e-12


SYSTEM = Path(__file__).parents[1] / "systems" / "octomag"
SYSTEM_KEYS = ["workspace_half_width_mm", "max_current_a", "max_slew_rate_a_per_s", "kind",
               "zernike_disk_radius_mm", "background", "channels", "channel_limits"]  # fmt: skip
SYSTEM_VALUES = ["[Coil_0]", "{Coil_0: {max_current_a: 1e400}}", "[a, a]", "lut", "maps"]


@st.composite
def system_folders(draw: st.DrawFn) -> dict[str, bytes | None]:
    """Files to replace in a copy of an imported system folder (None: delete the file):
    settings of system.yaml drawn from hostile numbers and shapes, the maps and the fitted
    models cut or overwritten, or swapped for any JSON."""
    out: dict[str, bytes | None] = {}
    described = yaml.safe_load((SYSTEM / "system.yaml").read_text())
    drawn = draw(st.lists(st.sampled_from(SYSTEM_KEYS), max_size=3, unique=True))
    lines = [yaml.safe_dump({k: v for k, v in described.items() if k not in drawn})]
    lines += [f"{k}: {draw(numbers | st.sampled_from(SYSTEM_VALUES))}" for k in drawn]
    out["system.yaml"] = "\n".join(lines).encode()
    for name in ("reference_maps.npz", "zernike_model.json", "zernike_fit.json"):
        match draw(st.sampled_from(["keep"] * 6 + ["damage", "json", "delete"])):
            case "damage":
                out[name] = draw(damaged((SYSTEM / name).read_bytes()))
            case "json":
                out[name] = json.dumps(draw(json_values)).encode()
            case "delete":
                out[name] = None
    return out


@settings(max_examples=100, deadline=None)
@given(files=system_folders())
def test_system_folders_of_anything_are_loaded_or_named(
    tmp_path_factory: pytest.TempPathFactory, files: dict[str, bytes | None]
) -> None:
    """What ``magrun run`` reads of a system folder before its first trial either loads, with
    finite positive limits, or raises a ``ValueError`` naming the folder or its file."""
    folder = tmp_path_factory.mktemp("system")
    shutil.copytree(SYSTEM, folder, dirs_exist_ok=True)
    for name, content in files.items():
        if content is None:
            (folder / name).unlink()
        else:
            (folder / name).write_bytes(content)
    try:
        coils = CoilSystem.load(folder)
        ChannelGrid.load(coils)
        ZernikeFieldModel.load(system=folder)
        LookupTableFieldModel.load(system=folder)
    except ValueError as exc:  # the one allowed failure, naming where
        message = str(exc)
    else:
        message = None
    event("refused" if message else "loaded")
    if message is not None:
        assert str(folder) in message
        return
    limits = np.append(coils.max_current, coils.max_slew_rate)
    assert np.all(np.isfinite(limits))
    assert np.all(limits > 0)


@pytest.fixture(scope="module")
def emulator() -> RigEmulator:
    emu = RigEmulator(SimRig.default(robot="magnet", seed=0, camera=None), "127.0.0.1", 0)
    with emu:
        yield emu


lines = st.one_of(
    st.binary(max_size=80).filter(lambda b: b"\n" not in b and not b.lstrip().startswith(b"BYE")),
    st.builds(
        lambda cmd, args: (cmd + " " + " ".join(args)).encode(),
        st.sampled_from(["HELLO", "WATCHDOG", "SET", "ZERO", "ARM", "STATUS", "RESET", "GRAB",
                         "POSE", "CHALLENGE", "AUTH", "set", "", "SET 1"]),
        st.lists(numbers, max_size=10),
    ),
)  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(requests=st.lists(lines, min_size=1, max_size=8))
def test_the_line_protocol_answers_anything_and_keeps_serving(
    emulator: RigEmulator, requests: list[bytes]
) -> None:
    """Every line gets one reply of the protocol's words; the serving thread survives; a
    current is driven only where a well-formed SET of finite values asked for it."""
    sock = socket.create_connection(emulator.address, timeout=10)
    conn = LineConnection(sock, timeout=10)
    try:
        for raw in requests:
            sock.sendall(raw + b"\n")
            try:
                blank = not raw.decode("ascii").strip()
            except UnicodeDecodeError:
                blank = False  # answered ERR: not ASCII
            if blank:
                continue  # an empty line gets no reply
            reply = conn.read_line().split()
            assert reply, raw
            assert reply[0] in {"OK", "ACK", "ERR", "STATUS", "POSE", "FRAME", "NONCE"}, raw
            if reply[0] == "FRAME":
                conn.read_bytes(int(reply[5]))
            bound = np.asarray(emulator.rig.max_current)
            assert np.all(np.abs(emulator.rig.target) <= bound + 1e-9), raw
        conn.send_line("ZERO")
        assert conn.read_line().startswith(("ACK", "ERR"))
        conn.send_line("HELLO 1")
        assert conn.read_line().startswith("OK magrun-rig 1")  # still serving
        conn.send_line("BYE")
        assert conn.read_line() == "OK"
    finally:
        conn.close()
