"""Screenshots of a recording in the Rerun web viewer, taken by headless Chromium.

``python -m windowvo.viz.webshot RECORDING.rrd OUT_DIR [--theme light dark] [--size 1920x1080]``
writes ``OUT_DIR/viewer_<theme>.png`` and prints one line per screenshot.

Everything runs in a private network namespace (``unshare -n``, needs root or user namespaces): the
viewer's asset server (rerun-sdk's ``serve_web_viewer``, which listens on all interfaces), a file
server for the recording on 127.0.0.1, and Chromium, driven over ``--remote-debugging-pipe`` (no
debugging port). Nothing is reachable from outside the namespace and nothing inside reaches out.

The screenshot is taken once the page stops changing (two identical captures in a row), or after
``--timeout`` seconds.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import fcntl
import functools
import http.server
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from ..errors import WindowVOError, cli_error

SETTLED_FRACTION = 0.002  # the page counts as drawn when fewer pixels than this change in 1 s
VIEWER_PORT = 9090  # inside the private namespace only
FILE_PORT = 9091
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


class WebshotError(WindowVOError):
    """The screenshot could not be taken (no Chromium, no namespace, viewer did not load)."""


def find_chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def namespace_problem() -> str | None:
    """Why a private network namespace cannot be made here, or None when it can."""
    if shutil.which("unshare") is None:
        return "the `unshare` tool (util-linux) is not installed"
    try:
        r = subprocess.run(["unshare", "-n", "true"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"`unshare -n` failed: {err}"
    if r.returncode != 0:
        return f"`unshare -n` failed (needs root or user namespaces): {r.stderr.strip()[:200]}"
    return None


def _loopback_up() -> None:
    """Bring up ``lo`` in a fresh network namespace (ioctl, no iproute2 needed)."""
    siocgifflags, siocsifflags, iff_up = 0x8913, 0x8914, 0x1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        req = struct.pack("16sH", b"lo", 0)
        flags = struct.unpack("16sH", fcntl.ioctl(s, siocgifflags, req)[:18])[1]
        fcntl.ioctl(s, siocsifflags, struct.pack("16sH", b"lo", flags | iff_up))


class _CorsHandler(http.server.SimpleHTTPRequestHandler):
    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, format, *args) -> None:
        pass


class _Cdp:
    """A minimal Chrome DevTools Protocol client over Chromium's --remote-debugging-pipe (fds 3 and 4)."""

    def __init__(self, chromium: str, args: list[str]):
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()
        # Chromium reads commands on fd 3 and answers on fd 4: move the child's ends above 4 first so
        # that putting them in place cannot overwrite one with the other.
        child_r = fcntl.fcntl(to_chrome_r, fcntl.F_DUPFD, 10)
        child_w = fcntl.fcntl(from_chrome_w, fcntl.F_DUPFD, 10)
        for fd in (to_chrome_r, from_chrome_w):
            os.close(fd)

        def child_fds() -> None:
            os.dup2(child_r, 3)
            os.dup2(child_w, 4)

        self.proc = subprocess.Popen([chromium, "--remote-debugging-pipe", *args], pass_fds=(3, 4),
                                     preexec_fn=child_fds, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(child_r)
        os.close(child_w)
        self._next = 0
        self._replies: dict[int, dict] = {}
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        buf = b""
        while True:
            chunk = os.read(self._from_chrome, 1 << 20)
            if not chunk:
                break
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                if "id" in msg:
                    with self._cond:
                        self._replies[msg["id"]] = msg
                        self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0) -> dict:
        self._next += 1
        mid = self._next
        msg: dict = {"id": mid, "method": method, "params": params or {}}
        if session is not None:
            msg["sessionId"] = session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        with self._cond:
            while mid not in self._replies:
                left = deadline - time.monotonic()
                if left <= 0 or not self._reader.is_alive():
                    raise WebshotError(f"Chromium did not answer {method}")
                self._cond.wait(left)
            reply = self._replies.pop(mid)
        if "error" in reply:
            raise WebshotError(f"Chromium: {method}: {reply['error'].get('message')}")
        return reply.get("result", {})

    def close(self) -> None:
        with contextlib.suppress(WebshotError):
            self.call("Browser.close", timeout=10)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_chrome)


