"""Lock files opened as untrusted paths (eol_cal.infra.lockfile): a symbolic link or a FIFO planted
at a lock's path is refused, never followed or waited on, and nothing it points to changes; the
panel's station lock, the record journal's in-flight lock and the kept programs' compile lock."""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

import pytest

from eol_cal.errors import InputError
from eol_cal.infra.lockfile import NotALockFile, open_lock_file, refusal
from eol_cal.numerics import exported
from eol_cal.panel.serve import station_lock
from eol_cal.records.spool import hold_in_flight

PRECIOUS = "the quality engineer's notes\n" * 20


def _victim(tmp_path: Path) -> Path:
    v = tmp_path / "victim.txt"
    v.write_text(PRECIOUS)
    return v


def _returns_soon(fn, *args) -> BaseException | object:
    """``fn(*args)``'s result or exception, from a thread joined within 20 s (an ``open()`` that
    waits on a FIFO's writer would block forever: the test fails instead of hanging)."""
    out: list = []

    def run() -> None:
        try:
            out.append(fn(*args))
        except BaseException as e:  # noqa: BLE001 - handed to the test
            out.append(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(20.0)
    assert out, f"{fn.__name__} blocked on {args}"
    return out[0]


def test_a_lock_file_is_opened_only_as_a_regular_file(tmp_path: Path) -> None:
    fd = open_lock_file(tmp_path / "ok.lock")
    os.close(fd)
    assert (tmp_path / "ok.lock").is_file()

    link = tmp_path / "link.lock"
    link.symlink_to(_victim(tmp_path))
    with pytest.raises(OSError) as e:
        open_lock_file(link)
    assert e.value.errno == errno.ELOOP and "symbolic link" in refusal(e.value)

    fifo = tmp_path / "fifo.lock"
    os.mkfifo(fifo)
    got = _returns_soon(open_lock_file, fifo)
    assert isinstance(got, NotALockFile) and "not a regular file" in refusal(got)

    (tmp_path / "dir.lock").mkdir()
    with pytest.raises(OSError) as e:
        open_lock_file(tmp_path / "dir.lock")
    assert "directory" in refusal(e.value)
    assert (tmp_path / "victim.txt").read_text() == PRECIOUS


def test_the_panels_station_lock_refuses_a_link_and_leaves_its_target_alone(tmp_path: Path) -> None:
    # before: the lock followed the link, truncated the target and wrote its pid and address into it
    (tmp_path / "locks").mkdir()
    victim = _victim(tmp_path)
    (tmp_path / "locks" / "panel-EOL-T.lock").symlink_to(victim)
    with pytest.raises(InputError) as e, station_lock(tmp_path / "locks", "EOL-T", "http://127.0.0.1:1/"):
        pass
    assert "panel-EOL-T.lock" in str(e.value) and "symbolic link" in str(e.value)
    assert victim.read_text() == PRECIOUS

    os.mkfifo(tmp_path / "locks" / "panel-EOL-U.lock")

    def enter() -> None:
        with station_lock(tmp_path / "locks", "EOL-U", "x"):
            pass

    got = _returns_soon(enter)
    assert isinstance(got, InputError) and "not a regular file" in str(got)


def test_the_journals_in_flight_lock_refuses_a_link_unlocked(tmp_path: Path) -> None:
    import fcntl

    victim = _victim(tmp_path)
    (tmp_path / ".in-flight").mkdir()
    (tmp_path / ".in-flight" / "RUN1.lock").symlink_to(victim)
    with pytest.raises(OSError):  # the verdict's journal then goes on without the lock (decide_verdict.journal)
        hold_in_flight(tmp_path, "RUN1")
    assert victim.read_text() == PRECIOUS
    with victim.open("rb") as f:  # nobody holds the link's target
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    held = hold_in_flight(tmp_path, "RUN2")  # a plain one still works
    held.release()


def test_the_compile_lock_goes_on_unlocked_past_a_link(tmp_path: Path) -> None:
    victim = _victim(tmp_path)
    (tmp_path / "p.lock").symlink_to(victim)
    with exported.one_at_a_time(tmp_path / "p.lock") as held:
        assert held is False
    assert victim.read_text() == PRECIOUS
