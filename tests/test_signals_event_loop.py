"""A signal that comes while the dyno transfer builds its event loop ends the command with the one
Interrupted, not an "Exception ignored ... Traceback" when the half-built loop is collected (seen
on a loaded machine in ``eol-cal acquire``: tests/test_signals_acquire.py). The signal is
delivered deterministically, inside the loop's constructor, as the CLI's handler delivers it."""

from __future__ import annotations

import asyncio
import gc
import sys
import threading

import pytest

from eol_cal.infra import interrupts
from eol_cal.dyno import transfer
from eol_cal.errors import Interrupted


@pytest.fixture
def signal_inside_the_loop_constructor(monkeypatch):
    """SIGINT arrives after the loop's selector is made and before its self-pipe is."""
    original = asyncio.selector_events.BaseSelectorEventLoop._make_self_pipe

    def make_self_pipe(self):
        interrupts.deliver("SIGINT")
        original(self)

    monkeypatch.setattr(asyncio.selector_events.BaseSelectorEventLoop, "_make_self_pipe", make_self_pipe)
    unraisable: list[sys.UnraisableHookArgs] = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    interrupts.reset()
    yield unraisable
    interrupts.reset()


def _collect(unraisable: list) -> list[str]:
    gc.collect()
    return [f"{type(u.exc_value).__name__}: {u.exc_value}" for u in unraisable]


def test_the_stream_reader_interrupted_while_it_builds_its_loop(signal_inside_the_loop_constructor):
    with pytest.raises(Interrupted) as info:
        transfer.BufferReader(transfer.DynoConfig(host="127.0.0.1", port=1))
    assert info.value.signal_name == "SIGINT"
    del info  # its traceback holds the loop
    assert _collect(signal_inside_the_loop_constructor) == []
    assert [t for t in threading.enumerate() if t.name == "dyno-stream" and t.is_alive()] == []


def test_the_whole_buffer_read_interrupted_while_it_builds_its_loop(signal_inside_the_loop_constructor):
    with pytest.raises(Interrupted) as info:
        transfer.read_capture_buffer(transfer.DynoConfig(host="127.0.0.1", port=1), ["torque"], 10)
    del info  # its traceback holds the loop
    assert _collect(signal_inside_the_loop_constructor) == []
