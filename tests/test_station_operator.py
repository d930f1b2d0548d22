"""``eol-cal station --demo`` driven through a real pseudo-terminal, as an operator (or a barcode
scanner) would drive it: prompts, typed serials, the large verdicts, Ctrl-C as a signal to the
process group, and the records the session leaves in the database.

Real processes and parts: the CLI in its own session on a pty (stdlib ``pty``), per motor a
loopback ECU simulator (python-can-remote) and dyno simulator (pymodbus) on 127.0.0.1 with the
plant, SQLite. Each simulated motor takes about 10-15 s.
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import signal
import sqlite3
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from cli.station import DEMO_LIMITS
from eol_cal.sim.loopback import demo_motor_spec
from eol_cal.station.operator_session import demo_seed

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop

ROOT = Path(__file__).resolve().parent.parent
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07|\r")
MOTOR_S = 180.0  # one motor's budget on a loaded shared machine (about 15 s alone)
#: a hang guard for every other line the session prints (a prompt, a report written, the summary):
#: what is checked is what comes and in which order; 10 s was a race with the report step at load 16
PROMPT_S = 120.0
PASSING = ("M-0001", "M-0002")  # plant motors 1 and 2: k6 0.65 and 0.64 mN*m/A
FAILING = "M-0003"  # plant motor 3: k6 0.81 mN*m/A


class Terminal:
    """``eol-cal ARGS`` with a pseudo-terminal as its stdin, stdout and stderr, in its own session."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 160, 0, 0))
        # the suite's cache directory kept (its programs, not the user's ~/.cache), the rest of ours not
        env = {k: v for k, v in os.environ.items()
               if (not k.startswith("EOL_CAL_") or k == "EOL_CAL_JAX_CACHE") and k != "COLUMNS"}
        env.update(PYTHONPATH=str(ROOT), TERM="xterm-256color")
        self.proc = subprocess.Popen([sys.executable, "-m", "cli.main", *args], stdin=slave, stdout=slave,
                                     stderr=slave, cwd=cwd, env=env, start_new_session=True, close_fds=True)
        os.close(slave)
        self.text = ""
        self.pos = 0

    def _read(self, timeout: float) -> bool:
        ready, _, _ = select.select([self.master], [], [], timeout)
        if not ready:
            return False
        try:
            data = os.read(self.master, 65536)
        except OSError:  # EIO: the child closed the terminal
            return False
        self.text += ANSI.sub("", data.decode("utf-8", "replace"))
        return bool(data)

    def expect(self, pattern: str, timeout: float) -> re.Match:
        """Wait for ``pattern`` after the last match; the match."""
        end = time.monotonic() + timeout
        rx = re.compile(pattern)
        while True:
            m = rx.search(self.text, self.pos)
            if m:
                self.pos = m.end()
                return m
            if time.monotonic() > end or (not self._read(0.5) and self.proc.poll() is not None):
                raise AssertionError(f"{pattern!r} not seen; exit {self.proc.poll()}; output:\n{self.text[-4000:]}")

    def type(self, line: str, enter: str = "\n") -> None:
        os.write(self.master, (line + enter).encode())

    def interrupt(self) -> None:
        """Ctrl-C: SIGINT to the process group, as the terminal sends it."""
        os.killpg(self.proc.pid, signal.SIGINT)

    def exit_code(self, timeout: float = 120.0) -> int:
        end = time.monotonic() + timeout
        while self.proc.poll() is None and time.monotonic() < end:
            self._read(0.2)
        while self._read(0.05):
            pass
        return self.proc.wait(1)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        os.close(self.master)


@pytest.fixture
def terminal():
    started: list[Terminal] = []

    def start(args: list[str], cwd: Path) -> Terminal:
        started.append(Terminal(args, cwd))
        return started[-1]

    yield start
    for t in started:
        t.close()


def _rows(db: Path) -> list[tuple]:
    with sqlite3.connect(db) as con:
        return con.execute("SELECT serial, verdict, station, operator, reasons FROM runs ORDER BY started_at").fetchall()


