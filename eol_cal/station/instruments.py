"""The station's instruments as the cycle's steps call them: the dyno (the pre-flight's check, an
acquisition of the profile's windows with the ECU's state read around it, the safe state after a
failure) and the ECU (a block
flashed, read back and archived; the calibrated flash's first half opened ahead).

:class:`Instruments` is the seam: :class:`~eol_cal.station.context.CycleContext` holds one and its
steps call nothing else of the rig. :class:`BenchInstruments` is the production one, today's
Modbus dyno client (:mod:`eol_cal.dyno.profile_run`) and UDS/ISO-TP ECU client
(:mod:`eol_cal.ecu.sequence`) on the configuration's addresses; another implementation (a plant
driven in-process) gives the same calls what the production path would decode.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Protocol
from collections.abc import Callable, Sequence

from eol_cal.ecu.session import ClientTiming
from eol_cal.station.acquisition import ReadAfter, acquire_traced, read_ecu_with
from eol_cal.station.archive import flash_archived
from eol_cal.station.flash_ahead import FlashAhead
from eol_cal.station.preflight import preflight
from eol_cal.station.run import safe_state

if TYPE_CHECKING:
    from concurrent.futures import Future

    from eol_cal.capture.data import Capture
    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.capture.ecu_state import Trace
    from eol_cal.dyno.profile_run import WindowHook
    from eol_cal.dyno.setpoints import DynoSetpoint
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.records.record import FlashedBlock, PreflightResult
    from eol_cal.station.run import StationConfig

#: what a flash returns: the ECU's report and the archived block's record
Flashed = tuple["FlashReport", "FlashedBlock"]


class OpenFlash(Protocol):
    """A flash whose first half (sessions, identification, erase) is under way (:class:`FlashAhead`)."""

    def flash(self, data: bytes, *, role: str, path: Path, source: str,
              progress: Callable[[str], None] | None = None,
              before_commit: Callable[[], None] | None = None, read_back: bool = True) -> Flashed: ...

    def close(self) -> None: ...

    @property
    def state(self) -> Future[EcuState] | None:
        """The ECU's state its first requests read (opened ``traced``), else None."""
        ...


class Instruments(Protocol):
    """The dyno and the ECU of one motor's cycle (module doc)."""

    @property
    def channels(self) -> frozenset[str]:
        """The channels the dyno records (its register map's)."""
        ...

    def preflight(self, serial: str) -> PreflightResult:
        """Dyno ready, ECU answering and accepting the key, its serial ``serial``
        (:func:`eol_cal.station.preflight.preflight`); problems listed, never raised."""
        ...

    def acquire(self, segments: Sequence[DynoSetpoint], *, serial: str, rate_hz: int, channels: Sequence[str],
                comment: str, on_window: WindowHook | None = None, lead_in_s: float = 0.0,
                lead_in_point: DynoSetpoint | None = None, read_after: ReadAfter | None = None
                ) -> tuple[Capture, Trace]:
        """The profile's windows joined into one capture, the ECU's state read before the first
        and after the last (:func:`eol_cal.station.acquisition.acquire_traced`; ``read_after``
        started for the read after); not written."""
        ...

    def flash(self, data: bytes, *, role: str, path: Path, source: str,
              before_commit: Callable[[], None] | None = None, read_back: bool = True) -> Flashed:
        """Flash the block image ``data`` on a session of its own and archive it at ``path``
        (:func:`eol_cal.station.archive.flash_archived`)."""
        ...

    def flash_ahead(self, traced: bool = False) -> OpenFlash:
        """Start a flash's first half now, on a thread of its own (:class:`FlashAhead`; ``traced``:
        its first requests read the ECU's state)."""
        ...

    def safe_state(self) -> str:
        """Command the dyno's safe state once more (best effort, after a failure or on a signal);
        say whether it was confirmed (:func:`eol_cal.station.run.safe_state`)."""
        ...


class BenchInstruments:
    """The production instruments: the configuration's Modbus dyno and its ECU on the CAN bus."""

    def __init__(self, cfg: StationConfig) -> None:
        self.cfg = cfg
        self.timing = cfg.ecu_timing or ClientTiming()

    @property
    def channels(self) -> frozenset[str]:
        return frozenset(self.cfg.dyno.regmap.channels)

    def preflight(self, serial: str) -> PreflightResult:
        return preflight(serial, self.cfg.dyno, self.cfg.open_bus, self.cfg.seed_to_key, self.timing)

    def acquire(self, segments: Sequence[DynoSetpoint], *, serial: str, rate_hz: int, channels: Sequence[str],
                comment: str, on_window: WindowHook | None = None, lead_in_s: float = 0.0,
                lead_in_point: DynoSetpoint | None = None, read_after: ReadAfter | None = None
                ) -> tuple[Capture, Trace]:
        return acquire_traced(read_ecu_with(self.cfg.open_bus, self.timing), self.cfg.dyno, segments, None,
                              read_after, serial=serial, rate_hz=rate_hz, channels=tuple(channels),
                              extra_metadata={"comment": comment}, on_window=on_window, lead_in_s=lead_in_s,
                              lead_in_point=lead_in_point)

    def flash(self, data: bytes, *, role: str, path: Path, source: str,
              before_commit: Callable[[], None] | None = None, read_back: bool = True) -> Flashed:
        return flash_archived(self.cfg.open_bus, data, role=role, path=path, seed_to_key=self.cfg.seed_to_key,
                              timing=self.timing, motor=self.cfg.motor, source=source, before_commit=before_commit,
                              read_back=read_back)

    def flash_ahead(self, traced: bool = False) -> OpenFlash:
        return FlashAhead(self.cfg.open_bus, seed_to_key=self.cfg.seed_to_key, timing=self.timing,
                          motor=self.cfg.motor, traced=traced)

    def safe_state(self) -> str:
        return safe_state(self.cfg.dyno)


def bench_instruments(cfg: StationConfig) -> Instruments:
    """The production instruments of ``cfg`` (:class:`BenchInstruments`)."""
    return BenchInstruments(cfg)


__all__ = ["BenchInstruments", "Flashed", "Instruments", "OpenFlash", "bench_instruments"]
