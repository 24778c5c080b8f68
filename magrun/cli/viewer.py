"""The Rerun viewers the commands open: a window, the web viewer, or one already running.

``magrun view`` opens a file in one (:func:`open_file`). ``magrun run`` and ``magrun replay``
stream to one while they record (:func:`live_view`, options :func:`live_view_options`): the
recorders send each trial to a gRPC URL (``rerun+http://HOST:PORT/proxy``) as well as to
their files (:class:`magrun.recordings.rerun_log.RerunLog`), and the files are written the
same whether a viewer is there, closes half-way or never answers.

- ``--view``: a new viewer window (it stays open when the command ends);
- ``--connect ADDR``: a viewer or gRPC server already running (``rerun``, ``rerun
  --serve-grpc``), at PORT, HOST:PORT or its URL;
- ``--web``: Rerun's web viewer, served on 127.0.0.1 for a browser (a headless workstation,
  a remote server over an ssh tunnel); it keeps serving after the run until Ctrl-C.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

import click

from magrun.cli.common import InputError

#: the web viewer's HTTP port unless --web-port / --port says otherwise
WEB_PORT = 9090
#: how long a viewer this command starts may take to listen, s
START_TIMEOUT_S = 30.0


def rerun_executable() -> str:
    """The ``rerun`` command-line tool of the installed rerun-sdk."""
    return shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def check_display(instead: str) -> None:
    """An InputError pointing to ``instead`` (a command with --web) where a window cannot
    open (Linux without a display)."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise InputError(
            "no display to open the viewer on (neither DISPLAY nor WAYLAND_DISPLAY is set); "
            f"serve it to a browser instead: {instead}"
        )


def grpc_url(addr: str) -> str:
    """A viewer's gRPC URL from what a user types: ``PORT``, ``HOST:PORT`` or the URL
    itself (``rerun+http://HOST:PORT/proxy``, ``rerun://``, ``rerun+https://``)."""
    text = addr.strip()
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    if "://" not in text:
        text = f"rerun+http://{text}/proxy"
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError as exc:
        raise InputError(f"--connect {addr}: {exc}") from exc
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname:
        raise InputError(f"--connect {addr}: give PORT, HOST:PORT or rerun+http://HOST:PORT/proxy")
    if port is None:
        text = text.replace(parts.netloc, f"{parts.netloc}:9876", 1)
    if urlsplit(text).path != "/proxy":
        raise InputError(f"--connect {addr}: a viewer's URL ends in /proxy")
    return text


def web_address(web_port: int, grpc: str) -> str:
    """The address to open in a browser: the web viewer, told where its data is."""
    return f"http://127.0.0.1:{web_port}/?url={quote(grpc, safe='')}"


def live_view_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """``--view``, ``--connect``, ``--web`` and ``--web-port`` (module doc)."""
    options = [
        click.option(
            "--view", "open_view", is_flag=True,
            help="Show it in a new Rerun viewer window while it is written (the window "
            "stays open).",
        ),
        click.option(
            "--connect", metavar="ADDR",
            help="Stream it to a Rerun viewer already running: PORT, HOST:PORT or "
            "rerun+http://HOST:PORT/proxy (a `rerun` window listens on 9876).",
        ),
        click.option(
            "--web", is_flag=True,
            help="Stream it to Rerun's web viewer, served on 127.0.0.1 (it prints the "
            "address; it keeps serving at the end until Ctrl-C).",
        ),
        click.option(
            "--web-port", type=click.IntRange(1, 65535), default=WEB_PORT,
            show_default=True, help="With --web: the web viewer's HTTP port.",
        ),
    ]  # fmt: skip
    for option in reversed(options):
        f = option(f)
    return f


class LiveView:
    """A viewer that a command streams to: its gRPC ``url``, and the process when this
    command started it (a window, or the web viewer's server)."""

    def __init__(self, url: str, process: subprocess.Popen[bytes] | None = None,
                 web: str = "") -> None:  # fmt: skip
        self.url = url
        self.process = process
        self.web = web  # the browser's address (--web)

    def linger(self) -> None:
        """With --web: serve until Ctrl-C (SIGTERM too), so the browser can still look."""
        if self.process is None or not self.web:
            return
        click.echo(f"serving the live view at {self.web} (Ctrl-C stops)", err=True)
        wait_interruptible(self.process)

    def close(self) -> None:
        """Stop the web viewer's server if it still runs; a window stays open."""
        if self.web and self.process is not None and self.process.poll() is None:
            _stop(self.process)


