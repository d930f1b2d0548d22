"""The report pages without a station: the same inputs give the same bytes, a record that
lacks parts (a run that ended early, fields older records do not have) still renders, and
every limit is a row with its margin."""

from __future__ import annotations


import numpy as np
import pytest

from eol_cal.sim.run_records import make_record
from eol_cal.records.limits import LIMIT_KEYS, VariantLimits

LIMITS = VariantLimits.of("T", max_k6=0.0025, max_pp_before_pct=25.0, max_pp_after_pct=2.0,
                          min_improvement_pct=40.0, min_r2=0.3, max_rms_nm=0.1, max_ci_k6_rel=0.05,
                          max_ci_phase_k6_deg=3.0, max_ci_c6_nm=0.01, max_hall_deviation_deg=3.0, source="limits.toml")


def error_record(**limits):
    """A run that ended in the acquisition after the prepare step: no fit, no metrics, no calibrated block."""
    return make_record("E-1", started="2026-11-23T10:00:00.000+00:00", variant="T", station=None,
                       limits={**LIMITS.values, **limits}, error_step="acquire")


def test_a_record_without_fit_renders_every_limit_as_not_measured():
    from eol_cal.report.motor_page import limit_rows, render_motor_report

    rec = error_record()
    rows = limit_rows(rec)
    judged = [k for k in LIMIT_KEYS if getattr(LIMITS, k) is not None]  # an optional limit left off is no row
    assert "max_pp_after_no_mech1_pct" not in judged
    assert [r.key for r in rows] == judged
    assert {r.status for r in rows} == {"not measured"}
    html = render_motor_report(rec, [])
    assert 'id="verdict" class="verdict error">ERROR<' in html
    assert html.count('class="limit-row"') == len(judged)
    every_optional = {"max_pp_after_no_mech1_pct": 1.0, "max_mech1_after_nm": 0.002, "min_model_check_p": 0.001}
    assert [r.key for r in limit_rows(error_record(**every_optional))] == list(LIMIT_KEYS)
    assert "simulated fault" in html and 'id="no-plots"' in html
    assert "operator</th><td>not recorded" in html


def test_limit_rows_show_the_records_checks_in_display_units():
    from eol_cal.report.motor_page import limit_rows, render_motor_report

    rec = make_record("F-1", variant="T", limits=dict(LIMITS.values), pp_before=5.0, pp_after=2.5, k6=0.0011)
    assert rec.verdict == "fail" and rec.reasons == ("p-p ripple compensated = 2.5 % exceeds max_pp_after_pct = 2 %",)
    rows = {r.key: r for r in limit_rows(rec)}
    after = rows["max_pp_after_pct"]
    assert (after.value, after.limit, after.status) == (2.5, 2.0, "FAIL")
    assert after.margin == pytest.approx(-0.5)
    assert rows["max_pp_before_pct"].status == "PASS" and rows["max_pp_before_pct"].margin == pytest.approx(20.0)
    imp = rows["min_improvement_pct"]  # 50 % against at least 40 %: a min limit's margin is value - limit
    assert imp.status == "PASS" and imp.margin == pytest.approx(10.0)
    k6 = rows["max_k6"]  # one unit per quantity: k6 in mN*m/A
    assert (k6.value, k6.limit, k6.unit, k6.status) == (pytest.approx(1.1), pytest.approx(2.5), "mN*m/A", "PASS")
    # the report shows what the record says; it never judges again: a check marked failed is FAIL
    import dataclasses

    forged = dataclasses.replace(rec, checks=tuple(dataclasses.replace(c, passed=False) if c.key == "max_k6" else c
                                                   for c in rec.checks))
    assert {r.key: r.status for r in limit_rows(forged)}["max_k6"] == "FAIL"
    html = render_motor_report(rec, [])
    assert "1.1 ± " in html and "mN*m/A" in html and "N*m/A<" not in html.replace("mN*m/A", "")


