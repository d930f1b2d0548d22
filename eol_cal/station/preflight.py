"""Pre-flight of the station cycle.

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

The acquisition with the ECU's state read around it is :mod:`eol_cal.station.acquisition`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

from eol_cal.capture.ecu_state import EcuState
from eol_cal.errors import EolCalError
from eol_cal.records.record import DynoStatus, EcuFound, PreflightResult, Problem

if TYPE_CHECKING:
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu.client import ClientTiming, SeedToKey


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


def check_dyno(config: DynoConfig) -> tuple[DynoStatus | None, list[Problem]]:
    """The dyno's identification and status, and why it is not ready (nothing is commanded).

    Returns ``(None, [why])`` when it does not answer: the client's timeout and retries bound the wait.
    """
    from eol_cal.dyno.client import DynoClient
    from eol_cal.dyno.registers import DriveState, Interlock, fault_names

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
    clear = f"check the dyno, then eol-cal dyno-clear --dyno {client.config.host}:{client.config.port}"
    if found.faults:
        names = "+".join(fault_names(found.faults))
        problems.append(Problem("dyno_fault", f"{where} has latched faults {names} (faults=0x{found.faults:04x}): {clear}"))
    if found.drive_state == DriveState.TRIPPED:
        problems.append(Problem("dyno_tripped", f"{where}: drive tripped: {clear}"))
    missing = Interlock.ALL & ~Interlock(found.interlocks & Interlock.ALL)
    if missing:
        problems.append(Problem("dyno_interlocks", f"{where}: interlocks not met: "
                                + "+".join(i.name or f"0x{int(i):04x}" for i in Interlock if i != Interlock.ALL and i & missing)))
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
