"""Exit codes (issue 23, class 7): bad input is exit 2 whichever option carries it (``refit``'s
limits, variant, motor and bench were exit 1, one error row per capture; a scheduler address that
is malformed or down was a traceback), and a run that is signalled again while it ends still
ends with exit 2, not by the signal."""

from __future__ import annotations

import signal
import socket
import time

import pytest
from click.testing import CliRunner

from cli.main import cli
from test_station_kill import _wait_for_erase, station  # noqa: F401 - the fixture: ECU simulator process, dyno simulator

from eol_cal.records.query import query_records


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def lot_dir(tmp_path):
    from _capture_helpers import small_capture
    from eol_cal.capture.io import write_capture

    d = tmp_path / "lot"
    d.mkdir()
    write_capture(small_capture(serial="R-1"), d / "R-1.csv")
    return d


def _two(res, *words: str) -> None:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output, res.output
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("error:"), res.output
    for w in words:
        assert w in line, res.output


@pytest.mark.parametrize("args, words", [
    (["--limits", "{bad}"], ["not valid TOML"]),
    (["--limits", "{limits}", "--variant", "NOPE"], ["variant", "NOPE"]),
    (["--variant", "EPS-STD"], ["variant", "without --limits"]),
    (["--motor", "no-such-motor"], ["no-such-motor"]),
    (["--bench", "no-such-bench"], ["bench"]),
    (["--scheduler", "garbage"], ["scheduler"]),
    (["--scheduler", "http://127.0.0.1:8786"], ["scheduler"]),
    (["--scheduler", "tcp://a b:8786"], ["scheduler"]),
])
def test_refit_bad_input_is_exit_2_before_any_cluster_starts(tmp_path, lot_dir, args, words):
    from pathlib import Path

    bad = tmp_path / "bad.toml"
    bad.write_text("x = \n")
    limits = Path(__file__).resolve().parents[1] / "fixtures" / "limits.toml"
    argv = ["refit", str(lot_dir), "-o", str(tmp_path / "rows.jsonl"), *[a.format(bad=bad, limits=limits) for a in args]]
    _two(CliRunner().invoke(cli, argv), *words)
    assert not (tmp_path / "rows.jsonl").exists()


@pytest.mark.slow  # waits out the connect timeout: 10 s
def test_refit_with_a_scheduler_that_is_down_is_one_line_exit_2(tmp_path, lot_dir):
    res = CliRunner().invoke(cli, ["refit", str(lot_dir), "-o", str(tmp_path / "rows.jsonl"),
                                   "--scheduler", f"tcp://127.0.0.1:{_free_port()}"])
    _two(res, "scheduler", "cannot connect")


# a station process each (6-8 s): the first gap stays in the fast loop
@pytest.mark.parametrize("gap_s", [0.0] + [pytest.param(g, marks=pytest.mark.slow) for g in (0.3, 1.0, 2.5)])
def test_a_second_signal_while_the_run_ends_is_still_exit_2(station, gap_s):  # noqa: F811 - the fixture
    """SIGINT during the flash, then SIGINT again ``gap_s`` later: while the run records its
    error, writes its report, or is already exiting (threads, atexit). Every time: exit 2, no
    traceback, the record kept."""
    start, tmp_path, dyno = station
    ecu, run = start("--slow", "erase:3")
    _wait_for_erase(tmp_path, run)  # the prepare flash has sent its erase
    time.sleep(1.0)  # inside the slowed erase
    run.send_signal(signal.SIGINT)
    time.sleep(gap_s)
    if run.poll() is None:
        run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=120)
    assert run.returncode == 2, err
    assert "Traceback" not in err, err
    recs = query_records(tmp_path / "db.sqlite")
    assert [r.verdict for r in recs] == ["error"]
    assert not dyno.enabled and dyno.speed == 0.0
