"""What the motor's ECU was running during a capture: its active block, before and after.

A capture's torque depends on the block the ECU runs (estimator, compensation), so a capture
without that record cannot be trusted for a fit: a capture taken under compensation shows the
residual of the old table, not the motor's ripple. The acquisition reads the ECU's active
block over UDS (DID FD01 and the block header's flags) right before the first capture and
right after the last window, and the capture's metadata carries both as ``ecu_before.*`` /
``ecu_after.*`` keys (``docs/capture-format.md``, "ECU state"):

==============================  ======  ===========================================================
key                             type    meaning
==============================  ======  ===========================================================
``ecu_before.bank``             text    ``0`` or ``1``: the active bank; ``none``: no valid bank
``ecu_before.sequence``         int     the active block's sequence (absent with ``none``)
``ecu_before.crc32``            text    the active block's CRC, 8 hex digits (absent with ``none``)
``ecu_before.flags``            text    the block's flags by name, ``COMP_ENABLE|INTERP_ENABLE``
``ecu_before.serial``           text    the ECU's serial (F18C), when it was read
==============================  ======  ===========================================================

and the same under ``ecu_after.``. A capture with neither is *untraced*.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any
from collections.abc import Mapping, Sequence

from eol_cal.errors import InputError

#: the two moments of a capture whose ECU state is recorded
WHEN = ("ecu_before", "ecu_after")
#: the fields of one ECU state in the metadata (``<when>.<field>``)
FIELDS = ("bank", "sequence", "crc32", "flags", "serial")
#: ``bank`` of an ECU without a valid block
NO_BLOCK = "none"
#: metadata types of the ECU-state keys (merged into the capture format's typed keys)
METADATA_TYPES: dict[str, type] = {f"{w}.{f}": (int if f == "sequence" else str) for w in WHEN for f in FIELDS}


@dataclass(frozen=True)
class EcuState:
    """The ECU's active block at one moment.

    Attributes
    ----------
    bank : int or None
        Active bank (0 or 1); None: no valid bank (a blank ECU runs the raw encoder angle).
    sequence : int or None
        The active block's write counter.
    crc32 : str or None
        The active block's CRC, 8 lower-case hex digits.
    flags : str or None
        The block's flags by name (``eol_cal.firmware.block.flag_names``).
    serial : str or None
        The ECU's serial (F18C); None when not read (a simulated capture).
    """

    bank: int | None
    sequence: int | None = None
    crc32: str | None = None
    flags: str | None = None
    serial: str | None = None

    @property
    def has_block(self) -> bool:
        return self.bank is not None

    def flag_set(self) -> set[str]:
        """The flag names as a set (empty without a block)."""
        return set(self.flags.split("|")) if self.flags else set()

    def estimator_options(self) -> int | None:
        """The estimator option bits (contract flags bits 2-5) the ECU ran with this block; None
        without a block (the raw encoder angle, no estimator)."""
        from eol_cal.firmware.contract import FLAGS
        from eol_cal.firmware.options import honoured_options

        if not self.has_block:
            return None
        bits = sum(1 << FLAGS[name].bit for name in self.flag_set() if name in FLAGS)
        return honoured_options(bits)

    def same_block(self, other: EcuState) -> bool:
        """The same active block (bank, sequence, CRC and flags; the serial is not compared)."""
        return (self.bank, self.sequence, self.crc32, self.flags) == (other.bank, other.sequence, other.crc32,
                                                                      other.flags)

    def describe(self) -> str:
        """One line: ``bank 1, sequence 2, CRC 1a2b3c4d, flags COMP_ENABLE|INTERP_ENABLE``."""
        if not self.has_block:
            return "no valid block"
        return f"bank {self.bank}, sequence {self.sequence}, CRC {self.crc32}, flags {self.flags}"

    def to_dict(self) -> dict[str, Any]:
        """JSON form (records, ``--json``): every field, ``bank`` null without a block."""
        return {"bank": self.bank, "sequence": self.sequence, "crc32": self.crc32, "flags": self.flags,
                "serial": self.serial}

    def to_metadata(self, when: str) -> dict[str, str | int]:
        """The metadata keys of this state under ``when`` (``ecu_before`` or ``ecu_after``)."""
        if when not in WHEN:
            raise ValueError(f"unknown ECU-state key {when!r}")
        items: dict[str, str | int] = {f"{when}.bank": NO_BLOCK if self.bank is None else str(self.bank)}
        if self.has_block:
            items.update({f"{when}.sequence": int(self.sequence or 0), f"{when}.crc32": str(self.crc32),
                          f"{when}.flags": str(self.flags)})
        if self.serial is not None:
            items[f"{when}.serial"] = self.serial
        return items


def with_ecu_state(metadata: Mapping[str, Any], before: EcuState, after: EcuState) -> dict[str, Any]:
    """``metadata`` with both ECU states in it (any earlier ECU-state keys replaced)."""
    out = {k: v for k, v in metadata.items() if k.split(".", 1)[0] not in WHEN}
    out.update(before.to_metadata("ecu_before"))
    out.update(after.to_metadata("ecu_after"))
    return out


def ecu_state(metadata: Mapping[str, Any], when: str, file: str | None = None) -> EcuState | None:
    """The ECU state recorded under ``when``, or None when the capture has no record of it.

    Raises
    ------
    InputError
        A partial or malformed record (a bank that is not 0, 1 or ``none``; a block without its
        sequence, CRC or flags).
    """
    keys = {f: metadata.get(f"{when}.{f}") for f in FIELDS}
    if all(v is None for v in keys.values()):
        return None
    bank_text = keys["bank"]
    if bank_text is None:
        raise InputError(file, f"{when}.bank", "missing: the ECU-state record needs its bank (0, 1 or none)")
    serial = None if keys["serial"] is None else str(keys["serial"])
    bank_text = str(bank_text).strip()
    if bank_text == NO_BLOCK:
        return EcuState(None, serial=serial)
    if bank_text not in ("0", "1"):
        raise InputError(file, f"{when}.bank", f"{bank_text!r}: must be 0, 1 or {NO_BLOCK}")
    for f in ("sequence", "crc32", "flags"):
        if keys[f] is None:
            raise InputError(file, f"{when}.{f}", f"missing: bank {bank_text} is recorded, its {f} is not")
    if not isinstance(keys["sequence"], int):
        raise InputError(file, f"{when}.sequence", f"must be an integer, got {keys['sequence']!r}")
    crc = str(keys["crc32"]).strip().lower()
    if len(crc) != 8 or any(ch not in "0123456789abcdef" for ch in crc):
        raise InputError(file, f"{when}.crc32", f"{keys['crc32']!r}: must be 8 hex digits")
    return EcuState(int(bank_text), int(keys["sequence"]), crc, str(keys["flags"]).strip(), serial)


@dataclass(frozen=True)
class Trace:
    """A capture's ECU states (None: not recorded)."""

    before: EcuState | None
    after: EcuState | None

    @property
    def traced(self) -> bool:
        return self.before is not None and self.after is not None

    def to_dict(self) -> dict[str, Any]:
        return {w: (None if s is None else s.to_dict()) for w, s in zip(WHEN, (self.before, self.after), strict=True)}

    def describe(self) -> str:
        """One line for a report: what the ECU ran, or that it is not recorded."""
        before, after = self.before, self.after
        if before is None or after is None:  # not traced
            return "no record of the ECU state"
        if before.same_block(after):
            return f"ECU: {before.describe()}"
        return f"ECU changed: before {before.describe()}; after {after.describe()}"