@pytest.fixture(scope="module")
def fitted():
    """A real fit of synthetic captures (six load points) and the ripple at the 65 A point."""
    from eol_cal.analysis.fit import FitSpec, fit_many
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.capture.synthetic import synthetic_capture
    from eol_cal.analysis.point_metrics import point_ripple

    points = [(120.0, 20.0), (120.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
    caps = [synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.5, seed=i, theta_r0=0.7 * i, serial="R-1",
                              k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1) for i, (rpm, iq) in enumerate(points)]
    (mi,) = motor_inputs(caps)
    spec = FitSpec(harmonics=(6, 12))
    (fit,) = fit_many([mi.segments], spec)
    before = point_ripple(mi.captures[1], mi.angles[1])
    flat = synthetic_capture(rpm=120.0, i_qo=65.0, seconds=0.5, seed=9, serial="R-1", k6=0.00003, c6=0.0002)
    from eol_cal.analysis.angle import capture_angle

    after = point_ripple(flat, capture_angle(flat))
    return mi, fit, spec, (before, after)


@pytest.mark.slow
def test_the_same_inputs_give_the_same_page_bytes(fitted, tmp_path):
    from eol_cal.station.report_files import write_report

    mi, fit, spec, pr = fitted
    rec = at_point(make_record("R-1", variant="T", limits=dict(LIMITS.values), pp_before=pr[0].pp_pct,
                               pp_after=pr[1].pp_pct), 120.0, 65.0)
    pages = []
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        pages.append(write_report(rec, tmp_path / d, fit_extra=(mi, fit, spec), point_ripple=pr).read_bytes())
    assert pages[0] == pages[1]
    html = pages[0].decode()
    assert html.count('<svg') == 3
    assert html.count('id="residual-segment-') == mi.segments.n_segments
    # ids are unique on the page although every figure defines its own clip paths and glyphs
    import re

    ids = re.findall(r'\bid="([^"]+)"', html)
    assert len(ids) == len(set(ids))


def at_point(rec, speed_rpm: float, i_qo_a: float):
    """The record with its operating point moved (fit and metrics)."""
    import dataclasses

    from eol_cal.analysis.motor_result import OperatingPoint

    return dataclasses.replace(rec, fit=dataclasses.replace(rec.fit, operating_point=OperatingPoint(speed_rpm, i_qo_a)),
                               metrics=dataclasses.replace(rec.metrics, speed_rpm=speed_rpm, i_qo_a=i_qo_a))


def lot_record(serial: str, started: str, verdict: str, k6: float = 1.0e-3, after: float = 0.8,
               station: str = "L1-S1"):
    """A run record as the station writes it: ``fail`` by its compensated p-p, ``error`` in the acquisition,
    ``refused`` by the pre-flight (a wrong serial)."""
    kw = dict(started=started, station=station, variant="T", limits=dict(LIMITS.values), k6=k6, pp_before=5.0,
              pp_after=2.5 if verdict == "fail" else after)
    if verdict == "error":
        return make_record(serial, error_step="acquire", **kw)
    if verdict == "refused":
        return make_record(serial, refused=("wrong_serial",), **kw)
    return make_record(serial, **kw)


def test_records_plot_is_against_time_with_limits_and_error_runs():
    from eol_cal.lot.lot_page import timeline_figure
    from eol_cal.rendering.figures import pyplot

    recs = [lot_record("A", "2026-11-22T09:00:00+00:00", "pass"),
            lot_record("B", "2026-11-22T12:00:00+00:00", "error"),
            lot_record("C", "2026-11-22T10:00:00+00:00", "fail", after=2.5),
            lot_record("D", "2026-11-23T08:00:00+00:00", "error")]
    fig = timeline_figure(recs, "lot")
    try:
        def by_gid(gid):
            return fig.findobj(lambda a: a.get_gid() == gid)

        (k6,) = by_gid("runs-k6")
        import matplotlib.dates as mdates

        # x is the start time, in time order (C at 10:00 before B's error at 12:00)
        x = k6.get_offsets()[:, 0]
        assert list(mdates.num2date(x[i]).hour for i in range(2)) == [9, 10]
        assert len(by_gid("error-runs")) == 2
        (lim,) = by_gid("limit-max_k6")
        assert set(lim.get_ydata()) == {LIMITS.max_k6 * 1e3}
        assert by_gid("limit-max_pp_after_pct") and by_gid("limit-max_pp_before_pct")
    finally:
        pyplot().close(fig)


@pytest.fixture(scope="module")
def lot_db(tmp_path_factory):
    """A records database of 24 production runs on two stations and 2 refusals; one motor's report page exists."""
    from eol_cal.report.motor_page import render_motor_report
    from eol_cal.records.write import insert_records

    d = tmp_path_factory.mktemp("lot")
    rng = np.random.default_rng(3)
    recs = []
    for i in range(24):
        verdict = "error" if i % 11 == 5 else ("fail" if i % 7 == 3 else "pass")
        recs.append(lot_record(f"M{i:03d}", f"2026-11-{20 + i // 12}T{8 + i % 12:02d}:00:00.000+00:00", verdict,
                               k6=float(rng.normal(1.0e-3, 1e-4)), after=float(abs(rng.normal(0.9, 0.3))),
                               station=f"L1-S{1 + i % 2}"))
    # a mis-scan before M000's first run and a dead dyno after its pass: neither is M000's result
    recs += [lot_record("M000", "2026-11-20T07:00:00.000+00:00", "refused", station="L1-S1"),
             lot_record("M000", "2026-11-22T08:00:00.000+00:00", "refused", station="L1-S1")]
    run_dir = d / "reports" / "M003_run"
    run_dir.mkdir(parents=True)
    import dataclasses

    recs[3] = dataclasses.replace(recs[3], report_dir=str(run_dir))
    (run_dir / "report.html").write_text(render_motor_report(recs[3], []))
    insert_records(d / "lot.sqlite", recs)
    return {"dir": d, "db": d / "lot.sqlite", "records": recs}


@pytest.mark.slow
def test_lot_report_cli_writes_the_same_page_twice_and_filters(lot_db):
    from click.testing import CliRunner

    from cli.main import cli

    out = lot_db["dir"] / "pages"
    runner = CliRunner()
    pages = []
    for name in ("a.html", "b.html"):
        res = runner.invoke(cli, ["lot", "report", "--db", str(lot_db["db"]), "-o", str(out / name)])
        assert res.exit_code == 0, res.output
        pages.append((out / name).read_bytes())
    assert pages[0] == pages[1]
    html = pages[0].decode()
    assert html.count('class="worst-row"') == 15 and 'href="../reports/M003_run/report.html"' in html
    res = runner.invoke(cli, ["lot", "report", "--db", str(lot_db["db"]), "--station", "L1-S2", "--since", "2026-11-21",
                              "-o", str(out / "s2.html")])
    assert res.exit_code == 0 and "(6 runs)" in res.output  # the refusals are of station L1-S1
    res = runner.invoke(cli, ["lot", "report", "--db", str(lot_db["db"]), "--since", "21-11-2026", "-o", str(out / "x.html")])
    assert res.exit_code == 2 and "since" in res.output and "YYYY-MM-DD" in res.output
    assert not (out / "x.html").exists()


@pytest.mark.slow
def test_lot_page_in_chromium_offline_hover_and_zoom(lot_db, tmp_path):
    from _chromium import Chromium, element_sizes, marked_processes, not_blank
    from playwright.sync_api import expect

    from eol_cal.lot.lot_page import write_lot_page

    page = write_lot_page(lot_db["records"], tmp_path / "lot.html", title="lot.sqlite", filters={"variant": None})
    with Chromium() as b:
        log = b.open(page.as_uri())
        running = marked_processes(b.marker)  # the browser's processes, seen by the check after it closes
        p = b.page
        sizes = element_sizes(p, "svg.plot")
        # hover text: one <title> per drawn point, naming the serial
        k6_titles = p.locator('[id="timeline-runs-k6"] use > title').all_text_contents()
        pass_rate = p.locator("#pass-rate").text_content()
        fpy = p.locator("#fpy").text_content()
        quantity_rows = p.locator("tr.quantity-row").evaluate_all("rs => rs.map(r => r.dataset.key)")
        causes = p.locator("tr.cause-row td:first-child").all_text_contents()
        refusals = p.locator("tr.refusal-row").all_text_contents()
        worst = dict(p.locator("tr.worst-row").evaluate_all("rs => rs.map(r => [r.cells[0].textContent, "
                                                             "r.cells[1].textContent])"))
        expect(p.locator("#refused")).to_have_text("2")
        control_lines = p.locator("[id^=control-L1-S][id$=-cl-k6-ucl]").count()
        few = p.locator("[id^=control-L1-S][id$=-few-k6]").count()
        cpk = p.locator("tr.quantity-row[data-key=k6] td.cpk").text_content()
        # zoom: the mouse wheel over a chart narrows its viewBox, a double-click restores it
        chart = p.locator("#fig-timeline svg").first
        before = chart.get_attribute("viewBox")
        chart.hover()
        p.mouse.wheel(0, -100)
        expect(chart).not_to_have_attribute("viewBox", before)
        zoomed = chart.get_attribute("viewBox")
        chart.dblclick()
        expect(chart).to_have_attribute("viewBox", before)
        shot = b.screenshot(tmp_path / "lot.png")
        log_after = b.open(page.as_uri())  # events of the zoom: none may be an error
    assert len(running) >= 2 and b.left_behind == []  # the browser and its renderer at least; none left
    assert log.console_errors == [] and log_after.console_errors == []
    assert set(log.requests) == {page.as_uri()}
    # timeline, histograms, Pareto, one control chart per station
    assert [s["id"] for s in sizes] == ["fig-timeline", "fig-histograms", "fig-pareto", "fig-refusals",
                                        "fig-control-L1-S1", "fig-control-L1-S2"]
    assert all(s["w"] > 100 and s["h"] > 100 for s in sizes), sizes
    measured = [r for r in lot_db["records"] if r.kind == "production"]
    with_k6 = sorted((r for r in measured if r.fit), key=lambda r: r.started_at)
    assert len(k6_titles) == len(with_k6) and all(t.startswith(r.serial) for t, r in zip(k6_titles, with_k6, strict=True))
    judged = [r for r in measured if r.verdict != "error"]
    assert pass_rate == f"{100 * sum(r.verdict == 'pass' for r in judged) / len(judged):.1f} %"
    first = {}
    for r in sorted(measured, key=lambda r: r.started_at):
        first.setdefault(r.serial, r.verdict)
    assert first["M000"] == "pass"  # its first measured run; the mis-scan before it measured nothing
    assert fpy == f"{100 * sum(v == 'pass' for v in first.values()) / len(first):.1f} %"
    # the refusals: their own Pareto; M000's latest measured run passed (the dead dyno after it is no result)
    assert refusals == ["wrong_serial2100 %"]
    assert worst.get("M000", "PASS") == "PASS"
    assert quantity_rows == ["k6", "phase_k6", "c6", "phase_c6", "pp_before_pct", "pp_after_pct", "improvement_pct",
                             "fit_r2", "fit_rms_nm"]
    assert sorted(causes) == ["error in acquire", "max_pp_after_pct"]
    # 10 or 11 runs with a k6 per station, 20 in the lot: no control limits and no Cpk below n = 25, said so
    assert control_lines == 0 and few == 2
    assert cpk == f"n = {len(with_k6)} < 25"
    assert float(zoomed.split()[2]) < float(before.split()[2])
    colours, spread = not_blank(shot)
    assert colours > 50 and spread > 10


@pytest.mark.parametrize("n", [3, 40])
def test_hover_titles_go_on_every_point_in_data_order(n):
    """matplotlib writes few points as paths and many as <use> of one marker; both get their
    title, in the data's order, and a count that does not match is refused."""
    import re

    from eol_cal.rendering.figures import pyplot
    from eol_cal.report.svg import figure_svg

    def fig():
        f, ax = pyplot().subplots(figsize=(3, 2))
        ax.scatter(np.arange(n), np.arange(n) ** 2, c=(["tab:red", "tab:green"] * n)[:n], gid="pts")
        return f

    svg = figure_svg(fig(), "f", {"pts": [f"P{i}" for i in range(n)]})
    assert re.findall(r"<title>(P\d+)</title>", svg) == [f"P{i}" for i in range(n)]
    xs = [float(x) for x in re.findall(r'<use [^>]*? x="([-\d.]+)"[^>]*><title>', svg)] or \
         [float(m) for m in re.findall(r'<path d="M ([-\d.]+) [^>]*><title>', svg)]
    assert xs == sorted(xs) and len(xs) == n
    with pytest.raises(ValueError, match="points drawn"):
        figure_svg(fig(), "f", {"pts": ["only one"] * (n + 1)})


@pytest.mark.slow
def test_a_large_lot_draws_its_points_as_an_image_without_hover_text(lot_db, monkeypatch, tmp_path):
    import eol_cal.lot.lot_page as lot

    monkeypatch.setattr(lot, "MAX_HOVER_POINTS", 5)
    html = lot.write_lot_page(lot_db["records"], tmp_path / "big.html", title="big", filters={}).read_text()
    import re

    # only the few points beyond the control limits keep their hover text
    titles = re.findall(r"<title>([^<]*)</title>", html.split("</head>")[1])
    assert all(t.endswith("beyond the control limits") for t in titles) and "data:image/png;base64" in html
    assert "More than 5 runs: points without hover text" in html


@pytest.mark.slow
def test_a_plot_that_cannot_be_drawn_says_why_and_the_page_is_still_written(fitted, tmp_path):
    """Ripple data without angles (a caller that does not keep them): the angle plot says why,
    the other plots are drawn and the page is written."""
    import dataclasses

    from eol_cal.station.report_files import write_report

    mi, fit, spec, pr = fitted
    broken = tuple(dataclasses.replace(p, theta_r=None) for p in pr)
    rec = at_point(make_record("R-1"), 120.0, 65.0)
    html = write_report(rec, tmp_path, fit_extra=(mi, fit, spec), point_ripple=broken).read_text()
    assert html.count('class="plot-error"') == 1 and "This plot could not be drawn: TypeError" in html
    assert html.count("<svg") == 2


def test_the_report_shows_the_mechanical_orders_and_the_identification_margin():
    """A run of revision 1.2 (the demo record): the block's switch, the margin, the fitted orders,
    order 1 before and with the compensation."""
    import json
    from pathlib import Path

    from eol_cal.report.motor_page import mech_section, render_motor_report
    from eol_cal.records.record import RunRecord

    doc = json.loads((Path(__file__).resolve().parents[1] / "fixtures" / "run_record_demo.json").read_text())
    rec = RunRecord.from_json(doc, "run_record_demo.json")
    sec = mech_section(rec)
    assert sec["status"].startswith("MECH_COMP_ENABLE on: predicted identification margin 0.8")
    assert [row[0] for row in sec["rows"]] == [1, 2, 3]
    assert "mN*m" in sec["rows"][0][1] and "uncompensated" in sec["rows"][0][2]
    html = render_motor_report(rec, [])
    assert 'id="mech"' in html and "Mechanical orders" in html
    assert "the mechanical orders are compensated too" in html


def _drawn_texts(fig):
    """Every visible, non-empty text of ``fig`` with its extent in pixels (the figure drawn once
    on Agg), and the renderer."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    # an axis keeps tick labels beyond its view that it does not draw: only the drawn ones count
    ticks = {id(t) for ax in fig.axes for axis in (ax.xaxis, ax.yaxis) for t in axis.get_ticklabels(which="both")}
    drawn = {id(lab) for ax in fig.axes for axis in (ax.xaxis, ax.yaxis)
             for tick in axis._update_ticks() for lab in (tick.label1, tick.label2)}
    return [(t, t.get_window_extent(renderer)) for t in fig.findobj(Text)
            if t.get_visible() and t.get_text().strip() and (id(t) not in ticks or id(t) in drawn)], renderer


@pytest.mark.parametrize("draw", ["angle", "spectrum", "residual", "residual in rows"])
def test_the_report_figures_fixed_margins_keep_every_label_on_the_figure_and_clear_of_the_panels(
        fitted, draw, monkeypatch):
    """The report's figures are laid out by fixed margins, not by measuring them (``tight_layout``
    drew each once more): every label must still lie on the figure, and the axis labels clear of
    the tick labels and panels beside them."""
    from eol_cal.report import motor_page as mp

    mi, fit, spec, pr = fitted
    rec = at_point(make_record("R-1", variant="T", limits=dict(LIMITS.values), pp_before=pr[0].pp_pct,
                               pp_after=pr[1].pp_pct), 120.0, 65.0)
    figs = []
    real = mp.figure_svg
    monkeypatch.setattr(mp, "figure_svg", lambda fig, name, *a, **k: (figs.append(fig), real(fig, name, *a, **k))[1])
    {"angle": lambda: mp.angle_figure(rec, pr, (mi, fit, spec)), "spectrum": lambda: mp.spectrum_figure(rec, pr),
     "residual": lambda: mp.residual_figure((mi, fit, spec)),
     "residual in rows": lambda: mp.residual_figure((mi, fit, spec), cols=2)}[draw]()
    (fig,) = figs
    page = fig.bbox
    texts, renderer = _drawn_texts(fig)
    assert texts
    for t, box in texts:
        assert page.x0 - 1 <= box.x0 and box.x1 <= page.x1 + 1 and page.y0 - 1 <= box.y0 and box.y1 <= page.y1 + 1, \
            (t.get_text(), box, page)
    # the y axis' labels (and the figure's) left of the tick labels in the left half, the x axis'
    # labels below those in the bottom half: (x or y, the page's half, the label's far edge, the ticks' near edge)
    ticks = {}
    for xy, half, far, near in (("y", page.x0 + page.width / 2, "x1", "x0"), ("x", page.y0 + page.height / 2, "y1", "y0")):
        axis, sup = f"{xy}axis", f"_sup{xy}label"
        labels = [getattr(ax, axis).label for ax in fig.axes if getattr(ax, axis).label.get_text()] + \
            ([getattr(fig, sup)] if getattr(fig, sup, None) is not None else [])
        ticks[xy] = [box for t, box in texts if t in {lab for ax in fig.axes for lab in getattr(ax, axis).get_ticklabels()}]
        for label in labels:
            edge = getattr(label.get_window_extent(renderer), far)
            assert all(edge <= getattr(box, near) + 1 for box in ticks[xy] if getattr(box, near) < half), label.get_text()
    # panels side by side do not overlap each other's tick labels
    for i, a in enumerate(ticks["x"]):
        for b in ticks["x"][i + 1:]:
            assert not a.overlaps(b), (a, b)
