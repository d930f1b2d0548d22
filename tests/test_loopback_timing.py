"""The tester's timing towards the loopback simulators (``eol_cal.sim.loopback``): they answer from
the tester's own process, so a loaded machine makes them late by however long it does not schedule
that process; the demo's cycle must wait for them as for an ECU that answers late, not fail the
motor (``eol-cal station --demo`` failed motors at load 11-14 with the real ECU's 0.5 s P2)."""

from __future__ import annotations

import pytest

from eol_cal.ecu.client import ecu_state
from eol_cal.ecu.session import ClientTiming, EcuError
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.ecu.simconfig import Faults
from eol_cal.sim.loopback import SIM_ECU_TIMING, loopback_station

LATE_S = 0.8  # each frame the simulator sends: what a host that did not run its process for 0.8 s gives


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
