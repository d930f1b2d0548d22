"""python-can, imported without its MF4 log format.

Importing python-can imports asammdf for its MF4 logger, and with it pandas: most of a second
(several under load) that an ``eol-cal run`` paid before its pre-flight could open the bus.
eol-cal never logs CAN traffic to MF4; its captures use asammdf directly
(:mod:`eol_cal.capture.mdf4_io`), which the station cycle imports on its helper thread while the
dyno turns. Only the first import of python-can in a process decides: the station's commands
call :func:`import_can` before anything else imports it.
"""

from __future__ import annotations

import sys
from types import ModuleType


def import_can() -> ModuleType:
    """python-can with its MF4 reader and writer left unavailable (the rest as usual); when it is
    already imported, that module as it is."""
    if "can" in sys.modules:
        return sys.modules["can"]
    masked = "asammdf" not in sys.modules
    if masked:
        sys.modules["asammdf"] = None  # type: ignore[assignment]  # "import asammdf" fails: python-can skips MF4
    try:
        import can
    finally:
        if masked and sys.modules.get("asammdf", "") is None:
            del sys.modules["asammdf"]
    return can
