"""Test profiles: what the dyno and the ECU's command do over a capture (TOML).

A profile is a list of segments, played in order::

    name = "eol-default"
    description = "..."

    [[segment]]
    speed_rpm = 60.0      # dyno speed, rpm, signed (negative = reverse rotation)
    iq = 65.0             # nominal q current i_qo (A, signed) - or torque_nm (N*m), not both
    seconds = 1.0         # duration (s), ramp included
    ramp_s = 0.1          # optional: speed and load move linearly from the previous segment's
                          # values over the first ramp_s seconds (default 0: a step)

Built-in profiles live in ``eol_cal/profiles/NAME.toml``. Any problem is refused with an
:class:`~eol_cal.errors.InputError` naming the file, the key (``segment[2].seconds``) and why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from eol_cal.errors import InputError
from eol_cal.infra.inputs import MAX_TOML_BYTES, loads_toml, read_text

MAX_RPM = 6000.0
MAX_IQ_A = 300.0
MAX_SECONDS = 3600.0
_SEGMENT_KEYS = {"speed_rpm", "iq", "torque_nm", "seconds", "ramp_s"}
_TOP_KEYS = {"name", "description", "segment"}


@dataclass(frozen=True)
class ProfileSegment:
    """One segment of a test profile (``[[segment]]`` in its TOML): speed (rpm, signed), load
    as i_qo (A) or torque (N*m), duration and ramp time (s)."""

    speed_rpm: float
    seconds: float
    iq: float | None = None
    torque_nm: float | None = None
    ramp_s: float = 0.0

    def i_qo(self, kt: float) -> float:
        """Nominal q current (A) of this segment for a motor of torque constant ``kt`` (N*m/A)."""
        if self.iq is not None:
            return self.iq
        assert self.torque_nm is not None  # a segment gives iq or torque_nm (_segment refuses neither)
        return self.torque_nm / kt


@dataclass(frozen=True)
class Profile:
    """A named sequence of segments."""

    name: str
    segments: tuple[ProfileSegment, ...]
    description: str = ""

    @property
    def seconds(self) -> float:
        """Total duration (s)."""
        return sum(s.seconds for s in self.segments)

    def ticks(self, f_tick: float, kt: float) -> tuple[np.ndarray, np.ndarray]:
        """Speed reference (rpm) and i_qo (A) at every tick of rate ``f_tick`` (Hz)."""
        speeds, currents = [], []
        prev_speed = prev_iq = None
        for seg in self.segments:
            n = max(1, int(round(seg.seconds * f_tick)))
            iq = seg.i_qo(kt)
            if prev_speed is None or seg.ramp_s <= 0.0:
                w = np.ones(n)
            else:
                w = np.clip((np.arange(n) / f_tick + 1.0 / f_tick) / seg.ramp_s, 0.0, 1.0)
            p_speed = seg.speed_rpm if prev_speed is None else prev_speed
            p_iq = iq if prev_iq is None else prev_iq
            speeds.append(p_speed + w * (seg.speed_rpm - p_speed))
            currents.append(p_iq + w * (iq - p_iq))
            prev_speed, prev_iq = seg.speed_rpm, iq
        return np.concatenate(speeds), np.concatenate(currents)

    def segment_bounds(self, f_tick: float) -> list[tuple[int, int]]:
        """Tick ranges ``[start, stop)`` of each segment."""
        out, start = [], 0
        for seg in self.segments:
            n = max(1, int(round(seg.seconds * f_tick)))
            out.append((start, start + n))
            start += n
        return out


def constant(speed_rpm: float, seconds: float, iq: float | None = None, torque_nm: float | None = None,
             name: str = "constant") -> Profile:
    """A one-segment profile (the CLI's ``--speed-rpm/--torque-nm|--iq/--seconds``)."""
    seg = _segment({"speed_rpm": speed_rpm, "seconds": seconds, "iq": iq, "torque_nm": torque_nm}
                   if iq is not None or torque_nm is not None else
                   {"speed_rpm": speed_rpm, "seconds": seconds, "iq": 0.0}, "<command line>", "")
    return Profile(name, (seg,))


def _number(value: object, file: str, key: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(file, key, f"must be a finite number, got {value!r}")
    if not lo <= value <= hi:
        raise InputError(file, key, f"{value!r} is outside [{lo:g}, {hi:g}]")
    return float(value)


def _segment(data: dict, file: str, where: str) -> ProfileSegment:
    data = {k: v for k, v in data.items() if v is not None}
    for key in data:
        if key not in _SEGMENT_KEYS:
            raise InputError(file, f"{where}{key}", f"unknown key; known: {', '.join(sorted(_SEGMENT_KEYS))}")
    for key in ("speed_rpm", "seconds"):
        if key not in data:
            raise InputError(file, f"{where}{key}", "missing")
    if ("iq" in data) == ("torque_nm" in data):
        raise InputError(file, f"{where}iq", "give exactly one of iq (A) and torque_nm (N*m)")
    speed = _number(data["speed_rpm"], file, f"{where}speed_rpm", -MAX_RPM, MAX_RPM)
    seconds = _number(data["seconds"], file, f"{where}seconds", 0.0, MAX_SECONDS)
    if seconds <= 0.0:
        raise InputError(file, f"{where}seconds", "must be positive")
    ramp = _number(data.get("ramp_s", 0.0), file, f"{where}ramp_s", 0.0, MAX_SECONDS)
    if ramp > seconds:
        raise InputError(file, f"{where}ramp_s", f"ramp {ramp:g} s is longer than the segment's {seconds:g} s")
    iq = torque = None
    if "iq" in data:
        iq = _number(data["iq"], file, f"{where}iq", -MAX_IQ_A, MAX_IQ_A)
    else:
        torque = _number(data["torque_nm"], file, f"{where}torque_nm", -100.0, 100.0)
    return ProfileSegment(speed_rpm=speed, seconds=seconds, iq=iq, torque_nm=torque, ramp_s=ramp)


def parse_profile(text: str, file: str) -> Profile:
    """Profile from TOML text; ``file`` names the source in error messages."""
    data = loads_toml(text, file)
    for key in data:
        if key not in _TOP_KEYS:
            raise InputError(file, key, f"unknown key; known: {', '.join(sorted(_TOP_KEYS))}")
    segs = data.get("segment")
    if not isinstance(segs, list) or not segs:
        raise InputError(file, "segment", "needs at least one [[segment]] table")
    segments = []
    for i, seg in enumerate(segs):
        if not isinstance(seg, dict):
            raise InputError(file, f"segment[{i}]", "must be a table")
        segments.append(_segment(seg, file, f"segment[{i}]."))
    name = data.get("name", Path(file).stem)
    if not isinstance(name, str):
        raise InputError(file, "name", "must be a string")
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise InputError(file, "description", "must be a string")
    return Profile(name=name, segments=tuple(segments), description=desc)


def builtin_profiles() -> list[str]:
    """Names of the built-in profiles."""
    root = resources.files("eol_cal.profiles")
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def load_profile(name_or_file: str | Path) -> Profile:
    """A built-in profile by name, or a TOML profile file by path."""
    text_name = str(name_or_file)
    if text_name in builtin_profiles():
        text = resources.files("eol_cal.profiles").joinpath(f"{text_name}.toml").read_text()
        return parse_profile(text, f"profile {text_name}")
    path = Path(name_or_file)
    if not path.exists():
        raise InputError(text_name, None, f"no such profile file, and not a built-in profile "
                         f"({', '.join(builtin_profiles())})")
    return parse_profile(read_text(path, max_bytes=MAX_TOML_BYTES), text_name)
