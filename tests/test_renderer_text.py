"""Text that reaches a renderer (issue 23, class 5): serials, station ids, variants, failure
causes, file and database names from records and inputs are drawn and printed as written, never
interpreted: not as matplotlib math text (``$\\foo{$`` was a ParseFatalException in ``lot
report``, ``analyze --plot``, ``simulate --plot``), not as rich markup (``[/]`` was a
MarkupError), and a record's ``report_dir`` never becomes a link with a URL scheme."""

from __future__ import annotations

import json
import re
import sqlite3
from pathlib import Path

import pytest
from click.testing import CliRunner

from _capture_helpers import small_capture
from cli.main import cli
from eol_cal.capture.io import write_capture
from eol_cal.rendering.renderer import file_link, literal_texts, plain, pyplot

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"

#: matplotlib math text that does not parse, valid math text, a lone dollar, rich markup, an emoji code
HOSTILE = (r"$\foo{$", "$x^2$", r"a\$b$", "[/]", "[bold red]x", ":smile:")


def _ok(res) -> None:
    assert res.exit_code == 0, res.output
    assert "Traceback" not in res.output and "Error" not in res.output.split("\n")[-1], res.output


@pytest.mark.parametrize("text", HOSTILE)
def test_plain_text_is_drawn_as_written_and_the_net_catches_what_was_not_escaped(text):
    plt = pyplot()
    fig, ax = plt.subplots()
    try:
        title = ax.set_title(plain(text))
        raw = ax.set_xlabel(text)  # not escaped: the net draws it literally if it does not parse
        ax.set_yscale("log")  # tick labels keep their math text
        literal_texts(fig)
        fig.canvas.draw()
        dollars = title.get_text().count("$") - title.get_text().count(r"\$")
        assert dollars == 0  # no math left in the escaped text
        assert raw.get_text() == text
    finally:
        plt.close(fig)


@pytest.mark.parametrize("text", HOSTILE)
def test_analyze_and_capture_info_take_a_hostile_serial_and_file_name(tmp_path, text):
    cap = small_capture()
    cap.metadata["serial"] = text
    path = tmp_path / f"cap {text.replace('/', '_')}.csv"
    write_capture(cap, path)
    png = tmp_path / f"plot {text.replace('/', '_')}.png"
    res = CliRunner().invoke(cli, ["analyze", str(path), "--plot", str(png)])
    _ok(res)
    assert png.stat().st_size > 0
    res = CliRunner().invoke(cli, ["capture", "info", str(path)])
    assert res.exit_code in (0, 2) and "Traceback" not in res.output, res.output
    assert text in res.stdout  # printed as written, not eaten as markup


@pytest.mark.slow  # a plant simulation per case: 20 s
@pytest.mark.parametrize("text", [r"$\foo{$", "[/]"])
def test_simulate_plots_a_hostile_serial(tmp_path, text):
    png = tmp_path / "sim.png"
    res = CliRunner().invoke(cli, ["simulate", "--serial", text, "-o", str(tmp_path / "s.csv"), "--plot", str(png),
                                   "--seconds", "0.2", "--speed-rpm", "60", "--iq", "10"])
    _ok(res)
    assert png.stat().st_size > 0


def _hostile_db(tmp_path: Path, report_dir: str) -> Path:
    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records

    base = json.loads((FIXTURES / "run_record_demo.json").read_text())
    recs = []
    for k, text in enumerate(HOSTILE):
        rec = json.loads(json.dumps(base))
        rec["run_id"] = f"{k:032x}"
        rec["serial"] = f"S{k}{text}"
        rec["station"]["id"] = f"line {text}"
        rec["limits"]["variant"] = f"V{text}"
        rec["report_dir"] = report_dir
        if k % 2:
            rec["verdict"] = "fail"
            rec["reasons"] = [f"{text}: too much ripple"]
        recs.append(rec)
    db = tmp_path / "lot $\\foo{$ [red].sqlite"
    insert_records(db, [RunRecord.from_json(r) for r in recs])
    return db


@pytest.mark.slow  # a lot page: 13 s
def test_lot_report_and_records_plot_take_hostile_records_and_link_only_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # a directory that exists under the name a hostile record gives as its report_dir
    evil = tmp_path / "javascript:alert(1)"
    evil.mkdir()
    (evil / "report.html").write_text("<p>x</p>")
    db = _hostile_db(tmp_path, "javascript:alert(1)")
    page = tmp_path / "lot.html"
    res = CliRunner().invoke(cli, ["lot", "report", "--db", str(db), "-o", str(page)])
    _ok(res)
    html = page.read_text()
    hrefs = re.findall(r'href="([^"]*)"', html)
    assert hrefs, "the existing report should be linked"
    for href in hrefs:
        assert ":" not in href.split("/")[0] or href.startswith("#"), href  # no scheme: a relative file path
    assert "javascript%3Aalert%281%29/report.html" in hrefs
    assert "<script>alert" not in html
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--plot", str(tmp_path / "r.png")])
    _ok(res)
    assert "S3[/]" in res.stdout  # the serial printed as written
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db)])
    assert res.exit_code in (0, 1) and "Traceback" not in res.output, res.output


def test_file_link_is_relative_and_percent_encoded(tmp_path):
    target = tmp_path / "a b:c" / "report.html"
    target.parent.mkdir()
    target.write_text("x")
    assert file_link(target, tmp_path) == "a%20b%3Ac/report.html"
    assert file_link(tmp_path / "missing.html", tmp_path) is None
    assert file_link(tmp_path, tmp_path) is None  # a directory is not a file to link
    with sqlite3.connect(tmp_path / "x.sqlite"):
        pass
