"""Recovering a dyno that latched a fault, on purpose (issue 36, class 7).

A fault latches on the dyno (its communication watchdog, over-speed, the torque sensor) and
stays until it is reset through the register map's ``fault_reset``: every later run is refused
(``dyno_tripped``) until then. :func:`inspect_faults` reads what is latched; :func:`clear_faults`
resets it, only at standstill and with the drive disabled (nothing is started), then reads the
status again: a fault whose cause persists latches again at once and is reported, not hidden.
``eol-cal dyno-clear`` asks the operator before it writes anything.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from eol_cal.dyno.client import DynoClient, DynoError
from eol_cal.dyno.registers import Command, DriveState, Switch, fault_names
from eol_cal.dyno.transfer import DynoConfig

#: the shaft counts as at standstill below this speed (rpm): a fault is cleared only then
STANDSTILL_RPM = 1.0
#: seconds the dyno has to take the reset (its status polled until then)
CLEAR_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class DynoFaults:
    """What a dyno's status says of its faults.

    Attributes
    ----------
    faults : int
        The ``faults`` register (latched bits, :class:`~eol_cal.dyno.registers.Fault`).
    drive_state : str
        The drive's state by name (``TRIPPED`` while a trip is latched).
    speed_rpm : float
        The shaft's speed (rpm).
    """

    faults: int
    drive_state: str
    speed_rpm: float

    @property
    def latched(self) -> bool:
        return bool(self.faults) or self.drive_state == DriveState.TRIPPED.name

    def describe(self) -> str:
        what = "+".join(fault_names(self.faults)) or "none"
        return f"faults {what} (0x{self.faults:04x}), drive {self.drive_state}, speed {self.speed_rpm:.1f} rpm"


def _faults(client: DynoClient) -> DynoFaults:
    st = client.status()
    state = int(st["drive_state"])
    name = DriveState(state).name if state in tuple(DriveState) else f"state {state}"
    return DynoFaults(int(st["faults"]), name, float(st["speed"]))


def inspect_faults(config: DynoConfig) -> DynoFaults:
    """Read the dyno's faults (identification checked first; nothing written)."""
    client = DynoClient(config)
    try:
        client.connect()
        return _faults(client)
    finally:
        client.close()


def clear_faults(config: DynoConfig, timeout_s: float = CLEAR_TIMEOUT_S) -> tuple[DynoFaults, DynoFaults]:
    """Reset the dyno's latched faults: (status before, status after).

    Only at standstill: the drive is disabled and its set point 0 first (nothing is started),
    then ``fault_reset`` is written and the status polled until the faults are gone or
    ``timeout_s`` passed; a fault still latched then (its cause persists) is in the status after.

    Raises
    ------
    DynoError
        The dyno cannot be reached, its identification does not match the map, or the shaft
        turns (nothing is written then).
    """
    client = DynoClient(config)
    try:
        client.connect()
        before = _faults(client)
        if abs(before.speed_rpm) > STANDSTILL_RPM:
            raise DynoError(f"{client.where}: the shaft turns ({before.speed_rpm:.1f} rpm): a fault is cleared only at "
                            "standstill; nothing was written")
        client.write(speed_setpoint=0.0)
        client.write(enable=Switch.OFF)
        client.write(fault_reset=Command.EXECUTE)
        deadline = time.monotonic() + timeout_s
        after = _faults(client)
        while after.latched and time.monotonic() < deadline:
            time.sleep(config.poll_interval)
            after = _faults(client)
        return before, after
    finally:
        client.close()
