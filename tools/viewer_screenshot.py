"""Screenshot a recording in Rerun's web viewer, as a user sees it, without a display.

    python tools/viewer_screenshot.py RECORDING OUT.png [--wait 25] [--size 1600x1000]
    python tools/viewer_screenshot.py PROTOCOL.yaml OUT.png --wait 20 [--shots 3]

Serves RECORDING (.rrd or .mcap) with ``magrun view --web``, opens it in headless Chromium
with a software renderer (SwiftShader: no GPU needed) and saves the page as a PNG. Given a
protocol instead, runs ``magrun run PROTOCOL --quick --web`` into a temporary folder and
screenshots the live view while it runs: ``--shots N`` saves N pictures ``--wait`` s apart
(OUT-1.png, OUT-2.png, …). What it
needs besides magrun: Chromium (Debian: ``apt-get install chromium``, at /usr/bin/chromium,
or ``--chromium PATH``) and Playwright's Python package (``pip install -e ".[viewshot]"``;
its own browser download is not used). Check the views by eye with it after changing what
the recorder logs or the blueprint; ``docs/img/rerun-view.png`` is made with it.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHROMIUM_FLAGS = [
    "--no-sandbox", "--no-first-run", "--disable-quic", "--disable-background-networking",
    "--disable-component-update", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
]  # fmt: skip


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--wait", type=float, default=25.0, help="seconds to let it render")
    parser.add_argument("--size", default="1600x1000", help="viewport, px (WxH)")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--shots", type=int, default=1, help="with a protocol: pictures taken")
    args = parser.parse_args()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sys.exit('Playwright is missing: pip install -e ".[viewshot]"')
    if not Path(args.chromium).exists():
        sys.exit(f"no Chromium at {args.chromium} (Debian: apt-get install chromium)")
    width, height = (int(v) for v in args.size.split("x"))
    port = _free_port()
    live = args.recording.suffix.lower() in (".yaml", ".yml")
    tmp = tempfile.TemporaryDirectory(prefix="viewshot-")
    command = (
        ["run", str(args.recording), "--quick", "--out", tmp.name] if live
        else ["view", str(args.recording)]
    )  # fmt: skip
    viewer = subprocess.Popen(
        [sys.executable, "-m", "magrun.cli", *command, "--web", "--web-port", str(port)],
        stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        url = None
        assert viewer.stderr is not None
        for line in viewer.stderr:
            match = re.search(r"(http://127\.0\.0\.1:\d+/\S+)", line)
            if match:
                url = match.group(1)
                break
        if url is None:
            sys.exit(f"magrun view did not serve {args.recording}")
        time.sleep(2)  # the HTTP server starts just after the address is printed
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            shots = max(args.shots, 1) if live else 1
            for i in range(1, shots + 1):
                time.sleep(args.wait)
                out = args.out if shots == 1 else args.out.with_stem(f"{args.out.stem}-{i}")
                page.screenshot(path=str(out))
                print(f"wrote {out}")
            browser.close()
    finally:
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(timeout=60)
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
