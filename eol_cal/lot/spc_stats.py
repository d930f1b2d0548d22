"""The SPC parts of a lot's statistics, as the ``lot stats`` document and the lot page show them.

Over a :class:`eol_cal.lot.runs.Lot` (display units), with the definitions of
:mod:`eol_cal.lot.stats` and :mod:`eol_cal.lot.spc` (``docs/spc.md``):

- :func:`capability_groups`: Cp/Cpk/Ppk per variant (all its stations) and per variant and
  station, each against that variant's limit, gated by the minimum n; never across variants.
- :func:`circular_figures`: a phase's circular mean, circular sd and histogram on the circle.
- :func:`control_limits`: the individuals / moving-range limits of the charted quantities per
  station, gated by the minimum n.
- :func:`judge_lot`: each variant and station's runs against a frozen baseline: Nelson's
  rules that fire, with the runs, and the lines judged against.
"""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Iterable

import numpy as np

from eol_cal.lot.baseline import Baseline, line_document
from eol_cal.lot.runs import Lot, Quantity
from eol_cal.lot.spc import (CIRCULAR, DEFAULT_MIN_N, RULES, circular_histogram, circular_summary, gate, gated_capability,
                             judge, natural_floor)
from eol_cal.lot.stats import imr_limits

#: sectors of a phase's histogram on the circle (15 deg each)
CIRCLE_BINS = 24


def _limits(q: Quantity, value: float) -> tuple[float | None, float | None]:
    return (None, value) if q.sense == "max" else (value, None)


def capability_groups(lot: Lot, q: Quantity, min_n: int = DEFAULT_MIN_N) -> list[dict[str, Any]]:
    """Capability of one quantity per variant (``station`` None: all its stations) and per
    variant and station, against the variant's limit; each index a value or None with its
    ``*_reason``. Variants without the limit, and phases (no two-sided limit), have none."""
    if q.limit_key is None or q.key in CIRCULAR:
        return []
    x = lot.display(q)
    out = []
    for variant, vidx in lot.variants():
        limits = lot.variant_limit_values(q, variant)
        if not limits:
            continue
        groups = [(None, vidx)] + [(s, vidx[lot.station[vidx] == s]) for s in sorted(set(lot.station[vidx].tolist()))]
        for station, idx in groups:
            xs = x[idx]
            n = int(np.count_nonzero(np.isfinite(xs)))
            item: dict[str, Any] = {"variant": variant, "station": station, "n": n, "limit_key": q.limit_key,
                                    "limit": limits[0] if len(limits) == 1 else None}
            if len(limits) > 1:
                why = f"{q.limit_key} changed within the lot ({', '.join(f'{v:g}' for v in limits)})"
                figures = {k: gate(None, n, 0, why) for k in ("cp", "cpk", "ppk")}
            else:
                figures = gated_capability(xs, *_limits(q, limits[0]), min_n=min_n)
            for name, g in figures.items():
                item[name], item[f"{name}_reason"] = g.value, g.reason
            out.append(item)
    return out


def lot_capability(groups: list[dict[str, Any]], lot: Lot) -> dict[str, Any]:
    """The lot-wide figures of a quantity's ``quantities`` entry: the one variant's (all stations)
    when the lot holds one variant, else None with the reason."""
    names = ("cp", "cpk", "ppk")
    whole = [g for g in groups if g["station"] is None]
    if len(whole) == 1 and len(lot.variants()) == 1:
        return {k: whole[0][k] for n in names for k in (n, f"{n}_reason")}
    why = "the lot mixes variants: capability per variant" if len(whole) > 1 or len(lot.variants()) > 1 else "no limit"
    return {k: (None if not k.endswith("_reason") else why) for n in names for k in (n, f"{n}_reason")}


def circular_figures(lot: Lot, q: Quantity, bins: int = CIRCLE_BINS) -> dict[str, Any]:
    """A phase's circular mean and sd (display units: deg), the mean resultant length and the
    histogram on the circle (``edges`` from -180 to 180 deg, ``counts``)."""
    theta = lot.values[q.key]  # rad
    s = circular_summary(theta)
    counts, edges = circular_histogram(theta, bins)
    return {"mean": s.mean * q.scale, "sd": s.sd * q.scale, "resultant": s.resultant,
            "histogram": {"edges": (edges * q.scale).tolist(), "counts": counts.tolist()}}


