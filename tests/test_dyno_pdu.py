"""Register reads coded in one ``struct`` call (eol_cal.dyno.pdu): the bytes and the register lists
of pymodbus's own classes, refusals where pymodbus refuses, and a real server and client on
127.0.0.1 answering the same words to pymodbus's plain client as to ours."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu.register_message import ReadHoldingRegistersResponse, ReadInputRegistersResponse

from eol_cal.dyno.client import DynoClient
from eol_cal.dyno.mapfile import load_register_map
from eol_cal.dyno.pdu import HoldingResponse, InputResponse, fast_reads
from eol_cal.dyno.regmap import READ_FC
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread
from eol_cal.dyno.transfer import DynoConfig

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@pytest.mark.parametrize(("ours", "theirs"), [(HoldingResponse, ReadHoldingRegistersResponse),
                                              (InputResponse, ReadInputRegistersResponse)])
def test_the_same_bytes_and_registers_as_pymodbus(ours, theirs):
    rng = np.random.default_rng(37)
    for count in (1, 2, 3, 64, 124, 125):
        for regs in ([0] * count, [0xFFFF] * count, rng.integers(0, 1 << 16, count).tolist()):
            data = theirs(registers=regs).encode()
            assert ours(registers=regs).encode() == data
            a, b = ours(), theirs()
            a.decode(data)
            b.decode(data)
            assert a.registers == b.registers == regs
            assert type(a.registers) is list and a.function_code == b.function_code


def test_a_byte_count_the_frame_does_not_hold_is_refused():
    with pytest.raises(ModbusIOException):  # beyond the frame, as pymodbus refuses it
        HoldingResponse().decode(bytes([8, 0, 1, 0, 2]))
    with pytest.raises(ModbusIOException):  # odd: half a register
        InputResponse().decode(bytes([3, 0, 1, 0, 2]))


@pytest.mark.parametrize("name", ["default", "vendor-b"])
def test_the_simulator_answers_ours_and_pymodbus_s_plain_client_alike(name):
    """Both register maps (a shared space and separate input/holding tables): the capture window
    and the registers that hold still (the status ones move with the shaft and the heartbeat),
    read by pymodbus's client as it comes and by one with ours."""
    regmap = load_register_map(name)
    thread = DynoSimThread(DynoSim(synthetic_source, serial="M-PDU", register_map=regmap)).start()
    try:
        dc = DynoClient(DynoConfig(port=thread.port, register_map=regmap, timeout=5.0, retries=0))
        dc.connect()
        dc.set_point(DynoSetpoint(60.0, 0.05, iq=10.0))
        dc.capture(500, 10000)
        channel = next(iter(regmap.analog_channels))
        reads = [(READ_FC[regmap.window.table], regmap.window.address, 125)]
        reads += [(READ_FC[e.table], e.address, e.count) for e in regmap.entries.values()
                  if e.role.group in ("identification", "control", "transfer")]
        got = []
        for fast in (False, True):
            c = ModbusTcpClient("127.0.0.1", port=thread.port, timeout=5.0, retries=0)
            if fast:
                fast_reads(c)
            c.connect()
            try:
                for address, words, _ in regmap.write_runs({"buf_channel": channel, "buf_offset": 0}):
                    assert not c.write_registers(address, words, device_id=1).isError()
                rows = []
                for fc, address, count in reads:
                    r = (c.read_input_registers if fc == 4 else c.read_holding_registers)(address, count=count,
                                                                                          device_id=1)
                    assert not r.isError()
                    rows.append(list(r.registers))
                got.append(rows)
            finally:
                c.close()
        assert got[0] == got[1]
        assert any(got[1][0])  # the window holds the capture, not zeros
        dc.close()
    finally:
        thread.stop()


def test_its_text_names_the_response_without_formatting_every_register():
    r = HoldingResponse(registers=list(range(125)), dev_id=1, transaction_id=7)
    assert str(r) == "HoldingResponse(dev_id=1, transaction_id=7, 125 registers)"
