"""The calibrated block's flash, opened while the fit computes the block.

The flash sequence's first half needs nothing of the block (:class:`eol_cal.ecu.sequence.Programming`:
extended and programming sessions, security access, F18C/FD00/FD01, the ECU's motor type and
the erase of the inactive bank when no earlier block lives there). On the station's critical path
it would run after the fit; :class:`FlashAhead` runs it on a thread of its own from the fit's
start, on a bus of its own, so the flash step starts at the download. The session stays open
meanwhile (TesterPresent, :class:`~eol_cal.ecu.session.UdsSession`).

Opened ``traced`` (the station opens it as the calibration capture's last window is in), its first
requests read the ECU's state as :func:`~eol_cal.ecu.client.ecu_state` does (extended session, F18C,
FD01, the active block's header): the capture's state after its windows (:attr:`FlashAhead.state`),
read on the session the flash goes on with. A read of its own would hold the ECU until the flash
ahead may start (two testers cannot share it): the first half's ~0.15 s began only after it.

:meth:`FlashAhead.flash` writes the block (checked against the identification as
:func:`~eol_cal.ecu.sequence.flash_block` checks it) and archives it as
:func:`~eol_cal.station.archive.flash_archived` does; a cycle that ends without flashing (the fit
failed the motor, an error, a signal) calls :meth:`FlashAhead.close`, which waits for the first
half and leaves the session: the active block is the one the ECU booted before, and the inactive
bank holds no block (it held none, or the erase was left for the write).
"""

from __future__ import annotations

import contextlib
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

from eol_cal.ecu.client import session_state
from eol_cal.ecu.sequence import Programming, refuse_block
from eol_cal.ecu.session import UdsSession
from eol_cal.station.archive import archived

if TYPE_CHECKING:
    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.ecu.session import ClientTiming
    from eol_cal.domain.motor_params import MotorParams
    from eol_cal.records.record import FlashedBlock

#: seconds :meth:`FlashAhead.close` waits for the first half (its requests are bounded by the
#: session's timeouts; a thread still blocked after it is a daemon and its bus is shut down)
CLOSE_WAIT_S = 30.0


class FlashAhead:
    """The first half of a flash, started at once on a thread of its own (module doc).

    Parameters
    ----------
    open_bus : callable
        Opens the tester's bus (its own, closed by :meth:`flash` or :meth:`close`).
    seed_to_key : callable
        The ECU's security algorithm.
    timing : ClientTiming
    motor : MotorParams
        The station's motor (the block's physical checks, the ECU's type without a block).
    traced : bool
        Read the ECU's state first (:attr:`state`; module doc).
    """

    def __init__(self, open_bus: Callable[[], Any], *, seed_to_key: Callable[[bytes], bytes], timing: ClientTiming,
                 motor: MotorParams, traced: bool = False) -> None:
        self.motor = motor
        self.erased: bool | None = None
        #: the ECU's state read first (``traced``), else None; its failure is the first half's
        self.state: Future[EcuState] | None = Future() if traced else None
        self._open_bus, self._seed_to_key, self._timing = open_bus, seed_to_key, timing
        self._bus: Any = None
        self._session: UdsSession | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._opened: Future[Programming] = Future()
        threading.Thread(target=self._open, name="flash-ahead", daemon=True).start()

    def _open(self) -> None:
        try:
            with self._lock:
                if self._closed:
                    raise RuntimeError("closed before it opened")
                self._bus = self._open_bus()
                self._session = UdsSession(self._bus, seed_to_key=self._seed_to_key, timing=self._timing)
                self._session.__enter__()
            if self.state is not None:
                self.state.set_result(session_state(self._session))
            programming = Programming(self._session, self.motor)
            programming.identify()
            self.erased = programming.erase_ahead()
            self._opened.set_result(programming)
        except BaseException as exc:  # noqa: BLE001 - the flash step raises it
            if self.state is not None and not self.state.done():
                self.state.set_exception(exc)
            self._opened.set_exception(exc)

    def flash(self, data: bytes, *, role: str, path: Path, source: str,
              progress: Callable[[str], None] | None = None,
              before_commit: Callable[[], None] | None = None,
              read_back: bool = True) -> tuple[FlashReport, FlashedBlock]:
        """Write ``data`` (:meth:`Programming.write`, read back before its CRC unless not
        ``read_back``) and archive it at ``path``
        (:func:`~eol_cal.station.archive.archived`); the first half's failure is raised here.
        The session and the bus are closed in every case."""
        t0 = time.perf_counter()
        try:
            blk = refuse_block(data, source, self.motor)
            programming = self._opened.result()
            programming.prog.callback = progress

            def write() -> FlashReport:
                report = programming.write(blk, verify=read_back, before_commit=before_commit)
                report.seconds = time.perf_counter() - t0
                return report

            return archived(role, path, write, read_back=read_back)
        finally:
            self.close()

    def close(self) -> None:
        """Wait for the first half (at most :data:`CLOSE_WAIT_S`), leave the session, shut the bus.
        Idempotent."""
        with contextlib.suppress(BaseException):  # its failure was raised by flash(), or does not matter now
            self._opened.exception(CLOSE_WAIT_S)
        with self._lock:
            if self._closed:
                return
            self._closed = True
            session, bus = self._session, self._bus
        if session is not None:
            if self._opened.done():  # else the first half still holds the session: the bus's end stops it
                with contextlib.suppress(Exception):  # best effort: the ECU may be gone
                    session.leave()
            with contextlib.suppress(Exception):
                session.__exit__(None, None, None)
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()
