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
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

from eol_cal.capture.ecu_state import EcuState, Trace, with_ecu_state
from eol_cal.errors import EolCalError
from eol_cal.station.record import DynoStatus, EcuFound, FlashedBlock, PreflightResult, Problem

if TYPE_CHECKING:
    from eol_cal.capture.model import Capture
    from eol_cal.dyno.client import DynoConfig, DynoSetpoint
    from eol_cal.ecu.client import ClientTiming, SeedToKey

#: reads the ECU's state now (opens and closes its own bus)
ReadEcu = Callable[[], EcuState]


class PreflightFailed(EolCalError):
    """The pre-flight found the station not ready for this motor; nothing was written (exit 2).

    Attributes
    ----------
    problems : list of Problem
        Every problem found: its refusal code and one line.
    """

    def __init__(self, problems: Sequence[Problem]) -> None:
        super().__init__("; ".join(p.text for p in problems))
        self.problems = list(problems)
        self.reasons = [p.text for p in problems]


class EcuStateMismatch(EolCalError):
    """The ECU did not run the block the cycle expected during an acquisition (exit 2)."""


def check_dyno(config: DynoConfig) -> tuple[DynoStatus | None, list[Problem]]:
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
        return None, [Problem("dyno_unreachable", f"dyno not reachable: {exc}")]
    finally:
        client.close()
    found = DynoStatus(map_version=int(ident["map_version"]), dut_serial=str(ident.get("dut_serial") or ""),
                       faults=int(st["faults"]), interlocks=int(st["interlocks"]), drive_state=int(st["drive_state"]))
    where = f"dyno {client.config.host}:{client.config.port}"
    problems = []
    if found.faults:
        names = "+".join(f.name for f in Fault if f & found.faults)
        problems.append(Problem("dyno_fault", f"{where} has latched faults {names} (faults=0x{found.faults:04x}): "
                                              "clear them at the dyno"))
    if found.drive_state == DriveState.TRIPPED:
        problems.append(Problem("dyno_tripped", f"{where}: drive tripped"))
    missing = Interlock.ALL & ~Interlock(found.interlocks & Interlock.ALL)
    if missing:
        problems.append(Problem("dyno_interlocks", f"{where}: interlocks not met: "
                                + "+".join(i.name for i in Interlock if i != Interlock.ALL and i & missing)))
    return found, problems


def check_ecu(open_bus: Callable[[], Any], seed_to_key: SeedToKey | None, timing: ClientTiming
              ) -> tuple[EcuFound, list[Problem]]:
    """:func:`eol_cal.ecu.client.preflight_ecu` on a bus of its own (a bus that cannot be opened is a
    problem); what it found and its problems with their codes."""
    from eol_cal.ecu.client import preflight_ecu

    try:
        bus = open_bus()
    except Exception as exc:  # noqa: BLE001 - python-can raises many kinds; each is a reason here
        text = f"ECU bus cannot be opened: {type(exc).__name__}: {exc}"
        return EcuFound(None, None, (text,)), [Problem("ecu_bus", text)]
    try:
        found = preflight_ecu(bus, seed_to_key, timing=timing)
    finally:
        bus.shutdown()
    # preflight_ecu: without a state the ECU did not answer; with one, a problem is the key's
    code = "ecu_silent" if found.state is None else "key_refused"
    return (EcuFound(found.state, found.key_accepted, tuple(found.problems)),
            [Problem(code, text) for text in found.problems])


def serial_problems(serial: str, ecu: EcuState | None, dut_serial: str | None) -> list[Problem]:
    """The given serial against the ECU's (F18C) and the dyno's motor serial (when it reports one)."""
    out = []
    if ecu is not None and ecu.serial is not None and ecu.serial != serial:
        out.append(Problem("wrong_serial", f"ECU serial {ecu.serial} (F18C) is not {serial}"))
    if dut_serial and dut_serial != serial:
        out.append(Problem("wrong_serial", f"dyno's motor serial {dut_serial} (dut_serial) is not {serial}"))
    return out


def preflight(serial: str, dyno: DynoConfig, open_bus: Callable[[], Any], seed_to_key: SeedToKey | None,
              timing: ClientTiming) -> PreflightResult:
    """Every check of the module docstring; its problems are empty when the station is ready.

    The dyno and the ECU are asked at the same time (each wait is bounded by its own timeouts)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="preflight-dyno") as pool:
        dyno_job = pool.submit(check_dyno, dyno)
        ecu, ecu_problems = check_ecu(open_bus, seed_to_key, timing)
        found_dyno, dyno_problems = dyno_job.result()
    problems = dyno_problems + ecu_problems + serial_problems(
        serial, ecu.state, None if found_dyno is None else found_dyno.dut_serial)
    return PreflightResult(found_dyno, ecu, tuple(problems))


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
                   out: str | Path | None, **acquire_kw: Any) -> tuple[Capture, Trace]:
    """:func:`eol_cal.dyno.client.acquire` with the ECU's state read before and after, into the
    capture's metadata (``ecu_before.*``, ``ecu_after.*``); written to ``out`` after both reads
    (``out`` None: the caller writes it).

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
        if out is not None:
            write_capture(capture, out)
        return capture, Trace(None, None)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ecu-trace") as pool:
        before_job = pool.submit(read_ecu)
        after_job: list[Future] = []
        capture = dc.acquire(config, segments, None, before_capture=before_job.result,
                             after_capture=lambda: after_job.append(pool.submit(read_ecu)), **acquire_kw)
        before, after = before_job.result(), after_job[0].result()
    capture = dataclasses.replace(capture, metadata=with_ecu_state(capture.metadata, before, after))
    if out is not None:
        write_capture(capture, out)
    return capture, Trace(before, after)


def expect_block(trace: Trace, which: str, expected: FlashedBlock | None) -> None:
    """Refuse a capture of the cycle whose ECU state changed, or is not the block the cycle flashed
    (``expected``; None: any block)."""
    before, after = trace.before, trace.after
    if before is None or after is None:
        raise EcuStateMismatch(f"{which}: no record of the ECU state")
    if not before.same_block(after):
        raise EcuStateMismatch(f"the ECU's active block changed during the {which} acquisition (before: "
                               f"{before.describe()}; after: {after.describe()})")
    if expected is not None and (before.bank, before.sequence, before.crc32) != (
            expected.bank, expected.sequence, expected.crc32):
        raise EcuStateMismatch(f"the ECU ran {before.describe()} during the {which} acquisition, not the block "
                               f"this cycle flashed (bank {expected.bank}, sequence {expected.sequence}, "
                               f"CRC {expected.crc32})")
