"""Pre-flight of the station cycle, and the traced acquisition.

The pre-flight runs before anything is written to the ECU: a typo in the dyno's address, the
wrong motor on the dyno or a wrong key must never cost the motor its calibration (the prepare
step erases nothing, but the uncompensated block it flashes supersedes the one the ECU had).
It checks, each within the existing timeouts (a dead dyno address ends within seconds):

- the dyno answers (register map version) and is ready: no latched fault, drive not tripped,
  every interlock met;
- the ECU answers (UDS: serial F18C, active block FD01 and its flags);
- the ECU's serial, the dyno's motor serial (when it reports one) and the given serial agree;
- the ECU accepts the security key (27 01/02 in the extended session: no programming session,
  nothing erased or written).

The traced acquisition (:func:`acquire_traced`) reads the ECU's active block right before the
first capture and right after the last window (alongside the dyno's ramps), and writes both into the capture's metadata
(:mod:`eol_cal.capture.ecu_state`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from eol_cal.capture.ecu_state import EcuState, Trace, with_ecu_state
from eol_cal.errors import EolCalError

if TYPE_CHECKING:
    from eol_cal.capture.model import Capture
    from eol_cal.dyno.client import DynoConfig, DynoSetpoint
    from eol_cal.ecu.client import ClientTiming, EcuCheck, SeedToKey

#: reads the ECU's state now (opens and closes its own bus)
ReadEcu = Callable[[], EcuState]


class PreflightFailed(EolCalError):
    """The pre-flight found the station not ready for this motor; nothing was written (exit 2).

    Attributes
    ----------
    reasons : list of str
        Every problem found, one line each.
    """

    def __init__(self, reasons: list[str]) -> None:
        super().__init__("; ".join(reasons))
        self.reasons = list(reasons)


class EcuStateMismatch(EolCalError):
    """The ECU did not run the block the cycle expected during an acquisition (exit 2)."""


@dataclass
class Preflight:
    """What the pre-flight found (for the record: ``preflight``)."""

    serial: str
    dyno: dict[str, Any] | None = None
    ecu: EcuCheck | None = None
    reasons: list[str] = field(default_factory=list)

    @property
    def dyno_reached(self) -> bool:
        return self.dyno is not None

    def to_dict(self) -> dict[str, Any]:
        return {"dyno": self.dyno, "ecu": None if self.ecu is None else self.ecu.to_dict(),
                "reasons": list(self.reasons)}


def check_dyno(config: DynoConfig) -> tuple[dict[str, Any] | None, list[str]]:
    """The dyno's identification and status, and why it is not ready (nothing is commanded).

    Returns ``(None, [why])`` when it does not answer: the client's timeout and retries bound the wait.
    """
    from eol_cal.dyno.client import DynoClient
    from eol_cal.dyno.registers import DriveState, Fault, Interlock

    client = DynoClient(config)
    try:
        ident = client.connect()
        st = client.status()
    except EolCalError as exc:
        return None, [f"dyno not reachable: {exc}"]
    finally:
        client.close()
    found = {"map_version": int(ident["map_version"]), "dut_serial": str(ident.get("dut_serial") or ""),
             "faults": int(st["faults"]), "interlocks": int(st["interlocks"]), "drive_state": int(st["drive_state"])}
    problems = []
    if found["faults"]:
        names = "+".join(f.name for f in Fault if f & found["faults"])
        problems.append(f"dyno {client.config.host}:{client.config.port} has latched faults {names} "
                        f"(faults=0x{found['faults']:04x}): clear them at the dyno")
    if found["drive_state"] == DriveState.TRIPPED:
        problems.append(f"dyno {client.config.host}:{client.config.port}: drive tripped")
    missing = Interlock.ALL & ~Interlock(found["interlocks"] & Interlock.ALL)
    if missing:
        problems.append(f"dyno {client.config.host}:{client.config.port}: interlocks not met: "
                        + "+".join(i.name for i in Interlock if i != Interlock.ALL and i & missing))
    return found, problems


def check_ecu(open_bus: Callable[[], Any], seed_to_key: SeedToKey | None, timing: ClientTiming) -> EcuCheck:
    """:func:`eol_cal.ecu.client.preflight_ecu` on a bus of its own (a bus that cannot be opened is a problem)."""
    from eol_cal.ecu.client import EcuCheck, preflight_ecu

    try:
        bus = open_bus()
    except Exception as exc:  # noqa: BLE001 - python-can raises many kinds; each is a reason here
        return EcuCheck(None, None, [f"ECU bus cannot be opened: {type(exc).__name__}: {exc}"])
    try:
        return preflight_ecu(bus, seed_to_key, timing=timing)
    finally:
        bus.shutdown()


def serial_problems(serial: str, ecu: EcuState | None, dut_serial: str | None) -> list[str]:
    """The given serial against the ECU's (F18C) and the dyno's motor serial (when it reports one)."""
    out = []
    if ecu is not None and ecu.serial is not None and ecu.serial != serial:
        out.append(f"ECU serial {ecu.serial} (F18C) is not {serial}")
    if dut_serial and dut_serial != serial:
        out.append(f"dyno's motor serial {dut_serial} (dut_serial) is not {serial}")
    return out


def preflight(serial: str, dyno: DynoConfig, open_bus: Callable[[], Any], seed_to_key: SeedToKey | None,
              timing: ClientTiming) -> Preflight:
    """Every check of the module docstring; the reasons are empty when the station is ready."""
    found = Preflight(serial)
    found.dyno, dyno_problems = check_dyno(dyno)
    found.ecu = check_ecu(open_bus, seed_to_key, timing)
    found.reasons = dyno_problems + list(found.ecu.problems) + serial_problems(
        serial, found.ecu.state, None if found.dyno is None else found.dyno["dut_serial"])
    return found


def read_ecu_with(open_bus: Callable[[], Any], timing: ClientTiming) -> ReadEcu:
    """A :data:`ReadEcu` that opens the bus, reads :func:`eol_cal.ecu.client.ecu_state` and closes it."""

    def read() -> EcuState:
        from eol_cal.ecu.client import ecu_state

        bus = open_bus()
        try:
            return ecu_state(bus, timing=timing)
        finally:
            bus.shutdown()

    return read


def acquire_traced(read_ecu: ReadEcu | None, config: DynoConfig, segments: Sequence[DynoSetpoint],
                   out: str | Path, **acquire_kw: Any) -> tuple[Capture, Trace]:
    """:func:`eol_cal.dyno.client.acquire` with the ECU's state read before and after, into the
    capture's metadata (``ecu_before.*``, ``ecu_after.*``); written to ``out`` after both reads.

    ``read_ecu`` None: no record of the ECU state (no ECU-state keys). The reads run alongside
    the dyno's ramps (:func:`eol_cal.dyno.client.run_profile`): the one before while the shaft
    ramps to the first segment, finished before the first capture is armed; the one after from
    the last window on, while the shaft stops. A failed read before stops the dyno (safe state)
    before any capture; a failed read after writes no capture.
    """
    from concurrent.futures import Future, ThreadPoolExecutor

    from eol_cal.capture import write_capture
    from eol_cal.dyno import client as dc

    if read_ecu is None:
        capture = dc.acquire(config, segments, None, **acquire_kw)
        write_capture(capture, out)
        return capture, Trace(None, None)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ecu-trace") as pool:
        before_job = pool.submit(read_ecu)
        after_job: list[Future] = []
        capture = dc.acquire(config, segments, None, before_capture=before_job.result,
                             after_capture=lambda: after_job.append(pool.submit(read_ecu)), **acquire_kw)
        before, after = before_job.result(), after_job[0].result()
    capture = dataclasses.replace(capture, metadata=with_ecu_state(capture.metadata, before, after))
    write_capture(capture, out)
    return capture, Trace(before, after)


def expect_block(trace: Trace, which: str, expected: dict[str, Any] | None) -> None:
    """Refuse a capture of the cycle whose ECU state changed, or is not the block the cycle flashed.

    ``expected``: the record's ``ecu_prepared`` or ``block`` (``bank``, ``sequence``, ``crc32``).
    """
    before, after = trace.before, trace.after
    if before is None or after is None:
        raise EcuStateMismatch(f"{which}: no record of the ECU state")
    if not before.same_block(after):
        raise EcuStateMismatch(f"the ECU's active block changed during the {which} acquisition (before: "
                               f"{before.describe()}; after: {after.describe()})")
    if expected is not None and (before.bank, before.sequence, before.crc32) != (
            expected.get("bank"), expected.get("sequence"), expected.get("crc32")):
        raise EcuStateMismatch(f"the ECU ran {before.describe()} during the {which} acquisition, not the block "
                               f"this cycle flashed (bank {expected.get('bank')}, sequence {expected.get('sequence')}, "
                               f"CRC {expected.get('crc32')})")
