"""The ECU simulator's bus paced to a CAN bit rate (issue 24): frames take their time on the bus,
both directions share it, and a flash through it is still correct.

Only lower bounds on time are asserted (a loaded machine can only be slower).
"""

from __future__ import annotations

import dataclasses
import time

import can
import pytest

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import flash_block, hmac_seed_to_key
from eol_cal.ecu.transport import private_channel_name
from eol_cal.ecu.wire import PacedBus, frame_bits, isotp_min_frames, wire_bits

from eol_cal.sim.virtual_rig import FAST_CLIENT, FAST_SIM, example_block, virtual_rig

KEY = hmac_seed_to_key(P.DEV_SECRET)


def test_frames_take_their_time_on_the_bus_both_ways():
    channel = private_channel_name("paced")
    peer = can.Bus(interface="virtual", channel=channel)
    paced = PacedBus(can.Bus(interface="virtual", channel=channel), 125_000)
    try:
        msg = can.Message(arbitration_id=P.ECU_ID, data=bytes(8), is_extended_id=False)
        reply = can.Message(arbitration_id=P.TESTER_ID, data=bytes(8), is_extended_id=False)
        # each frame its own length: eight zero bytes are stuffed hard (more than random data)
        frame_s = wire_bits(P.ECU_ID, bytes(8)) / 125_000
        reply_s = wire_bits(P.TESTER_ID, bytes(8)) / 125_000
        assert 111 < wire_bits(P.ECU_ID, bytes(8)) <= frame_bits(8)
        t0 = time.monotonic()
        for _ in range(20):  # queued as in a CAN controller: the other side sees them at the bit rate
            paced.send(msg)
        assert [peer.recv(1.0) is not None for _ in range(20)] == [True] * 20
        assert time.monotonic() - t0 >= 20 * frame_s
        for _ in range(20):  # the peer's frames share the same bus
            peer.send(reply)
        got = [paced.recv(1.0) for _ in range(20)]
        assert all(m is not None for m in got)
        assert time.monotonic() - t0 >= 20 * (frame_s + reply_s)
        assert paced.busy_s == pytest.approx(20 * (frame_s + reply_s))
    finally:
        paced.shutdown()
        peer.shutdown()


@pytest.mark.parametrize("bitrate", [500_000, 1_000_000])
def test_a_flash_on_a_paced_bus_takes_at_least_its_bus_time(tmp_path, bitrate):
    block = example_block(seed=3)
    config = dataclasses.replace(FAST_SIM, bitrate=bitrate)
    with virtual_rig(tmp_path / "flash.bin", config=config) as rig:
        report = flash_block(rig.tester, block, seed_to_key=KEY, timing=FAST_CLIENT)
        assert report.verified and report.active_after.sequence == 1
        paced = rig.sim.bus
        assert isinstance(paced, PacedBus)
        # the block went down and came back (read-back) at least once, each frame at least its
        # unstuffed bit time
        least = 2 * (isotp_min_frames(len(block)) - 2) * frame_bits(8, stuffing=False) / bitrate
        assert paced.busy_s >= least
        assert report.seconds >= least