def control_limits(lot: Lot, charted: Iterable[Quantity], min_n: int = DEFAULT_MIN_N) -> dict[str, dict[str, Any]]:
    """Per station, per charted quantity: ``runs``, ``n`` (runs with the value) and the I-MR
    limits of the station's own runs (None with ``reason`` when ``n < min_n``); an amplitude's
    LCL held at its natural zero, with the ``note`` that says so."""
    out: dict[str, dict[str, Any]] = {}
    charted = list(charted)
    for station, idx in lot.stations():
        out[station] = {}
        for q in charted:
            x = lot.display(q)[idx]
            x = x[np.isfinite(x)]
            g = gate(0.0, len(x), min_n)
            cl = imr_limits(x)
            figures = {k: (getattr(cl, k) if g.reason is None else None) for k in ("center", "ucl", "lcl", "mr_center", "mr_ucl")}
            floor = natural_floor(q.key)
            note = None
            if floor is not None and figures["lcl"] is not None and figures["lcl"] < floor:
                figures["lcl"], note = floor, f"LCL at the natural zero (centre - 2.66 MRbar = {cl.lcl:.4g} {q.unit})"
            out[station][q.key] = {"runs": len(idx), "n": len(x), **figures, "reason": g.reason, "note": note}
    return out


def judge_lot(lot: Lot, baseline: Baseline, quantities: Iterable[Quantity]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Each variant and station's runs (time order) against the baseline's lines.

    Returns
    -------
    violations : list of dict
        ``rule``, ``text``, ``side``, ``quantity``, ``variant``, ``station``, ``runs`` (run ids),
        ``serials``, ``started_at``, ``values`` (display units), ``index`` (positions in the lot);
        by first run.
    judged : list of dict
        Per quantity, variant and station: the baseline line (display units) and ``n``; a group
        the baseline has no line for, or one without limits, has ``reason`` and is not judged.
    """
    violations: list[dict[str, Any]] = []
    judged: list[dict[str, Any]] = []
    for variant, vidx in lot.variants():
        for station in sorted(set(lot.station[vidx].tolist())):
            idx = vidx[lot.station[vidx] == station]
            for q in quantities:
                line = baseline.line(q.key, variant, station)
                x = lot.values[q.key][idx]
                n = int(np.count_nonzero(np.isfinite(x)))
                head = {"quantity": q.key, "unit": q.unit, "variant": variant, "station": station}
                if line is None:
                    judged.append({**head, "runs": n, "reason": f"baseline {baseline.name!r} has no line for it"})
                    continue
                doc = line_document(line, q.scale)
                doc["reason"] = None if line.reason is None else f"baseline: {line.reason}"
                judged.append({**head, "runs": n, **{f"baseline_{k}" if k == "n" else k: v for k, v in doc.items()}})
                for v in judge(x, line, q.key):
                    pos = idx[list(v.runs)]
                    violations.append({"rule": v.rule, "text": v.text, "side": v.side_word,
                                       **head, "runs": lot.run_id[pos].tolist(), "serials": lot.serial[pos].tolist(),
                                       "started_at": lot.started_at[pos].tolist(),
                                       "values": [float(y) for y in lot.display(q)[pos]], "index": pos.tolist()})
    violations.sort(key=lambda v: (v["index"][0], v["rule"], v["quantity"]))
    return violations, judged


def rules_by_run(violations: Iterable[dict[str, Any]]) -> dict[str, list[str]]:
    """Per run id, the rules it is part of as ``QUANTITY:RULE`` (``k6:1``): the CSV's column."""
    out: dict[str, list[str]] = {}
    for v in violations:
        for rid in v["runs"]:
            tag = f"{v['quantity']}:{v['rule']}"
            if tag not in out.setdefault(rid, []):
                out[rid].append(tag)
    return {rid: sorted(tags, key=lambda t: (t.rsplit(":", 1)[0], int(t.rsplit(":", 1)[1]))) for rid, tags in out.items()}


def rule_texts() -> dict[str, str]:
    """The rules in words, by number (the JSON's ``rules``)."""
    return {str(k): v[3] for k, v in RULES.items()}


def gated_text(value: float | None, reason: str | None, digits: int = 3) -> str:
    """A gated figure of the document for people: the value, or why there is none (``n = 7 < 25``)."""
    if value is None or not math.isfinite(value):
        return reason or "-"
    return f"{value:.{digits}g}"


def quantity_note(q: dict[str, Any]) -> str:
    """One line of a ``quantities`` entry: mean and sd (a phase's on the circle), Cpk and Ppk or
    why not (the lot page's histogram titles)."""
    if q["circular"]:
        return f"circular mean {gated_text(q['mean'], None, 4)}, sd {gated_text(q['sd'], None)} {q['unit']}"
    text = f"mean {gated_text(q['mean'], None, 4)}, sd {gated_text(q['sd'], None)}"
    if q["limit_key"] and q["capability"]:
        text += f"; Cpk {gated_text(q['cpk'], q['cpk_reason'], 2)}, Ppk {gated_text(q['ppk'], q['ppk_reason'], 2)}"
    return text
