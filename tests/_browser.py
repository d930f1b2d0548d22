"""Headless Chromium (the distribution's ``chromium``) driven over the DevTools protocol.

One browser per :class:`Browser` context: started in its own process group with a private
profile directory, the DevTools endpoint bound to 127.0.0.1 on a port the browser picks, the
page's network switched off; on exit the whole process group is ended and waited for (no
process is left). :meth:`Browser.open` loads a page and records what the tests assert on:
console errors, uncaught exceptions, log errors, and the URL of every request.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import websocket


def chromium_path() -> str | None:
    """The Chromium binary (``chromium`` or ``chromium-browser`` on the PATH), or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


@dataclass
class PageLog:
    """What a page did while it loaded."""

    console_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)


class Browser:
    """``with Browser() as b: log = b.open(url)``; see the module doc."""

    def __init__(self, width: int = 1200, height: int = 900, timeout_s: float = 20.0) -> None:
        self.width, self.height, self.timeout_s = width, height, timeout_s
        self.proc: subprocess.Popen | None = None
        self.ws: websocket.WebSocket | None = None
        self._id = 0
        self._events: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ lifetime
    def __enter__(self) -> Browser:
        exe = chromium_path()
        if exe is None:
            raise RuntimeError("chromium not found (Debian: apt-get install -y chromium)")
        self.profile = Path(tempfile.mkdtemp(prefix="eol-cal-chromium-"))
        self.proc = subprocess.Popen(
            [exe, "--headless", "--disable-gpu", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
             "--no-default-browser-check",
             "--disable-extensions", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile}", f"--window-size={self.width},{self.height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port = self._port()
            self.ws = websocket.create_connection(self._page_ws(port), timeout=self.timeout_s,
                                                  suppress_origin=True)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End the browser's process group and wait for it; remove the profile directory."""
        if self.ws is not None:
            with contextlib.suppress(Exception):  # the browser goes next anyway
                self.ws.close()
            self.ws = None
        if self.proc is not None:
            pgid = self.proc.pid  # start_new_session: the group id is the browser's pid
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(pgid, signal.SIGKILL)
                self.proc.wait(timeout=10)
            # the renderer and GPU helpers are in the same group: wait until none is left
            end = time.monotonic() + 10
            while time.monotonic() < end and group_alive(pgid):
                time.sleep(0.05)
            if group_alive(pgid):
                os.killpg(pgid, signal.SIGKILL)
            self.pgid = pgid
            self.proc = None
        shutil.rmtree(getattr(self, "profile", ""), ignore_errors=True)

    def _port(self) -> int:
        marker = self.profile / "DevToolsActivePort"
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited with code {self.proc.returncode}")
            if marker.exists():
                lines = marker.read_text().split()
                if lines:
                    return int(lines[0])
            time.sleep(0.05)
        raise TimeoutError("chromium did not open its DevTools port")

    def _page_ws(self, port: int) -> str:
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
            time.sleep(0.05)
        raise TimeoutError("chromium has no page target")

    # ------------------------------------------------------------------ protocol
    def send(self, method: str, **params: Any) -> dict[str, Any]:
        """Call a DevTools method and return its result (events meanwhile are kept)."""
        self._id += 1
        my_id = self._id
        self.ws.send(json.dumps({"id": my_id, "method": method, "params": params}))
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == my_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self._events.append(msg)
        raise TimeoutError(method)

    def _wait_event(self, method: str) -> dict[str, Any]:
        for i, e in enumerate(self._events):
            if e["method"] == method:
                return self._events.pop(i)
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            msg = json.loads(self.ws.recv())
            if msg.get("method") == method:
                return msg
            if "method" in msg:
                self._events.append(msg)
        raise TimeoutError(method)

    # ------------------------------------------------------------------ what the tests use
    def open(self, url: str, settle_s: float = 0.3) -> PageLog:
        """Load ``url`` with the network off; returns its console errors and requests."""
        self._events.clear()
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.send(f"{domain}.enable")
        self.send("Network.emulateNetworkConditions", offline=True, latency=0, downloadThroughput=-1,
                  uploadThroughput=-1)
        self.send("Page.navigate", url=url)
        self._wait_event("Page.loadEventFired")
        time.sleep(settle_s)
        self.send("Runtime.evaluate", expression="1")  # drain the events that came meanwhile
        log = PageLog()
        for e in self._events:
            p = e.get("params", {})
            if e["method"] == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                log.console_errors.append(" ".join(str(a.get("value", a.get("description"))) for a in p.get("args", [])))
            elif e["method"] == "Runtime.exceptionThrown":
                log.console_errors.append(str(p.get("exceptionDetails", {}).get("exception", {}).get("description")))
            elif e["method"] == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                log.console_errors.append(p["entry"].get("text", ""))
            elif e["method"] == "Network.requestWillBeSent":
                log.requests.append(p["request"]["url"])
        return log

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression on the page (JSON-serialisable)."""
        res = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in res:
            raise RuntimeError(f"{expression}: {res['exceptionDetails']}")
        return res["result"].get("value")

    def screenshot(self, path: Path) -> Path:
        """The whole page (beyond the window) as PNG."""
        size = self.evaluate("[document.documentElement.scrollWidth, document.documentElement.scrollHeight]")
        res = self.send("Page.captureScreenshot", format="png", captureBeyondViewport=True,
                        clip={"x": 0, "y": 0, "width": size[0], "height": size[1], "scale": 1})
        path.write_bytes(base64.b64decode(res["data"]))
        return path

    def pdf(self) -> bytes:
        """The page printed as the browser prints it (CSS @page size and @media print)."""
        res = self.send("Page.printToPDF", preferCSSPageSize=True, printBackground=True)
        return base64.b64decode(res["data"])


def group_alive(pgid: int) -> bool:
    """Whether any process of the group is still running (zombies of our own children aside)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def pdf_pages(pdf: bytes) -> int:
    """Pages of a PDF as Chromium writes it (its page objects are ``/Type /Page``)."""
    import re

    return len(re.findall(rb"/Type\s*/Page(?!s)", pdf))


def not_blank(png: Path) -> tuple[int, float]:
    """Distinct colours and grey-level standard deviation of a screenshot."""
    import numpy as np
    from PIL import Image

    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB"))
    colours = len(np.unique(rgb.reshape(-1, 3)[::7], axis=0))
    return colours, float(rgb.mean(axis=2).std())


def element_sizes(browser: Browser, selector: str) -> list[dict[str, Any]]:
    """``{id, w, h}`` of every element matching ``selector`` (getBoundingClientRect)."""
    return browser.evaluate(
        f"Array.from(document.querySelectorAll({json.dumps(selector)})).map(e => {{"
        "const r = e.getBoundingClientRect(); "
        "return {id: e.id || (e.closest('[id]') || {}).id || '', w: r.width, h: r.height}; })")