@contextmanager
def live_view(
    open_view: bool, connect: str | None, web: bool, web_port: int, instead: str
) -> Iterator[LiveView | None]:
    """The live view the options ask for (None: none), open for the ``with`` body, closed
    after it (``instead``: the command with --web, suggested where no window can open)."""
    if connect is not None and web:
        raise InputError("--connect and --web exclude each other: one viewer at a time")
    if connect is not None:
        from magrun.recordings.rerun_log import viewer_listening

        url = grpc_url(connect)
        if not viewer_listening(url):
            raise InputError(
                f"--connect {connect}: no Rerun viewer listens at {url} (start one with "
                "`rerun`, or use --view to have one opened)"
            )
        yield LiveView(url)
        return
    if not (open_view or web):
        yield None
        return
    view = start_viewer(web, web_port, instead)
    try:
        yield view
    finally:
        view.close()


def start_viewer(web: bool, web_port: int, instead: str) -> LiveView:
    """Start a viewer window or the web viewer's server and wait until it listens."""
    grpc = free_port()
    url = f"rerun+http://127.0.0.1:{grpc}/proxy"
    env = {**os.environ, "RUST_LOG": os.environ.get("RUST_LOG", "warn")}
    if web:
        args = [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
                "--web-viewer-port", str(web_port)]  # fmt: skip
        env["BROWSER"] = "true"  # print the address; open no browser
    else:
        check_display(instead)
        args = [rerun_executable(), "--bind", "127.0.0.1", "--port", str(grpc)]
    with tempfile.TemporaryFile() as log:  # what it says, should it fail to start
        # a session of its own: a Ctrl-C stopping the run cleanly does not close the viewer
        process = subprocess.Popen(
            args, env=env, stdout=log, stderr=log, start_new_session=True
        )  # fmt: skip
        _wait_listening(process, url, log)
    view = LiveView(url, process, web_address(web_port, url) if web else "")
    if web:
        click.echo(f"live view: open {view.web} in a browser", err=True)
    return view


def _wait_listening(process: subprocess.Popen[bytes], url: str, log: Any) -> None:
    from magrun.recordings.rerun_log import viewer_listening

    deadline = time.monotonic() + START_TIMEOUT_S
    while not viewer_listening(url, timeout_s=0.5):
        if process.poll() is not None or time.monotonic() > deadline:
            if process.poll() is None:
                _stop(process)
            log.seek(0)
            tail = log.read().decode(errors="replace").strip().splitlines()[-3:]
            raise InputError(
                "the Rerun viewer did not start"
                + (f" (it said: {' / '.join(tail)})" if tail else "")
            )
        time.sleep(0.1)


def open_file(rrd: Path, web: bool, port: int, shown: Path) -> None:
    """Run the viewer on ``rrd`` (``shown`` is what the user named) until it is closed."""
    env = {**os.environ, "RUST_LOG": os.environ.get("RUST_LOG", "warn")}
    rerun = rerun_executable()
    if web:
        grpc = free_port()
        url = web_address(port, f"rerun+http://127.0.0.1:{grpc}/proxy")
        click.echo(f"serving {shown} at {url} (Ctrl-C stops)", err=True)
        args = [rerun, str(rrd), "--web-viewer", "--web-viewer-port", str(port),
                "--bind", "127.0.0.1", "--port", str(grpc)]  # fmt: skip
        env["BROWSER"] = "true"  # print the address; open no browser
    else:
        args = [rerun, str(rrd), "--bind", "127.0.0.1"]
    code = wait_interruptible(subprocess.Popen(args, env=env, start_new_session=True))
    if code:
        sys.exit(code)


def wait_interruptible(process: subprocess.Popen[bytes]) -> int:
    """Wait for ``process``; Ctrl-C or SIGTERM stops it (status 130)."""

    def stop(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt  # SIGTERM as Ctrl-C: stop the viewer, clean up, exit

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        return process.wait()
    except KeyboardInterrupt:
        _stop(process)  # a session of its own: the Ctrl-C or SIGTERM reached only us
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def _stop(process: subprocess.Popen[bytes]) -> None:
    """Stop a viewer started in a session of its own, with what it started (the ``rerun``
    script runs the viewer's binary as a child)."""
    for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, None)):
        with suppress(ProcessLookupError):  # gone already
            os.killpg(process.pid, sig)
        try:
            process.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue
