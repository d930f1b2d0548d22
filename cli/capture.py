"""``eol-cal capture info|convert``: describe a capture file, convert between formats."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import contextlib

from cli.common import CommandExit, console, handle_errors, print_json, styled
from cli.paths import io_paths


def _finite_range(values: Any) -> tuple[float | None, float | None, int]:
    import numpy as np

    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    if not finite.any():
        return None, None, int(values.size)
    return float(values[finite].min()), float(values[finite].max()), int((~finite).sum())


def capture_summary(capture: Any, file_format: str, problem: Any) -> dict[str, Any]:
    """The ``capture info --json`` document (keys documented in docs/capture.md)."""
    import numpy as np

    from eol_cal.capture.data import CANONICAL_CHANNELS
    from eol_cal.capture.validate import hall_changes, rising_edges, states_seen

    t = capture.t
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    channels = []
    for name in ("t", *capture.channels):
        lo, hi, bad = _finite_range(capture[name])
        channels.append(
            {
                "name": name,
                "unit": CANONICAL_CHANNELS.get(name, "?"),
                "dtype": str(np.asarray(capture[name]).dtype),
                "min": lo,
                "max": hi,
                "non_finite": bad,
            }
        )
    meta = capture.metadata
    encoder: dict[str, Any] = {
        "enc_a_rising_edges": rising_edges(capture["enc_a"]) if capture.has("enc_a") else None,
        "enc_b_rising_edges": rising_edges(capture["enc_b"]) if capture.has("enc_b") else None,
        "edges_per_electrical_rev": None,
    }
    with contextlib.suppress(KeyError, TypeError, ValueError, ZeroDivisionError):
        encoder["edges_per_electrical_rev"] = 2 * int(meta["encoder_ppr"]) / int(meta["poles"])
    hall: dict[str, Any] = {"states_seen": None, "changes": None}
    if capture.has("hall"):
        values = np.asarray(capture["hall"])
        finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values
        hall = {"states_seen": states_seen(finite), "changes": hall_changes(values)}
    from eol_cal.infra.jsonsafe import json_safe

    # a header's NaN kt or a NaN time stamp is what a bad capture holds: null in the document (the
    # problem says why), never a ValueError from the JSON writer
    return json_safe({
        "file": capture.source,
        "format": file_format,
        "samples": int(len(t)),
        "t_start_s": float(t[0]) if len(t) else None,
        "duration_s": duration,
        "sample_rate_hz": (len(t) - 1) / duration if duration > 0 else None,
        "channels": channels,
        "metadata": dict(meta),
        "truth_keys": sorted(capture.truth),
        "events": {name: int(len(ev[0])) for name, ev in capture.events.items()},
        "encoder": encoder,
        "hall": hall,
        "valid": problem is None,
        "problem": None if problem is None else {"file": problem.file, "field": problem.field, "reason": problem.reason},
    })


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.6g}"


def _print_summary(s: dict[str, Any]) -> None:
    from rich.table import Table

    rate = _fmt(s["sample_rate_hz"])
    console.print(styled((str(s["file"]), "bold"), f" ({s['format']}): {s['samples']} samples, {_fmt(s['duration_s'])} s "
                         f"at {rate} Hz"))
    table = Table("channel", "unit", "min", "max", "non-finite", "events")
    for ch in s["channels"]:
        events = s["events"].get(ch["name"])
        table.add_row(
            ch["name"], ch["unit"], _fmt(ch["min"]), _fmt(ch["max"]), str(ch["non_finite"]),
            "-" if events is None else str(events)
        )
    console.print(table)
    meta = Table("metadata", "value")
    for key, value in s["metadata"].items():
        meta.add_row(key, repr(value) if isinstance(value, str) and value != value.strip() else str(value))
    console.print(meta)
    if s["truth_keys"]:
        console.print(f"simulator truth keys (not read by analyses): {', '.join(s['truth_keys'])}")
    enc, hall = s["encoder"], s["hall"]
    console.print(
        f"encoder: A {enc['enc_a_rising_edges']} rising edges, B {enc['enc_b_rising_edges']}; "
        f"{_fmt(enc['edges_per_electrical_rev'])} A edges per electrical revolution"
    )
    console.print(f"hall: states seen {hall['states_seen']}, {hall['changes']} changes")
    if s["valid"]:
        console.print(styled(("valid", "green"), ": passes every capture-format check"))


@click.group("capture")
def capture_group() -> None:
    """Inspect and convert capture files (.csv, .mf4)."""


@capture_group.command("info")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--map", "map_file", type=click.Path(dir_okay=False), help="Channel map (TOML) for a foreign file.")
@click.option("--json", "as_json", is_flag=True, help="One JSON document on stdout (keys in docs/capture.md).")
@handle_errors
def info(file: str, map_file: str | None, as_json: bool) -> None:
    """Channels, units, ranges, rate, metadata, encoder edges, hall states and validity of FILE.

    Exit code 2 when the file cannot be read or the capture fails a check (the summary is
    still printed, the problem goes to stderr).
    """
    from eol_cal.capture import load_channel_map, read_capture
    from eol_cal.capture.file_options import SUFFIX_FORMATS
    from eol_cal.capture.io import capture_format
    from eol_cal.capture.validate import validate
    from eol_cal.errors import InputError

    channel_map = load_channel_map(map_file) if map_file else None
    capture = read_capture(file, channel_map, validate=False)
    problem = None
    try:
        validate(capture)
    except InputError as exc:
        problem = exc
    suffix = Path(file).suffix.lower()
    # csv, mf4, tdms by their suffix; a file of another suffix as what its map says it is (text, ...)
    file_format = suffix.lstrip(".") if suffix in SUFFIX_FORMATS else capture_format(file, channel_map)
    summary = capture_summary(capture, file_format, problem)
    if as_json:
        print_json({"schema": "eol-cal/capture-info/1", **summary})
    else:
        _print_summary(summary)
    if problem is not None:
        click.echo(f"error: invalid capture: {problem}", err=True)
        raise CommandExit(problem.exit_code)


@capture_group.command("convert")
@click.argument("src", metavar="IN", type=click.Path(dir_okay=False))
@click.argument("dst", metavar="OUT", type=click.Path(dir_okay=False))
@click.option("--map", "map_file", type=click.Path(dir_okay=False), help="Channel map (TOML) for a foreign IN.")
@click.option(
    "--digital",
    type=click.Choice(["levels", "events"]),
    default=None,
    help="MDF4 output: digital channels as sampled levels (default) or as change events.",
)
@handle_errors
@io_paths(inputs=("src", "map_file"), outputs=("dst",))
def convert(src: str, dst: str, map_file: str | None, digital: str | None) -> None:
    """Read IN (any reader, checked), write OUT (format from its suffix), atomically.

    Converting a foreign file with --map gives a capture with canonical names and SI units.
    CSV cannot hold change events: they become levels at the sample times.
    """
    from eol_cal.capture import read_capture, write_capture
    from eol_cal.errors import InputError

    opts = {}
    if digital is not None:
        if Path(dst).suffix.lower() != ".mf4":
            raise InputError(dst, "--digital", "only MDF4 output (.mf4) stores digital channels as events")
        opts["digital"] = digital
    capture = read_capture(src, map_file)
    write_capture(capture, dst, **opts)
    duration = float(capture.t[-1] - capture.t[0])
    console.print(f"wrote {dst}: {len(capture.t)} samples, {duration:.6g} s, channels {', '.join(capture.channels)}")


COMMANDS = [capture_group]
