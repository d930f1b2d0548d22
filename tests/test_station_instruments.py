"""The station's instrument seam (issue 39 item 1, eol_cal/station/instruments.py): the cycle's steps
reach the dyno and the ECU only through the context's instruments, so another implementation (a
plant driven in-process) runs the production steps unchanged."""

from __future__ import annotations

import dataclasses
import socket
from pathlib import Path
from typing import Any

import pytest

from eol_cal.dyno.transfer import DynoConfig
from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import hmac_seed_to_key
from eol_cal.plant.presets import preset_spec
from eol_cal.records.limits import load_limits
from eol_cal.sim import FIXTURES
from eol_cal.sim.loopback import loopback_station
from eol_cal.station.cycle import run_motor
from eol_cal.station.instruments import BenchInstruments
from eol_cal.station.run import StationConfig
from test_lot_simulate import PROFILE  # the short calibration profile both use



class Counted:
    """Instruments that count each call and hand it to ``inner``."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.calls = inner, []

    @property
    def channels(self) -> frozenset[str]:
        return self.inner.channels

    def __getattr__(self, name: str) -> Any:
        fn = getattr(self.inner, name)

        def call(*args: Any, **kw: Any) -> Any:
            self.calls.append(name)
            return fn(*args, **kw)

        return call


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # one station cycle on the plant (about 15 s quiet)
def test_a_cycle_reaches_the_dyno_and_the_ecu_only_through_its_instruments(tmp_path: Path):
    """The configuration the steps see points at nothing (a closed port, a bus that refuses to
    open); the instruments hold the loopback station's: the motor is measured and judged all the
    same, each instrument called as the steps need it."""
    (tmp_path / "short.toml").write_text(PROFILE)
    spec = preset_spec("paper", serial="SEAM-1")

    def no_bus() -> Any:
        raise AssertionError("a step opened the configuration's ECU bus, not the instruments'")

    with loopback_station("SEAM-1", 3, tmp_path / "sim", spec_for=lambda req: spec) as st:
        real = StationConfig(
            serial="SEAM-1", dyno=st.dyno_config(), open_bus=st.open_bus,
            ecu_timing=st.ecu_timing, seed_to_key=hmac_seed_to_key(P.DEV_SECRET),
            limits=load_limits(FIXTURES / "limits.toml", "EPS-STD"), db=tmp_path / "r.sqlite",
            report_dir=tmp_path / "reports", profile=str(tmp_path / "short.toml"), spool_dir=tmp_path / "spool",
            cache_dir=None)
        cut = dataclasses.replace(real, dyno=DynoConfig(port=_closed_port(), timeout=0.05, retries=0), open_bus=no_bus)
        instruments = Counted(BenchInstruments(real))
        out = run_motor(cut, instruments=instruments)
    rec = out.record
    assert rec.error is None and rec.verdict in ("pass", "fail"), rec.reasons
    assert [s.step for s in rec.steps] == ["pre-flight", "prepare ECU", "acquire", "fit", "table", "flash",
                                           "acquire compensated", "metrics", "report"]
    assert [b.role for b in rec.blocks] == ["prepare", "calibrated"] and all(b.confirmed for b in rec.blocks)
    assert sorted(instruments.calls) == ["acquire", "acquire", "flash", "flash_ahead", "preflight"]
    # the production instruments are the configuration's by default: the same configuration, no instruments
    # given, cannot reach anything
    refused = run_motor(dataclasses.replace(cut, report_dir=tmp_path / "r2")).record
    assert refused.kind == "refusal" and "dyno_unreachable" in refused.refusal_codes
