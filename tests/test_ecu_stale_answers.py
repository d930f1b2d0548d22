"""Stale answers from the ECU (issue 23, class 8): a late answer to an earlier request (a
RoutineControl 0x71 while the tester waits for ECUReset's 0x51) is discarded and the wait goes
on within P2/P2*; a good flash is not recorded as an error.

Real parts: the ECU simulator and the tester on a python-can virtual bus over can-isotp; the
simulator sends its previous answer again before every request's own (``Faults.stale_answers``:
a late duplicate at every step)."""

from __future__ import annotations

import dataclasses

import pytest

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import flash_block, hmac_seed_to_key, read_active_block
from eol_cal.ecu.matching import answers
from eol_cal.ecu.sim_ecu import Faults

from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig

KEY = hmac_seed_to_key(P.DEV_SECRET)
# P2 as the fault tests have it (0.15 s); generous enough for a loaded machine, since a stale
# answer arrives before the real one and must not cost a retry
TIMING = dataclasses.replace(FAST_CLIENT, p2_s=0.5)


@pytest.mark.parametrize("request_hex, message_hex, expected", [
    ("1101", "5101", True),                     # ECUReset's own answer
    ("1101", "7101ff00", False),                # the case: a late RoutineControl answer
    ("1101", "7f1178", True),                   # responsePending of this request
    ("1101", "7f3178", False),                  # responsePending of another service
    ("1101", "7f3122", False),                  # a late negative answer of another service
    ("3605aabb", "7604", False),                # TransferData: the previous block's late answer
    ("3605aabb", "7605", True),
    ("22f18c", "62fd010000", False),            # another DID's answer
    ("22f18c", "62f18c4d2d31", True),
    ("2702aabbccdd", "6701aabbccdd", False),    # the seed's late answer while the key is checked
    ("310101ff00", "710102ff0000", False),      # another routine's answer
    ("3101ff00", "7101ff0000", True),
    ("1002", "5003003201f4", False),            # the extended session's late answer
    ("37", "7101ff00", False),
    ("2324000000100010", "63" + "00" * 16, True),
    ("2324000000100010", "63" + "00" * 64, False),  # a late read of another size
    ("3e80", "7e00", True),
])
def test_the_matcher_takes_only_the_answer_to_the_request(request_hex, message_hex, expected):
    assert answers(bytes.fromhex(request_hex), bytes.fromhex(message_hex)) is expected


@pytest.mark.parametrize("verify", [True, False])
def test_a_flash_with_a_late_duplicate_at_every_step_completes(verify):
    block = example_block(seed=4)
    with virtual_rig(faults=Faults(stale_answers=True)) as rig:
        report = flash_block(rig.tester, block, seed_to_key=KEY, verify=verify, timing=TIMING)
        assert report.active_after.sequence == 1
        assert rig.sim.stale_sent >= 8, rig.sim.stale_sent  # session, security, DIDs, erase, ..., reset
        steps = set(rig.sim.steps_seen)
        assert {"erase", "download", "transfer", "transfer_exit", "check", "reset"} <= steps
        assert read_active_block(rig.tester, timing=TIMING) == block


def test_repeated_flashes_with_stale_answers_never_take_a_wrong_block():
    """Three flashes in a row, each reading the block back: every one boots what it wrote."""
    with virtual_rig(faults=Faults(stale_answers=True)) as rig:
        for seq, seed in enumerate((5, 6, 7), start=1):
            block = example_block(seed=seed)
            report = flash_block(rig.tester, block, seed_to_key=KEY, verify=True, timing=TIMING)
            assert report.active_after.sequence == seq
