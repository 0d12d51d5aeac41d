"""A minimal headless-Chromium driver over the Chrome DevTools Protocol (no Selenium or
Playwright: just the browser binary and the `websockets` client viser already needs)."""

from __future__ import annotations

import base64
import io
import itertools
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
INSTALL_HINT = "install it with: sudo apt-get install -y chromium (Debian/Ubuntu)"


def find_chromium() -> str | None:
    env = os.environ.get("FLAMENERF_CHROMIUM")
    if env:
        return shutil.which(env)
    for name in CHROMIUM_NAMES:
        p = shutil.which(name)
        if p:
            return p
    return None


class CDPError(RuntimeError):
    pass


class Browser:
    """One headless Chromium with one page; `with Browser(...) as b: b.goto(url)`."""

    def __init__(self, executable: str, width: int = 1200, height: int = 800,
                 timeout: float = 30.0):
        self.profile = tempfile.mkdtemp(prefix="flamenerf-chromium-")
        args = [
            executable, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--no-default-browser-check", "--disable-extensions",
            "--mute-audio", "--hide-scrollbars",
            # WebGL (three.js) on the CPU: SwiftShader must be allowed explicitly.
            "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            f"--user-data-dir={self.profile}", f"--window-size={width},{height}",
            "--remote-debugging-port=0", "--remote-debugging-address=127.0.0.1",
            "about:blank",
        ]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True)
        self._ids = itertools.count(1)
        self.events: list[dict] = []
        try:
            port = self._devtools_port(timeout)
            self.ws = self._connect_page(port, timeout)
        except BaseException:
            self.close()
            raise
        self.call("Page.enable")
        self.call("Runtime.enable")

    def _devtools_port(self, timeout: float) -> int:
        end = time.monotonic() + timeout
        lines = []
        while time.monotonic() < end:
            line = self.proc.stderr.readline()
            if not line:
                if self.proc.poll() is not None:
                    break
                continue
            lines.append(line)
            m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if m:
                self.log = lines
                threading.Thread(target=self._drain, daemon=True).start()
                return int(m.group(1))
        raise CDPError("chromium did not start: " + "".join(lines[-20:]))

    def _drain(self) -> None:
        for line in self.proc.stderr:  # keep the pipe from filling up
            self.log.append(line)
            del self.log[:-200]

    def _connect_page(self, port: int, timeout: float):
        from websockets.sync.client import connect

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                targets = json.loads(r.read())
            pages = [t for t in targets if t.get("type") == "page"]
            if pages:
                return connect(pages[0]["webSocketDebuggerUrl"], max_size=64 * 2**20,
                               open_timeout=timeout)
            time.sleep(0.1)
        raise CDPError("chromium opened no page")

    # -------------------------------------------------------------------- protocol

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise CDPError(f"{method}: no reply in {timeout} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == i:
                if "error" in msg:
                    raise CDPError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self.events.append(msg)

    def eval(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                      awaitPromise=True)
        if "exceptionDetails" in r:
            raise CDPError(f"JS error: {r['exceptionDetails']}")
        return r.get("result", {}).get("value")

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def wait_for(self, expression: str, timeout: float = 30.0, interval: float = 0.1):
        """Poll a JS expression until it is truthy; returns its value."""
        end = time.monotonic() + timeout
        last = None
        while time.monotonic() < end:
            last = self.eval(expression)
            if last:
                return last
            time.sleep(interval)
        raise CDPError(f"timed out after {timeout} s waiting for: {expression} "
                       f"(last value {last!r})")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of the viewport."""
        from PIL import Image

        r = self.call("Page.captureScreenshot", format="png")
        img = Image.open(io.BytesIO(base64.b64decode(r["data"]))).convert("RGB")
        return np.asarray(img)

    def click(self, x: float, y: float) -> None:
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left",
                      clickCount=1 if kind != "mouseMoved" else 0)

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 8) -> None:
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0, y=y0)
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0,
                  button="left", clickCount=1)
        for k in range(1, steps + 1):
            t = k / steps
            self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0 + t * (x1 - x0),
                      y=y0 + t * (y1 - y0), button="left", buttons=1)
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x1, y=y1,
                  button="left", clickCount=1)

    def close(self) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                self.ws.close()
        except Exception:  # noqa: BLE001
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> "Browser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
