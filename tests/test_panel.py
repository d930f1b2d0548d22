"""The operator panel's and the line view's server without a browser: the actions checked as the
terminal loop checks its input, the bind and credentials rules, one panel per station, the live
state from the cycle's events, and the line's figures from a records database (SQLite here; the
browser tests run them on PostgreSQL). A real uvicorn server on 127.0.0.1, a free port; urllib as
the client."""

from __future__ import annotations

import base64
import datetime as dt
import json
import threading
import urllib.error
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.msa.master import MasterSettings
from eol_cal.msa.rules import change
from eol_cal.panel.app import line_app, panel_app
from eol_cal.panel.controls import Controls, Scan
from eol_cal.panel.line import LineWatch, line_state, shift_of
from eol_cal.panel.serve import (Credentials, PanelBusy, listening_socket, load_credentials, parse_bind, served,
                                 station_lock)
from eol_cal.panel.state import PanelState, trace_points
from eol_cal.records.write import insert_records
from eol_cal.sim.run_records import make_record
from eol_cal.station.executor import StepEvent

RULES = MasterSettings("M-MASTER", {"k6": 0.62}, {"k6": 0.05}, every_h=8.0, source="test")


def _call(url: str, path: str, body: dict | None = None, headers: dict | None = None, raw: bytes | None = None,
          content_type: str = "application/json") -> tuple[int, dict | str]:
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    req = urllib.request.Request(url + path, data=data, method="GET" if data is None else "POST",
                                 headers={**({"Content-Type": content_type} if data is not None else {}), **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            text = r.read().decode()
            return r.status, json.loads(text) if r.headers.get_content_type() == "application/json" else text
    except urllib.error.HTTPError as exc:
        text = exc.read().decode()
        return exc.code, json.loads(text) if exc.headers.get_content_type() == "application/json" else text


@pytest.fixture
def panel():
    """A panel's server (no cycle behind it): its URL, state and controls."""
    state = PanelState("EOL-T")
    controls = Controls(state)
    closing = threading.Event()
    with served(panel_app(controls, closing.is_set), listening_socket("127.0.0.1", 0), closing) as url:
        yield SimpleNamespace(url=url, state=state, controls=controls)


def test_no_action_without_an_operator_and_names_checked_as_the_terminal_loop_does(panel):
    status, doc = _call(panel.url, "scan", {"line": "M-0001"})
    assert status == 403 and "sign in" in doc["error"]
    assert _call(panel.url, "stop", {})[0] == 403
    status, doc = _call(panel.url, "signin", {"name": "  "})
    assert status == 400 and "printable" in doc["error"]
    # the answer and the state the page is sent say the same: the page shows whichever comes last
    assert doc["error"] == panel.state.get("message")["text"]
    assert _call(panel.url, "signin", {"name": " alice "}) == (200, {"ok": True, "result": "alice"})
    assert panel.state.get("operator") == "alice"


def test_a_scan_is_checked_with_scanned_serial_and_a_markup_serial_is_refused_as_text(panel):
    _call(panel.url, "signin", {"name": "alice"})
    status, doc = _call(panel.url, "scan", {"line": "<b>M1</b>"})
    assert status == 400 and doc["error"].startswith("not a serial: ") and "'<' not allowed" in doc["error"]
    message = panel.state.get("message")  # one text for the answer and the state: no race on the page
    assert (message["level"], message["text"]) == ("error", doc["error"])
    status, doc = _call(panel.url, "scan", {"line": " M-0001\t\r"})
    assert (status, doc["result"]) == (200, "M-0001")
    assert panel.controls.next_scan() == Scan("M-0001", "alice")
    assert _call(panel.url, "scan", {"line": "M-0002"})[0] == 409  # one waits already (phase "starting")


def test_actions_need_a_json_body_from_the_page_origin(panel):
    _call(panel.url, "signin", {"name": "alice"})
    assert _call(panel.url, "scan", raw=b"line=M-1", content_type="application/x-www-form-urlencoded")[0] == 415
    assert _call(panel.url, "scan", {"line": "M-1"}, headers={"Origin": "http://evil.example"})[0] == 403
    assert _call(panel.url, "scan", raw=b"[1]")[0] == 400
    assert _call(panel.url, "scan", raw=b"x" * 5000)[0] == 413
    assert _call(panel.url, "stop", {})[0] == 409  # no motor runs
    assert _call(panel.url, "state")[0] == 200
    status, page = _call(panel.url, "")
    assert status == 200 and "<script src=\"panel.js\"" in page


def test_every_response_forbids_inline_script_and_foreign_content(panel):
    with urllib.request.urlopen(panel.url, timeout=30) as r:
        csp = r.headers["Content-Security-Policy"]
    assert "script-src 'self'" in csp and "default-src 'none'" in csp and "unsafe-inline" not in csp


def test_another_host_than_loopback_needs_credentials(tmp_path):
    assert parse_bind("127.0.0.1:0", None) == ("127.0.0.1", 0)
    assert parse_bind("localhost:8080", None) == ("localhost", 8080)
    with pytest.raises(InputError, match="--credentials"):
        parse_bind("0.0.0.0:8080", None)
    with pytest.raises(InputError, match="--credentials"):
        parse_bind("10.1.2.3:8080", None)
    assert parse_bind("0.0.0.0:8080", Credentials("line", "x" * 12)) == ("0.0.0.0", 8080)
    r = CliRunner().invoke(cli, ["line", "--db", str(tmp_path / "r.sqlite"), "--bind", "0.0.0.0:0"])
    assert r.exit_code == 2 and "--credentials" in r.output
    r = CliRunner().invoke(cli, ["station", "--demo", "--out", str(tmp_path / "d"), "--bind", "127.0.0.1:0"])
    assert r.exit_code == 2 and "--panel" in r.output


def test_a_credentials_file_is_private_and_strong_and_every_request_needs_it(tmp_path):
    f = tmp_path / "cred.toml"
    f.write_text('user = "line"\npassword = "correct-horse-battery"\n')
    f.chmod(0o644)
    with pytest.raises(InputError, match="chmod 600"):
        load_credentials(f)
    f.chmod(0o600)
    creds = load_credentials(f)
    assert creds.user == "line" and "correct" not in repr(creds)
    f.write_text('user = "line"\npassword = "short"\n')
    with pytest.raises(InputError, match="12 characters"):
        load_credentials(f)
    closing = threading.Event()
    state = PanelState("EOL-T")
    with served(panel_app(Controls(state), closing.is_set, creds), listening_socket("127.0.0.1", 0), closing) as url:
        assert _call(url, "state")[0] == 401
        assert _call(url, "state", headers={"Authorization": "Basic " + base64.b64encode(b"line:wrong").decode()})[0] == 401
        good = "Basic " + base64.b64encode(b"line:correct-horse-battery").decode()
        assert _call(url, "state", headers={"Authorization": good})[0] == 200


def test_one_panel_per_station(tmp_path):
    with station_lock(tmp_path, "EOL-T", "http://127.0.0.1:1/"):
        with pytest.raises(PanelBusy, match=r"already runs \(pid \d+, http://127.0.0.1:1/"), \
                station_lock(tmp_path, "EOL-T", "http://127.0.0.1:2/"):
            pass
        with station_lock(tmp_path, "EOL-U", "other station"):
            pass
    with station_lock(tmp_path, "EOL-T", "again"):  # released with the first
        pass


def test_a_port_in_use_is_refused_naming_bind():
    first = listening_socket("127.0.0.1", 0)
    try:
        with pytest.raises(InputError, match="--bind.*cannot listen"):
            listening_socket("127.0.0.1", first.getsockname()[1])
    finally:
        first.close()


class Captured:
    """What the panel reads of a capture: ``t``, ``has``, its channels by name."""

    def __init__(self, t, channels):
        self.t, self.channels = t, channels

    def has(self, name):
        return name in self.channels

    def __getitem__(self, name):
        return self.channels[name]


def test_the_state_follows_the_cycles_events_with_the_captures_trace():
    state = PanelState("EOL-T", "alice")
    state.begin("M-1")
    v0 = state.version
    t = np.linspace(0, 2, 20000)
    ctx = SimpleNamespace(before=Captured(t, {"torque": 1.0 + 0.01 * np.sin(6 * 2 * np.pi * t)}))
    state.observe(StepEvent("r1", "M-1", "acquire", "start", "m"))
    state.observe(StepEvent("r1", "M-1", "acquire", "done", "m", 6.5, ctx))
    snap = state.snapshot()
    assert snap["version"] > v0 and snap["steps"][0]["step"] == "acquire" and snap["steps"][0]["seconds"] == 6.5
    (trace,) = snap["traces"]
    assert trace["label"] == "calibration capture" and len(trace["t"]) == 600
    assert max(trace["torque"]) == pytest.approx(1.01, abs=1e-4)  # the peaks stay at any length


def test_a_report_written_after_the_next_scan_was_taken_updates_the_verdict_and_the_last_motors():
    """The report thread's outcome (cli/panel.py): where the report and the record went, and a verdict a
    failed report made an error, on the verdict still shown and in the last motors; a run no longer
    shown changes only its line among the last motors."""
    import dataclasses

    state = PanelState("EOL-T", "alice")
    state.begin("M-1")
    shown = make_record("M-1", run_id="a" * 32, k6=0.65e-3)
    state.verdict_known(shown)
    state.finished(shown, None, "being written (safe in the spool; the report and the database follow)",
                   {"runs": 1})
    assert state.get("phase") == "idle" and state.get("verdict")["record"].startswith("being written")
    final = dataclasses.replace(shown, verdict="error", reasons=("report: disk full",), report_error="OSError: disk full")
    state.written(final, None, "database r.sqlite")
    v = state.get("verdict")
    assert (v["verdict"], v["record"], v["reasons"]) == ("error", "database r.sqlite", ["report: disk full"])
    assert state.get("last")[0]["verdict"] == "error"
    state.begin("M-2")  # the next motor: the first one's verdict put away, its line stays
    state.written(dataclasses.replace(shown, verdict="fail"), "/r/report.html", "database r.sqlite")
    assert state.get("verdict") is None and state.get("last")[0]["verdict"] == "fail"


def test_trace_points_keep_short_captures_whole():
    t = np.arange(10.0)
    assert trace_points(t, t * 2)["torque"] == [float(x) for x in t * 2]


def test_the_line_view_per_station_fpy_shift_yield_and_a_due_master(tmp_path):
    db = tmp_path / "line.sqlite"
    now = dt.datetime.now(dt.UTC).replace(microsecond=0)
    at = [(now - dt.timedelta(minutes=m)).isoformat(timespec="milliseconds") for m in (50, 40, 30, 20, 10)]
    insert_records(db, [
        make_record("A-1", started=at[0], station="L-A", k6=2e-3),  # fails, then passes: first pass lost
        make_record("A-1", started=at[1], station="L-A"),
        make_record("A-2", started=at[2], station="L-A"),
        make_record("B-1", started=at[3], station="L-B"),
        make_record("B-2", started=at[4], station="L-B", refused=("dyno_not_ready",)),
    ])
    change(db, "L-B", RULES, set_by="qe")
    before = db.read_bytes()
    doc = line_state(db, (dt.time(6), dt.time(14), dt.time(22)))
    assert db.read_bytes() == before  # read only
    a, b = doc["stations"]
    assert (a["station"], a["state"], a["runs"], a["fpy"], a["yield"]) == ("L-A", "pass", 3, 0.5, 2 / 3)
    assert [r["serial"] for r in a["last"]] == ["A-2", "A-1", "A-1"]
    assert b["state"] == "blocked" and "master check due" in b["gate"] and b["runs"] == 1
    assert any("L-B" in x and "master check due" in x for x in doc["alarms"])
    assert doc["fpy"] == pytest.approx(2 / 3)
    assert sum(r["runs"] for r in doc["shifts"]) == 4


def test_shift_of_a_run_before_the_first_shift_start_is_yesterdays_last():
    shifts = (dt.time(6), dt.time(14), dt.time(22))
    assert shift_of("2026-11-28T05:59:00+00:00", shifts) == "2026-11-27 22:00"
    assert shift_of("2026-11-28T14:00:00+00:00", shifts) == "2026-11-28 14:00"


def test_the_line_view_has_no_action_and_says_when_it_cannot_read(tmp_path):
    watch = LineWatch(tmp_path / "missing.sqlite", (dt.time(6),), None, 0.5)
    watch.read()
    assert "database not found" in watch.snapshot()["error"]
    closing = threading.Event()
    with served(line_app(watch, closing.is_set), listening_socket("127.0.0.1", 0), closing) as url:
        assert _call(url, "state")[1]["error"].startswith("cannot read the records")
        assert _call(url, "scan", {"line": "M-1"})[0] in (404, 405)
        status, page = _call(url, "")
        assert status == 200 and "line.js" in page


def test_a_baseline_rule_broken_by_the_latest_run_is_an_alarm_on_the_panel_and_the_line(tmp_path):
    from eol_cal.lot.baseline import baseline_of_db, store
    from eol_cal.panel.line import station_alarms

    db = tmp_path / "line.sqlite"
    now = dt.datetime.now(dt.UTC).replace(microsecond=0)
    rng = np.random.default_rng(7)

    def at(minutes: int) -> str:
        return (now - dt.timedelta(minutes=minutes)).isoformat(timespec="milliseconds")

    # 30 runs around k6 0.64 mN*m/A: the frozen line; then a motor inside the limit but far outside the line
    insert_records(db, [make_record(f"A-{i}", started=at(200 - i), station="L-A", k6=0.64e-3 + 2e-6 * rng.standard_normal())
                        for i in range(30)])
    baseline = baseline_of_db(db, "week-48", {"stations": ["L-A"]})
    store(db, baseline)
    assert station_alarms(db, "L-A", baseline) == []
    assert line_state(db, (dt.time(6),), baseline)["stations"][0]["state"] == "pass"
    insert_records(db, [make_record("A-99", started=at(1), station="L-A", k6=0.70e-3)])
    (alarm,) = station_alarms(db, "L-A", baseline)
    assert "k6 breaks rule 1 of baseline 'week-48'" in alarm and "A-99" in alarm
    doc = line_state(db, (dt.time(6),), baseline)
    assert doc["stations"][0]["state"] == "alarm" and doc["alarms"] == [alarm]
    assert station_alarms(db, "L-B", baseline) == []
