"""Timing a process against another one's death, for the kill tests."""

from __future__ import annotations

import subprocess
import threading
import time


def ends_after(first: subprocess.Popen, then: subprocess.Popen, timeout: float) -> tuple[float, str]:
    """Seconds from ``first``'s exit (the ECU killed at a step) to ``then``'s (the command talking to
    it), and ``then``'s stderr; ``then``'s pipes are read meanwhile.

    Timed from the death, not from the command's start: process start and imports are several
    seconds on a loaded machine and are not what a dead-link bound is about.
    """
    ended: dict[str, object] = {}

    def reader() -> None:
        ended["err"] = then.communicate(timeout=timeout)[1]
        ended["at"] = time.monotonic()

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    first.wait(timeout)
    died = time.monotonic()
    thread.join(timeout)
    assert "at" in ended, f"{then.args[:4]} did not end within {timeout} s"
    return max(0.0, float(ended["at"]) - died), str(ended["err"])