def test_three_motors_one_failing_then_an_empty_line(tmp_path, terminal):
    # one limit between the plant motors' k6: the third motor is drawn with a k6 above it
    k6 = {s: demo_motor_spec(demo_seed(s), s).k6 for s in (*PASSING, FAILING)}
    low, high = max(k6[s] for s in PASSING), k6[FAILING]
    assert high > 1.2 * low
    max_k6 = (low + high) / 2
    limits = tmp_path / "tight.toml"
    limits.write_text(re.sub(r"max_k6 = [0-9.]+", f"max_k6 = {max_k6:.6f}", DEMO_LIMITS))
    out = tmp_path / "session"
    t = terminal(["station", "--demo", "--out", str(out), "--limits", str(limits), "--station-id", "L1-TEST"], tmp_path)
    t.expect(r"Operator: ", PROMPT_S)
    t.type("alice")
    t.expect(r"Scan serial \(Enter or q ends the session\): ", PROMPT_S)
    t.type("  bad serial!  ")  # a space inside: refused, asked again
    t.expect(r"not a serial: 'bad serial!': character ' ' not allowed", PROMPT_S)
    t.expect(r"Scan serial", PROMPT_S)
    t.type("X" * 17)
    t.expect(r"17 characters, at most 16", PROMPT_S)
    # a scanner's Enter is a CR (the terminal makes it a newline); some send CR LF: the LF, an
    # empty line, must not end the session
    # the next serial is asked for at the verdict: each motor's report follows while the next one runs,
    # and where it went is said at a later prompt (the last ones when the session ends)
    for serial, word, enter in ((PASSING[0], "PASS", "\r"), (FAILING, "FAIL", "\r\n"), (PASSING[1], "PASS", "\r")):
        t.expect(r"Scan serial", PROMPT_S)
        t.type(f" {serial}\t", enter=enter)
        t.expect(rf"{serial}: {word}", MOTOR_S)
    t.expect(r"Scan serial", PROMPT_S)
    t.type("")
    t.expect(r"session: 3 run\(s\) of 3 motor\(s\): 2 pass, 1 fail, 0 error", PROMPT_S)
    reports = re.findall(r"(\S+) report: \S+report\.html", t.text)
    assert reports == [PASSING[0], FAILING, PASSING[1]], t.text[-3000:]
    assert t.exit_code() == 0, t.text[-3000:]
    assert "fail: k6 " in t.text and "max_k6" in t.text
    assert (out / "lot.html").is_file() and "lot page: " in t.text
    rows = _rows(out / "results.sqlite")
    assert [(r[0], r[1], r[2], r[3]) for r in rows] == [
        (PASSING[0], "pass", "L1-TEST", "alice"), (FAILING, "fail", "L1-TEST", "alice"),
        (PASSING[1], "pass", "L1-TEST", "alice")]
    assert "max_k6" in rows[1][4]


def test_ctrl_c_between_motors_ends_the_session_cleanly(tmp_path, terminal):
    out = tmp_path / "session"
    t = terminal(["station", "--demo", "--out", str(out), "--operator", "bob"], tmp_path)
    t.expect(r"Scan serial", PROMPT_S)
    t.type(PASSING[0])
    t.expect(rf"{PASSING[0]}: PASS", MOTOR_S)
    t.expect(r"Scan serial", PROMPT_S)
    time.sleep(0.3)  # waiting in the prompt
    t.interrupt()
    t.expect(r"Ctrl-C between motors: the session ends", PROMPT_S)
    t.expect(r"session: 1 run\(s\) of 1 motor\(s\): 1 pass, 0 fail, 0 error", PROMPT_S)
    assert t.exit_code() == 0, t.text[-3000:]
    assert [(r[0], r[1], r[2], r[3]) for r in _rows(out / "results.sqlite")] == [(PASSING[0], "pass", "DEMO", "bob")]


def test_ctrl_c_during_a_motor_records_an_error_and_exits_2(tmp_path, terminal):
    out = tmp_path / "session"
    t = terminal(["station", "--demo", "--out", str(out), "--operator", "carol"], tmp_path)
    t.expect(r"Scan serial", PROMPT_S)
    t.type(PASSING[1])
    t.expect(rf"{PASSING[1]}: acquire", MOTOR_S)  # the dyno is turning
    time.sleep(0.5)
    t.interrupt()
    t.expect(rf"{PASSING[1]}: ERROR", PROMPT_S)
    t.expect(r"session: 1 run\(s\) of 1 motor\(s\): 0 pass, 0 fail, 1 error", PROMPT_S)
    assert t.exit_code() == 2, t.text[-3000:]
    (row,) = _rows(out / "results.sqlite")
    assert row[:4] == (PASSING[1], "error", "DEMO", "carol") and "acquire" in row[4]
    assert (out / "lot.html").is_file()  # a lot of one error run (no k6 to plot) has its page too


def test_end_of_input_at_the_operator_prompt_runs_nothing(tmp_path, terminal):
    t = terminal(["station", "--demo", "--out", str(tmp_path / "s")], tmp_path)
    t.expect(r"Operator: ", PROMPT_S)
    os.write(t.master, b"\x04")  # Ctrl-D: end of input
    t.expect(r"no operator: the session ends", PROMPT_S)
    assert t.exit_code() == 0
    assert not (tmp_path / "s" / "results.sqlite").exists()


@pytest.mark.parametrize("line, reason", [("", "empty"), ("M 1", "' ' not allowed"), ("M-1\x1b", "'\\x1b'"),
                                          ("Mé1", "'é' not allowed"), ("A" * 17, "17 characters")])
def test_a_scanned_line_that_is_no_serial_is_refused_with_the_reason(line, reason):
    from eol_cal.errors import InputError
    from eol_cal.station.operator_session import scanned_serial

    with pytest.raises(InputError) as info:
        scanned_serial(line)
    assert info.value.field == "serial" and reason in info.value.reason
    assert scanned_serial(" \tM-0001.a_B \r\n") == "M-0001.a_B"


def test_demo_serials_name_the_demo_motors():
    assert demo_seed("DEMO-0003") == 3 and demo_seed("M-17") == 17
    assert demo_seed("ABC") == demo_seed("ABC") != demo_seed("ABD")