def _shoot_inside(rrd: Path, out_dir: Path, themes: list[str], size: tuple[int, int], timeout_s: float,
                  min_wait_s: float, settled_fraction: float = SETTLED_FRACTION, debug: bool = False) -> list[Path]:
    """Runs inside the private namespace: servers, Chromium, screenshots."""
    import rerun as rr

    _loopback_up()
    chromium = find_chromium()
    if chromium is None:
        raise WebshotError("Chromium is not installed")
    rr.serve_web_viewer(web_port=VIEWER_PORT, open_browser=False)
    files = http.server.ThreadingHTTPServer(("127.0.0.1", FILE_PORT),
                                            functools.partial(_CorsHandler, directory=str(rrd.parent)))
    threading.Thread(target=files.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{VIEWER_PORT}/?url=http://127.0.0.1:{FILE_PORT}/{rrd.name}"
    w, h = size
    # Software WebGL (SwiftShader): no GPU here.
    cdp = _Cdp(chromium, ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                          "--no-first-run", "--no-default-browser-check", "--hide-scrollbars", "--mute-audio",
                          f"--window-size={w},{h}", f"--user-data-dir={out_dir / '.chromium-profile'}"])
    out: list[Path] = []
    try:
        # One page: load the recording once, then switch the colour scheme between captures.
        target = cdp.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        cdp.call("Emulation.setDeviceMetricsOverride",
                 {"width": w, "height": h, "deviceScaleFactor": 1, "mobile": False}, session)
        cdp.call("Page.enable", session=session)
        for i, theme in enumerate(themes):
            cdp.call("Emulation.setEmulatedMedia",
                     {"features": [{"name": "prefers-color-scheme", "value": theme}]}, session)
            t0 = time.monotonic()
            if i == 0:
                cdp.call("Page.navigate", {"url": url}, session)
            time.sleep(min_wait_s if i == 0 else 2.0)
            previous: np.ndarray | None = None
            png = b""
            while True:
                png = base64.b64decode(cdp.call("Page.captureScreenshot", {"format": "png"}, session)["data"])
                img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise WebshotError("Chromium returned an unreadable screenshot")
                changed = 1.0 if previous is None or previous.shape != img.shape else float(
                    np.mean(np.any(img != previous, axis=2)))
                if debug:
                    print(f"{theme} {time.monotonic() - t0:.1f} s: {100 * changed:.3f}% of pixels changed", flush=True)
                if changed < settled_fraction or time.monotonic() - t0 > timeout_s:
                    break
                previous = img
                time.sleep(1.0)
            path = out_dir / f"viewer_{theme}.png"
            path.write_bytes(png)
            print(f"{path} after {time.monotonic() - t0:.1f} s", flush=True)
            out.append(path)
    finally:
        cdp.close()
        files.shutdown()
    return out


def screenshot(rrd: Path, out_dir: Path, themes: tuple[str, ...] = ("light", "dark"), size: tuple[int, int] = (1920, 1080),
               timeout_s: float = 60.0, min_wait_s: float = 5.0) -> list[Path]:
    """Screenshots of ``rrd`` in the Rerun web viewer, one per theme, taken in a private network namespace."""
    rrd = Path(rrd).resolve()
    if not rrd.is_file():
        raise WebshotError(f"no recording at {rrd}")
    if find_chromium() is None:
        raise WebshotError("Chromium is not installed (Debian: apt-get install chromium)")
    problem = namespace_problem()
    if problem is not None:
        raise WebshotError(problem)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    cmd = ["unshare", "-n", sys.executable, "-m", "windowvo.viz.webshot", "--inside", str(rrd), str(out_dir),
           "--theme", *themes, "--size", f"{size[0]}x{size[1]}", "--timeout", str(timeout_s),
           "--min-wait", str(min_wait_s)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s * len(themes) + 120)
    except subprocess.TimeoutExpired:
        raise WebshotError("the screenshot run timed out") from None
    if r.returncode != 0:
        raise WebshotError(f"screenshot run failed: {(r.stderr or r.stdout).strip()[-800:]}")
    return [out_dir / f"viewer_{t}.png" for t in themes]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.viz.webshot", description=__doc__.splitlines()[0])
    p.add_argument("rrd", type=Path)
    p.add_argument("out_dir", type=Path)
    p.add_argument("--theme", nargs="+", default=["light", "dark"], choices=["light", "dark"])
    p.add_argument("--size", default="1920x1080")
    p.add_argument("--timeout", type=float, default=60.0)
    p.add_argument("--min-wait", type=float, default=5.0)
    p.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--debug", action="store_true", help="print how much of the page changed between captures")
    a = p.parse_args(argv)
    try:
        w, h = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        return cli_error(f"--size must be WIDTHxHEIGHT, got {a.size!r}")
    try:
        if a.inside:
            _shoot_inside(a.rrd.resolve(), a.out_dir.resolve(), a.theme, (w, h), a.timeout, a.min_wait, debug=a.debug)
        else:
            for path in screenshot(a.rrd, a.out_dir, tuple(a.theme), (w, h), a.timeout, a.min_wait):
                print(path)
    except WindowVOError as err:
        return cli_error(err)
    return 0


if __name__ == "__main__":
    sys.exit(main())
