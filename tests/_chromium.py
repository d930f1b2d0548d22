"""Headless Chromium for the page tests, driven by Playwright for Python.

The browser is the distribution's ``chromium`` (Debian's package, which scripts/test installs),
given to Playwright as its executable: no browser is downloaded (``playwright install`` is never
run; scripts/test sets ``PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD``). Each :class:`Chromium` context is
one browser with one offline page (``file://`` loads, the network does not); it records what the
tests assert on: console errors (the console API, uncaught exceptions and the browser's own log
errors such as a resource that failed to load) and every request's URL. On exit the browser is
closed and every process it started (the renderer and GPU helpers included, found by a marker in
their environment) must be gone: :attr:`Chromium.left_behind` lists any that is not.
"""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from playwright.sync_api import Browser, Page, Playwright, expect, sync_playwright

#: environment variable that marks every process of one test browser (inherited by its helpers)
MARKER = "EOL_CAL_TEST_BROWSER"

#: a hang guard, not a speed test: an assertion on the page waits this long (Playwright's 5 s
#: default is short for a browser on 2 cores at load 8)
TIMEOUT_S = 30.0
expect.set_options(timeout=TIMEOUT_S * 1000)
#: a hang guard for starting the browser, whatever the page's: at load 18 on 2 cores (fourteen busy
#: loops beside the suite) a launch took more than 30 s and failed a lot page test (2026-12-02)
LAUNCH_TIMEOUT_S = 180.0


def chromium_path() -> str | None:
    """The Chromium binary (``chromium`` or ``chromium-browser`` on the PATH), or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


@dataclass
class PageLog:
    """What a page did while it loaded."""

    console_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)


def marked_processes(marker: str) -> list[int]:
    """Pids of the running processes whose environment holds ``MARKER=marker`` (zombies aside)."""
    needle = f"{MARKER}={marker}".encode()
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if needle in (proc / "environ").read_bytes().split(b"\0") and " Z " not in (proc / "stat").read_text():
                found.append(int(proc.name))
        except OSError:  # ended meanwhile, or not ours
            continue
    return found


class Chromium:
    """``with Chromium() as b: log = b.open(url); b.page.locator(...)``; see the module doc."""

    def __init__(self, width: int = 1200, height: int = 900, timeout_s: float = TIMEOUT_S, offline: bool = True) -> None:
        self.width, self.height, self.timeout_ms = width, height, timeout_s * 1000
        self.offline = offline  # False: a page served on 127.0.0.1 (the operator panel)
        self.marker = uuid.uuid4().hex
        self.left_behind: list[int] = []
        self._pw: Playwright | None = None
        self._browser: Browser | None = None
        self._log = PageLog()

    def __enter__(self) -> Chromium:
        exe = chromium_path()
        if exe is None:
            raise RuntimeError("chromium not found (Debian: apt-get install -y chromium)")
        self._pw = sync_playwright().start()
        try:
            self._browser = self._pw.chromium.launch(
                executable_path=exe, headless=True, timeout=max(self.timeout_ms, LAUNCH_TIMEOUT_S * 1000),
                args=["--disable-gpu", "--no-sandbox", "--disable-dev-shm-usage"],
                env={**os.environ, MARKER: self.marker})
            context = self._browser.new_context(offline=self.offline, viewport={"width": self.width, "height": self.height})
            context.set_default_timeout(self.timeout_ms)
            self.page: Page = context.new_page()
        except BaseException:
            self.close()
            raise
        self.page.on("console", lambda m: self._log.console_errors.append(m.text) if m.type in ("error", "assert") else None)
        self.page.on("pageerror", lambda e: self._log.console_errors.append(str(e)))
        self.page.on("request", lambda r: self._log.requests.append(r.url))
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the browser and Playwright; wait (10 s) for every marked process to end."""
        if self._browser is not None:
            self._browser.close()
            self._browser = None
        if self._pw is not None:
            self._pw.stop()
            self._pw = None
        end = time.monotonic() + 10
        while (left := marked_processes(self.marker)) and time.monotonic() < end:
            time.sleep(0.05)
        self.left_behind = left

    def open(self, url: str, settle_s: float = 0.3) -> PageLog:
        """Load ``url`` (offline) and let its scripts run; its console errors and requests."""
        self._log = PageLog()
        self.page.goto(url, wait_until="load")
        self.page.wait_for_timeout(settle_s * 1000)
        return self._log

    def screenshot(self, path: Path) -> Path:
        """The whole page (beyond the window) as PNG."""
        self.page.screenshot(path=str(path), full_page=True)
        return path

    def pdf(self) -> bytes:
        """The page printed as the browser prints it (CSS @page size and @media print)."""
        return self.page.pdf(prefer_css_page_size=True, print_background=True)


def pdf_pages(pdf: bytes) -> int:
    """Pages of a PDF as Chromium writes it (its page objects are ``/Type /Page``)."""
    return len(re.findall(rb"/Type\s*/Page(?!s)", pdf))


def not_blank(png: Path) -> tuple[int, float]:
    """Distinct colours and grey-level standard deviation of a screenshot."""
    import numpy as np
    from PIL import Image

    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB"))
    colours = len(np.unique(rgb.reshape(-1, 3)[::7], axis=0))
    return colours, float(rgb.mean(axis=2).std())


def element_sizes(page: Page, selector: str) -> list[dict[str, Any]]:
    """``{id, w, h}`` of every element matching ``selector``: its id (or its nearest ancestor's)
    and its rendered size (px)."""
    out = []
    for element in page.locator(selector).all():
        box = element.bounding_box() or {"width": 0.0, "height": 0.0}
        ident = element.evaluate("e => e.id || (e.closest('[id]') || {}).id || ''")
        out.append({"id": ident, "w": box["width"], "h": box["height"]})
    return out