def trace_of(metadata: Mapping[str, Any], file: str | None = None) -> Trace:
    """Both ECU states of a capture's metadata (see :func:`ecu_state`); a record of only one of
    the two is refused (capture format, "ECU state"), whichever command reads the file."""
    trace = Trace(ecu_state(metadata, "ecu_before", file), ecu_state(metadata, "ecu_after", file))
    if (trace.before is None) != (trace.after is None):
        missing = "ecu_before" if trace.before is None else "ecu_after"
        raise InputError(file, missing, "the ECU state is recorded only at one end of the capture")
    return trace


def compensated(state: EcuState) -> bool:
    """The block's flags switch the compensation on."""
    from eol_cal.firmware.block import FLAG_COMP_ENABLE, flag_names

    return flag_names(FLAG_COMP_ENABLE) in state.flag_set()


def check_trace(trace: Trace, file: str | None, *, allow_untraced: bool = False,
                allow_compensated: bool = False, serial: str | None = None) -> list[str]:
    """Refuse a capture whose ECU record does not allow a fit of the motor's own ripple.

    Always refused: the ECU's active block changed during the acquisition (before != after),
    only one of the two states was recorded, or the ECU reported another serial (F18C) than the
    capture's ``serial`` (the dyno ran one motor under another motor's ECU and block). Refused
    unless allowed: no record at all (``allow_untraced``), and a capture taken under
    compensation (``allow_compensated``).

    Returns
    -------
    list of str
        The allowed problems, one line each (for a warning).

    Raises
    ------
    InputError
        The first refusal, naming ``file`` and the metadata key.
    """
    if trace.before is None and trace.after is None:
        problem = InputError(file, "ecu_before", "no record of the ECU state during the capture (untraced): "
                                                 "which block the ECU ran is unknown")
        if not allow_untraced:
            raise problem
        return [str(problem)]
    if trace.before is None or trace.after is None:
        missing = "ecu_before" if trace.before is None else "ecu_after"
        raise InputError(file, missing, "the ECU state is recorded only at one end of the capture")
    ecu_serial = trace.before.serial or trace.after.serial
    if serial and ecu_serial and ecu_serial != serial:
        raise InputError(file, "ecu_before.serial", f"the ECU reported serial {ecu_serial} (F18C), the capture is of "
                                                    f"{serial}: it ran another motor's block")
    if not trace.before.same_block(trace.after):
        raise InputError(file, "ecu_after", f"the ECU's active block changed during the acquisition (before: "
                                            f"{trace.before.describe()}; after: {trace.after.describe()})")
    if compensated(trace.before):
        problem = InputError(file, "ecu_before.flags", f"taken under compensation ({trace.before.describe()}): the "
                                                       "capture shows the old table's residual, not the motor's ripple")
        if not allow_compensated:
            raise problem
        return [str(problem)]
    return []


def recorded_options(files: Sequence[str], traces: Sequence[Trace]) -> dict[str, int]:
    """The estimator option bits (contract flags bits 2-5) each capture's ECU ran, by file: the
    captures whose ``ecu_before`` records a block (the others ran no estimator or are untraced)."""
    # estimator_options is None exactly when the state records no block
    return {f: options for f, t in zip(files, traces, strict=True)
            if t.before is not None and (options := t.before.estimator_options()) is not None}


def common_options(recorded: Mapping[str, int]) -> int | None:
    """The one set of option bits the captures ran (None: none recorded a block).

    Raises
    ------
    InputError
        The captures ran different options: they cannot share one firmware frame (names one
        file of each set and the metadata key).
    """
    from eol_cal.firmware.options import options_label

    found = set(recorded.values())
    if len(found) > 1:
        first = {options_label(r): f for f, r in recorded.items()}
        raise InputError(", ".join(first.values()), "ecu_before.flags",
                         f"the captures ran different estimator options ({', '.join(sorted(first))}): "
                         "they cannot share one firmware frame")
    return found.pop() if found else None
