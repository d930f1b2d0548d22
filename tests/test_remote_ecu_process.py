"""The ECU simulator served from a child process (``eol_cal.sim.remote_ecu.spawn_remote``), as the
loopback station serves it: a tester reaches it over python-can-remote on 127.0.0.1, the next
motor's ECU comes behind the same URL, a failure to start says why, and the child never outlives
the process that started it."""

from __future__ import annotations

import os

import pytest

from eol_cal.ecu.client import ecu_state
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.ecu.transport import open_bus
from eol_cal.sim.loopback import SIM_ECU_TIMING
from eol_cal.sim.remote_ecu import spawn_remote


def _serial(url: str) -> str:
    bus = open_bus("remote", url)
    try:
        return ecu_state(bus, timing=SIM_ECU_TIMING).serial
    finally:
        bus.shutdown()


def test_a_tester_reaches_it_and_the_next_motor_comes_behind_the_same_url(tmp_path):
    ecu = spawn_remote(tmp_path / "a.flash", config=SimConfig(serial="P-1"))
    try:
        url = ecu.url
        assert url.startswith("ws://127.0.0.1:")
        assert ecu.process.pid != os.getpid()
        assert _serial(url) == "P-1"
        assert (tmp_path / "a.flash").exists()  # the child's simulator made its flash file before it answered
        ecu.replace(tmp_path / "b.flash", SimConfig(serial="P-2"))
        assert ecu.url == url and _serial(url) == "P-2"
    finally:
        ecu.close()
    assert ecu.process.returncode == 0
    ecu.close()  # twice is once


def test_a_simulator_that_cannot_start_says_why(tmp_path):
    (tmp_path / "file").write_text("not a directory")
    ecu = spawn_remote(tmp_path / "file" / "x.flash")
    try:
        with pytest.raises(RuntimeError, match=r"ECU simulator process: cannot start on .*x\.flash"):
            ecu.url  # noqa: B018 - reading it waits for the child's answer
    finally:
        ecu.close()
    assert ecu.process.returncode == 0


def test_a_replacement_that_cannot_start_says_why_and_the_next_one_comes(tmp_path):
    (tmp_path / "file").write_text("not a directory")
    ecu = spawn_remote(tmp_path / "a.flash", config=SimConfig(serial="P-3"))
    try:
        with pytest.raises(RuntimeError, match=r"cannot replace the ECU with .*x\.flash"):
            ecu.replace(tmp_path / "file" / "x.flash", SimConfig(serial="P-4"))
        ecu.replace(tmp_path / "c.flash", SimConfig(serial="P-5"))
        assert _serial(ecu.url) == "P-5"
    finally:
        ecu.close()


def test_the_child_ends_when_its_parent_is_gone(tmp_path):
    ecu = spawn_remote(tmp_path / "a.flash")
    assert ecu.url
    assert ecu.process.stdin is not None
    ecu.process.stdin.close()  # what the parent's death does to the child's command pipe
    assert ecu.process.wait(30) == 0
    ecu.close()
