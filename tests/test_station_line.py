"""A line's simulators at fixed addresses for many motors (eol_cal.sim.loopback.loopback_line)."""

from __future__ import annotations

from eol_cal.dyno.client import DynoClient, parse_address
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.ecu.client import ecu_state
from eol_cal.ecu.transport import open_bus
from eol_cal.sim.loopback import loopback_line


def test_each_motor_gets_a_fresh_ecu_behind_the_same_addresses(tmp_path):
    with loopback_line(tmp_path, bitrate=500_000) as line:
        seen = []
        for serial, seed in (("LINE-1", 1), ("LINE-2", 2)):
            flash = line.load(serial, seed)
            bus = open_bus("remote", line.can_channel)
            try:
                state = ecu_state(bus)
            finally:
                bus.shutdown()
            host, port = parse_address(line.dyno_address)
            client = DynoClient(DynoConfig(host=host, port=port))
            try:
                ident = client.connect()
            finally:
                client.close()
            seen.append((state.serial, state.bank, ident["dut_serial"], flash.name))
        assert seen == [("LINE-1", None, "LINE-1", "LINE-1.flash"), ("LINE-2", None, "LINE-2", "LINE-2.flash")]


def test_a_line_readies_the_plants_programs_for_the_options_asked_before_it_serves(tmp_path, monkeypatch):
    """``prepare``: the plant's programs for the blocks of those estimator options are compiled before
    the simulators serve (a real dyno's data is never late), once, whatever motors follow; without it
    the first motor's capture compiles them."""
    from eol_cal.sim import loopback

    calls = []
    monkeypatch.setattr(loopback, "prepare_plant",
                        lambda spec_for, options, serial, seed=None: calls.append((options, spec_for(None).serial)))
    with loopback_line(tmp_path / "a", prepare=0x3C) as line:
        assert calls == [(0x3C, "PREPARE")]  # before the line is handed over
        line.load("LINE-1", 1)
        line.load("LINE-2", 2)
    assert calls == [(0x3C, "PREPARE")]
    with loopback_line(tmp_path / "b"):
        pass
    assert calls == [(0x3C, "PREPARE")]
