"""The tester's timing towards the loopback simulators (``eol_cal.sim.loopback``): they answer from
the tester's own process, so a loaded machine makes them late by however long it does not schedule
that process; the demo's cycle must wait for them as for an ECU that answers late, not fail the
motor (``eol-cal station --demo`` failed motors at load 11-14 with the real ECU's 0.5 s P2)."""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from eol_cal.dyno.client import DynoClient, DynoError
from eol_cal.dyno.sim_dyno import DynoSim
from eol_cal.ecu.client import ecu_state
from eol_cal.ecu.session import ClientTiming, EcuError
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.ecu.simconfig import Faults
from eol_cal.sim.loopback import SIM_DYNO_TIMEOUT_S, SIM_ECU_TIMING, loopback_station

#: each test waits seconds for a late simulator (CONTRIBUTING.md, "Fast or slow")
pytestmark = pytest.mark.slow

LATE_S = 0.8  # each frame the simulator sends: what a host that did not run its process for 0.8 s gives
#: each Modbus answer of the dyno simulator: later than a real dyno's 1 s time-out (``dyno.timeout_s``)
DYNO_LATE_S = 1.3


def _state(st, timing):
    bus = st.open_bus()
    try:
        return ecu_state(bus, timing=timing)
    finally:
        bus.shutdown()


def test_the_tester_waits_for_a_loopback_ecu_that_answers_late(tmp_path):
    with loopback_station("L-1", 1, tmp_path / "sim") as st:
        assert st.ecu_timing == SIM_ECU_TIMING
        st.ecu.replace(st.flash_file, SimConfig(serial="L-1"), Faults(delay_rate=1.0, delay_s=LATE_S))
        # the real ECU's timing (P2 0.5 s, what the demo used) gives up on the simulator ...
        with pytest.raises(EcuError, match="no response from the ECU"):
            _state(st, ClientTiming(retries=0))
        # ... the loopback timing waits for it (each answer after the one the tester gave up on)
        assert _state(st, st.ecu_timing).serial == "L-1"


def test_the_tester_waits_for_a_loopback_dyno_that_answers_late(tmp_path, monkeypatch):
    answer = DynoSim.action

    async def late(self, *args):
        await asyncio.sleep(DYNO_LATE_S)  # the simulator's loop not scheduled for that long
        return await answer(self, *args)

    monkeypatch.setattr(DynoSim, "action", late)  # before the server binds its requests to it
    with loopback_station("L-2", 2, tmp_path / "sim") as st:
        cfg = st.dyno_config()
        assert cfg.timeout == SIM_DYNO_TIMEOUT_S > DYNO_LATE_S
        # a real dyno's time-out (1 s, one try) gives up on the simulator ...
        real = DynoClient(dataclasses.replace(cfg, timeout=1.0, retries=0))
        try:
            with pytest.raises(DynoError):
                real.connect()
        finally:
            real.close()
        # ... the loopback's waits for it
        client = DynoClient(cfg)
        try:
            assert client.connect()["dut_serial"] == "L-2"
        finally:
            client.close()
