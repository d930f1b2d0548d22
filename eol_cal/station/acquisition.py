"""The station's traced acquisition: a dyno acquisition with the ECU's active block read right
before the first capture and right after the last window (alongside the dyno's ramps), both
written into the capture's metadata (:mod:`eol_cal.capture.ecu_state`); and the cycle's check that
the ECU ran the block the cycle flashed all along."""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

from eol_cal.capture import write_capture
from eol_cal.capture.ecu_state import EcuState, Trace, with_ecu_state
from eol_cal.dyno.profile_run import acquire
from eol_cal.ecu.client import ecu_state
from eol_cal.errors import EolCalError
from eol_cal.records.record import FlashedBlock

if TYPE_CHECKING:
    from eol_cal.capture.data import Capture
    from eol_cal.dyno.setpoints import DynoSetpoint
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu.client import ClientTiming

#: reads the ECU's state now (opens and closes its own bus)
ReadEcu = Callable[[], EcuState]
#: starts what reads the ECU's state after the last window, in place of a :data:`ReadEcu` of its own
#: (the station's flash ahead, :class:`~eol_cal.station.flash_ahead.FlashAhead`'s ``state``)
ReadAfter = Callable[[], "Future[EcuState]"]


class EcuStateMismatch(EolCalError):
    """The ECU did not run the block the cycle expected during an acquisition (exit 2)."""


def read_ecu_with(open_bus: Callable[[], Any], timing: ClientTiming) -> ReadEcu:
    """A :data:`ReadEcu` that opens the bus, reads :func:`eol_cal.ecu.client.ecu_state` and closes it."""

    def read() -> EcuState:
        bus = open_bus()
        try:
            return ecu_state(bus, timing=timing)
        finally:
            bus.shutdown()

    return read


def acquire_traced(read_ecu: ReadEcu | None, config: DynoConfig, segments: Sequence[DynoSetpoint],
                   out: str | Path | None, read_after: ReadAfter | None = None, **acquire_kw: Any
                   ) -> tuple[Capture, Trace]:
    """:func:`eol_cal.dyno.profile_run.acquire` with the ECU's state read before and after, into the
    capture's metadata (``ecu_before.*``, ``ecu_after.*``); written to ``out`` after both reads
    (``out`` None: the caller writes it).

    ``read_ecu`` None: no record of the ECU state (no ECU-state keys). The reads run alongside
    the dyno's ramps (:func:`eol_cal.dyno.profile_run.run_profile`): the one before while the shaft
    ramps to the first segment, finished before the first capture is armed; the one after from
    the last window on, while the shaft stops. A failed read before stops the dyno (safe state)
    before any capture; a failed read after writes no capture. ``read_after``: started after the
    last window in place of ``read_ecu``'s read there.
    """
    if read_ecu is None:
        capture = acquire(config, segments, None, **acquire_kw)
        if out is not None:
            write_capture(capture, out)
        return capture, Trace(None, None)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ecu-trace") as pool:
        before_job = pool.submit(read_ecu)
        after_job: list[Future] = []
        capture = acquire(config, segments, None, before_capture=before_job.result,
                          after_capture=lambda: after_job.append(read_after() if read_after is not None
                                                                 else pool.submit(read_ecu)), **acquire_kw)
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
