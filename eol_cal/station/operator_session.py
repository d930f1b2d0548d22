"""An operator's session on the station: scanned serials, and the tally of the motors run.

``eol-cal station`` asks for each motor's serial (a barcode scanner types it and Enter), runs
the cycle, and keeps the outcome here; at the end the tally is the session's summary.
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from eol_cal.errors import InputError

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord

#: a serial as the block's serial field carries it (1-16 ASCII characters), restricted to what a
#: label's barcode carries: letters, digits and - _ . (a scanner's stray control character or a
#: second code read into the same line is refused, not calibrated under a wrong serial)
SERIAL_RE = re.compile(r"[A-Za-z0-9._-]{1,16}")
#: longest operator name kept in a record
OPERATOR_MAX = 64


def scanned_serial(text: str) -> str:
    """The serial in a scanned line (surrounding whitespace dropped).

    Raises
    ------
    InputError
        When the line is not 1 to 16 letters, digits, ``-``, ``_`` or ``.``; the reason names
        the first character that is not allowed.
    """
    serial = text.strip()
    if SERIAL_RE.fullmatch(serial):
        return serial
    if not serial:
        why = "empty"
    elif len(serial) > 16:
        why = f"{len(serial)} characters, at most 16"
    else:
        bad = next(ch for ch in serial if not SERIAL_RE.fullmatch(ch))
        why = f"character {bad!r} not allowed"
    raise InputError(None, "serial", f"{serial!r}: {why} (letters, digits, - _ .)")


def operator_name(text: str) -> str:
    """The operator as typed (whitespace dropped); :class:`InputError` when empty, too long or not printable."""
    name = text.strip()
    if not name or len(name) > OPERATOR_MAX or not name.isprintable():
        raise InputError(None, "operator", f"{name!r}: 1 to {OPERATOR_MAX} printable characters")
    return name


def demo_seed(serial: str) -> int:
    """The simulated motor a serial stands for in the demo: its trailing digits (``DEMO-0003`` is
    ``eol-cal demo``'s third motor), else a CRC-32 of the serial; the same serial is the same motor."""
    digits = re.search(r"(\d+)$", serial)
    return int(digits.group(1)) if digits else zlib.crc32(serial.encode("ascii"))


@dataclass
class SessionTally:
    """The records of the motors run in one session, in order, and the ones interrupted."""

    records: list[RunRecord] = field(default_factory=list)
    reports: list[str | None] = field(default_factory=list)
    interrupted: list[str] = field(default_factory=list)

    def add(self, record: RunRecord, report: str | None) -> None:
        self.records.append(record)
        self.reports.append(report)

    def written(self, record: RunRecord, report: str | None) -> None:
        """A run added at its verdict, now with its report and final record (the report thread's)."""
        for k, rec in enumerate(self.records):
            if rec.run_id == record.run_id:
                self.records[k], self.reports[k] = record, report
                return
        self.add(record, report)

    def counts(self) -> dict[str, int]:
        """Runs, the motors they were (distinct serials: a re-test is a second run of one motor, the
        master's runs are one motor), and how many runs ended pass, fail and error (an interrupted
        one is an error), and how many were refused (nothing written to the ECU; counted in error
        as well)."""
        serials = {rec.serial for rec in self.records} | set(self.interrupted)
        out = {"runs": len(self.records) + len(self.interrupted), "motors": len(serials), "pass": 0, "fail": 0,
               "error": len(self.interrupted), "refused": 0}
        for rec in self.records:
            out[rec.verdict] += 1
            out["refused"] += rec.kind == "refusal"
        return out

    def summary(self) -> str:
        c = self.counts()
        text = f"{c['runs']} run(s) of {c['motors']} motor(s): {c['pass']} pass, {c['fail']} fail, {c['error']} error"
        return text + (f" ({c['refused']} of them refused before anything was written)" if c["refused"] else "")
