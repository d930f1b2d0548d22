"""The production spread as data: the distributions of the motor-to-motor variation, from a TOML
file (``eol_cal/spreads/NAME.toml`` or any file; format in ``eol_cal/spreads/default.toml`` and
``docs/plant.md``), every key checked on load.

A :class:`Spread` draws one motor per seed (numpy's PCG64 ``default_rng(seed)``), the parameters
in the fixed order of :data:`PARAMETERS`, then the position sensors
(:func:`eol_cal.firmware.kinematics.draw_sensor_errors`): the default spread draws the motors the
plant drew before it became data, seed for seed (``tests/test_plant_spread.py``).

The bench is not the motor's: a station has one, and every motor of a lot tested there runs on it.
The spread's ``[bench]`` table gives the distributions of its torque path's torsion mode
(:data:`BENCH_PARAMETERS`: ``resonance_hz``, the undamped frequency with the nominal rotor, and
``shaft_zeta``); :meth:`Spread.draw_bench` draws one bench per station (or lot) seed, from a
stream of its own, and :meth:`Spread.draw` draws the motors on it. Motors drawn without it keep
the base preset's bench, seed for seed as before.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.errors import InputError
from eol_cal.firmware.kinematics import draw_sensor_errors
from eol_cal.infra.inputs import load_toml
from eol_cal.plant.params import PlantSpec
from eol_cal.plant.presets import paper

TWO_PI = 2.0 * math.pi

#: the parameters drawn before the sensors (PlantSpec fields), in the order they are drawn
_FIRST = ("k6", "phase_k6", "c6", "phase_c6", "c12", "phase_c12", "k12", "phase_k12", "c18", "phase_c18",
          "k18", "phase_k18", "unb1", "phase_unb1", "R_s_scale", "temp_degC")
#: the parameters added since (issue 34: mechanical orders 2 and 3), drawn after the sensors so
#: that a seed still draws the motor it drew before, these added to it
_LATER = ("unb2", "phase_unb2", "unb3", "phase_unb3")
#: the parameters a spread may vary (PlantSpec fields), in the order they are drawn (the sensors
#: between ``_FIRST`` and ``_LATER``)
PARAMETERS = _FIRST + _LATER
#: parameters that are amplitudes (N*m, N*m/A): their draws may never be negative
_AMPLITUDES = frozenset({"k6", "c6", "c12", "k12", "c18", "k18", "unb1", "unb2", "unb3"})
#: the range a parameter's draws must stay in (beyond: refused on load), where it has one
_RANGES = {"R_s_scale": (0.5, 2.0), "temp_degC": (-40.0, 180.0)}
#: each distribution's keys: required, optional
_DISTS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "normal": (("mean",), ("sigma", "sigma_rel", "min", "max")),
    "half_normal": (("sigma",), ()),
    "uniform": (("low", "high"), ()),
    "phase": ((), ()),
    "rayleigh": (("scale",), ()),
    "fixed": (("value",), ()),
}
#: the [bench] table's parameters (the station's torque path), in the order they are drawn, and
#: the range each one's draws must stay in: resonance_hz (Hz) and shaft_zeta (1)
BENCH_PARAMETERS = {"resonance_hz": (10.0, 5000.0), "shaft_zeta": (0.01, 1.0)}
#: the stream a bench is drawn from is default_rng([seed, BENCH_STREAM]): apart from the motors'
BENCH_STREAM = 0xBE4C
#: keys of the [sensors] table and their defaults (draw_sensor_errors' arguments)
SENSOR_KEYS = {"edge_sigma_mech_deg": 0.1, "hall_sigma_elec_deg": 2.0 / 3.0, "hall_max_elec_deg": 2.0}


@dataclass(frozen=True)
class Dist:
    """One parameter's distribution (``kind`` one of normal, half_normal, uniform, phase, rayleigh,
    fixed; ``args`` its keys, in the parameter's unit)."""

    kind: str
    args: dict[str, float]

    def draw(self, rng: np.random.Generator) -> float:
        a = self.args
        if self.kind == "normal":
            # relative to the mean's size: a negative mean's sigma_rel is no negative sd (numpy refused it)
            sigma = a["sigma"] if "sigma" in a else abs(a["sigma_rel"] * a["mean"])
            x = float(rng.normal(a["mean"], sigma))
            if "min" in a:
                x = max(a["min"], x)
            return min(a["max"], x) if "max" in a else x
        if self.kind == "half_normal":
            return abs(float(rng.normal(0.0, a["sigma"])))
        if self.kind == "uniform":
            return float(rng.uniform(a["low"], a["high"]))
        if self.kind == "phase":
            return float(rng.uniform(0.0, TWO_PI))
        if self.kind == "rayleigh":
            return float(rng.rayleigh(a["scale"]))
        return a["value"]

    def support(self) -> tuple[float, float]:
        """Where the draws can land (normal: mean +- 6 sigma, within its min and max)."""
        a = self.args
        if self.kind == "normal":
            sigma = abs(a["sigma"] if "sigma" in a else a["sigma_rel"] * a["mean"])
            return max(a.get("min", -math.inf), a["mean"] - 6 * sigma), min(a.get("max", math.inf), a["mean"] + 6 * sigma)
        if self.kind == "half_normal":
            return 0.0, 6 * a["sigma"]
        if self.kind == "uniform":
            return a["low"], a["high"]
        if self.kind == "phase":
            return 0.0, TWO_PI
        if self.kind == "rayleigh":
            return 0.0, 8 * a["scale"]
        return a["value"], a["value"]


@dataclass(frozen=True)
class Spread:
    """A production spread: the distributions of :data:`PARAMETERS` it varies, the sensors'.

    Attributes
    ----------
    name : str
        The spread's name (the file's ``name``, else its stem).
    source : str
        Where it was read from (a file, or ``spread NAME`` for a built-in one).
    params : dict[str, Dist]
        Parameter -> distribution; parameters left out keep the base preset's value.
    sensors : dict[str, float]
        :func:`eol_cal.firmware.kinematics.draw_sensor_errors`'s arguments (degrees).
    description : str
        Free text.
    bench : dict[str, Dist]
        :data:`BENCH_PARAMETERS` -> distribution (empty: no bench spread).
    """

    name: str
    source: str
    params: dict[str, Dist]
    sensors: dict[str, float] = field(default_factory=lambda: dict(SENSOR_KEYS))
    description: str = ""
    bench: dict[str, Dist] = field(default_factory=dict)

    def draw_bench(self, seed: int, base: PlantSpec | None = None) -> PlantSpec:
        """``base`` on a bench drawn for one station (or lot) from ``seed``: the same seed, the same bench.

        The torsion mode's frequency (Hz, with the nominal rotor inertia ``base.motor.J``) and
        damping are drawn from ``[bench]`` (parameters left out keep the base bench's), and
        ``K_shaft = (2 pi f)^2 J J_dyno / (J + J_dyno)``; the dyno (``J_dyno``, its speed loop)
        stays the base bench's. Draw the lot's motors with :meth:`draw` on the result.
        """
        base = paper() if base is None else base
        mech = base.mechanics
        J, J_d = base.motor.J, mech.J_dyno
        J_eff = J * J_d / (J + J_d)
        rng = np.random.default_rng([seed, BENCH_STREAM])
        drawn = {name: self.bench[name].draw(rng) for name in BENCH_PARAMETERS if name in self.bench}
        f_n = drawn.get("resonance_hz", math.sqrt(mech.K_shaft / J_eff) / TWO_PI)
        bench = dataclasses.replace(
            mech, name=f"{self.name}-bench-{seed}", K_shaft=(TWO_PI * f_n) ** 2 * J_eff,
            shaft_zeta=drawn.get("shaft_zeta", mech.shaft_zeta), source=f"{self.source} [bench] seed {seed}", sha256="")
        return base.replace(mechanics=bench)

    def draw(self, seed: int, base: PlantSpec | None = None, serial: str | None = None) -> PlantSpec:
        """One motor as built, from ``seed``: the same seed gives the same motor.

        Parameters
        ----------
        seed : int
            Seed of the draw.
        base : PlantSpec, optional
            Bench and nominal motor data (default: the ``paper`` preset).
        serial : str, optional
            Serial; default ``SIM-<seed>``.
        """
        base = paper() if base is None else base
        rng = np.random.default_rng(seed)
        values = {name: self.params[name].draw(rng) for name in _FIRST if name in self.params}
        spec = base.replace(serial=serial if serial is not None else f"SIM-{seed:06d}", **values)
        err = draw_sensor_errors(rng, base.motor.N_enc, **self.sensors)
        later = {name: self.params[name].draw(rng) for name in _LATER if name in self.params}
        return spec.replace(
            **later,
            enc_edge_err_deg=tuple(float(v) for v in np.degrees(err.edge_error)),
            hall_err_deg=tuple(float(v) for v in np.degrees(np.asarray(err.hall_offset).ravel())),
            grid_offset_deg=float(np.degrees(err.grid_offset)),
        )


def _number(source: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(source, key, f"must be a finite number, got {value!r}")
    return float(value)


def _dist(source: str, name: str, table: Any) -> Dist:
    if not isinstance(table, dict):
        raise InputError(source, name, "must be a table with a dist key ([" + name + "] dist = ...)")
    kind = table.get("dist")
    if kind not in _DISTS:
        raise InputError(source, f"{name}.dist", f"unknown distribution {kind!r}; known: {', '.join(_DISTS)}")
    required, optional = _DISTS[kind]
    for key in table:
        if key != "dist" and key not in required + optional:
            raise InputError(source, f"{name}.{key}", f"not a key of a {kind} distribution; its keys: "
                                                     f"{', '.join(required + optional) or 'none'}")
    for key in required:
        if key not in table:
            raise InputError(source, f"{name}.{key}", f"missing: a {kind} distribution needs {', '.join(required)}")
    args = {k: _number(source, f"{name}.{k}", v) for k, v in table.items() if k != "dist"}
    if kind == "normal":
        if ("sigma" in args) == ("sigma_rel" in args):
            raise InputError(source, f"{name}.sigma", "a normal distribution needs one of sigma and sigma_rel")
        spread_key = "sigma" if "sigma" in args else "sigma_rel"
        if args[spread_key] < 0:
            raise InputError(source, f"{name}.{spread_key}", f"must be >= 0, got {args[spread_key]!r}")
        if "min" in args and "max" in args and args["min"] > args["max"]:
            raise InputError(source, f"{name}.min", f"{args['min']!r} is above max {args['max']!r}")
    elif kind in ("half_normal", "rayleigh"):
        key = "sigma" if kind == "half_normal" else "scale"
        if args[key] < 0:
            raise InputError(source, f"{name}.{key}", f"must be >= 0, got {args[key]!r}")
    elif kind == "uniform" and args["low"] > args["high"]:
        raise InputError(source, f"{name}.low", f"{args['low']!r} is above high {args['high']!r}")
    dist = Dist(kind, args)
    lo, hi = dist.support()
    if name in _AMPLITUDES and lo < 0:
        raise InputError(source, name, f"an amplitude, but the {kind} distribution can draw {lo:.6g} < 0 "
                                       "(give it min = 0, or a support that stays >= 0)")
    if name.startswith("phase_") and kind not in ("phase", "fixed", "normal", "uniform"):
        raise InputError(source, f"{name}.dist", f"a phase (rad) takes phase, normal, uniform or fixed, not {kind}")
    if name in _RANGES and not (_RANGES[name][0] <= lo and hi <= _RANGES[name][1]):
        raise InputError(source, name, f"draws from {lo:.6g} to {hi:.6g} leave the range {_RANGES[name][0]:g} .. "
                                       f"{_RANGES[name][1]:g} this parameter takes")
    return dist


def _sensors(source: str, table: Any, start: dict[str, float]) -> dict[str, float]:
    if not isinstance(table, dict):
        raise InputError(source, "sensors", "must be a table ([sensors])")
    out = dict(start)
    for key, value in table.items():
        if key not in SENSOR_KEYS:
            raise InputError(source, f"sensors.{key}", f"unknown sensor key; known: {', '.join(SENSOR_KEYS)}")
        out[key] = _number(source, f"sensors.{key}", value)
    if not 0.0 <= out["edge_sigma_mech_deg"] <= 5.0:
        raise InputError(source, "sensors.edge_sigma_mech_deg", f"must be 0 .. 5 mechanical degrees, got "
                                                                f"{out['edge_sigma_mech_deg']!r}")
    if not 0.0 < out["hall_sigma_elec_deg"] <= 20.0:
        raise InputError(source, "sensors.hall_sigma_elec_deg", f"must be > 0 and <= 20 electrical degrees, got "
                                                                f"{out['hall_sigma_elec_deg']!r}")
    # hall errors are redrawn beyond the maximum: a maximum far inside the sigma would redraw for ever
    if not 0.5 * out["hall_sigma_elec_deg"] <= out["hall_max_elec_deg"] <= 30.0:
        raise InputError(source, "sensors.hall_max_elec_deg", "must be at least half of hall_sigma_elec_deg and at most "
                                                              f"30 electrical degrees, got {out['hall_max_elec_deg']!r}")
    return out


def _bench(source: str, table: Any) -> dict[str, Dist]:
    """The ``[bench]`` table: one distribution per :data:`BENCH_PARAMETERS` key, its draws in range."""
    if not isinstance(table, dict):
        raise InputError(source, "bench", "must be a table ([bench] with [bench.resonance_hz], [bench.shaft_zeta])")
    out = {}
    for key, value in table.items():
        if key not in BENCH_PARAMETERS:
            raise InputError(source, f"bench.{key}", f"unknown bench parameter; known: {', '.join(BENCH_PARAMETERS)}")
        dist = _dist(source, f"bench.{key}", value)
        lo, hi = dist.support()
        low, high = BENCH_PARAMETERS[key]
        if not (low <= lo and hi <= high):
            raise InputError(source, f"bench.{key}", f"draws from {lo:.6g} to {hi:.6g} leave the range {low:g} .. "
                                                     f"{high:g} this parameter takes")
        out[key] = dist
    return out


def parse_spread(data: dict[str, Any], source: str, default_name: str) -> Spread:
    """A :class:`Spread` from a TOML document (a dict), every key checked (``InputError`` naming
    ``source``, the key and the reason)."""
    name, description = data.get("name", default_name), data.get("description", "")
    base = data.get("base")
    for key, value in (("name", name), ("description", description), ("base", base or "")):
        if not isinstance(value, str):
            raise InputError(source, key, f"must be a string, got {value!r}")
    params: dict[str, Dist] = {}
    sensors = dict(SENSOR_KEYS)
    bench: dict[str, Dist] = {}
    if base is not None:
        # a built-in spread this one starts from (by name only: no chain of files to follow)
        if base == default_name or Path(base).suffix:
            raise InputError(source, "base", f"must name another built-in spread, got {base!r}")
        start = _builtin(base)
        params, sensors, bench = dict(start.params), dict(start.sensors), dict(start.bench)
    for key, value in data.items():
        if key in ("name", "description", "base"):
            continue
        if key == "sensors":
            sensors = _sensors(source, value, sensors)
        elif key == "bench":
            bench = _bench(source, value)
        elif key in PARAMETERS:
            params[key] = _dist(source, key, value)
        else:
            raise InputError(source, key, f"unknown spread parameter; known: {', '.join(PARAMETERS)}, sensors, bench, "
                                          "name, description, base")
    if not params and "sensors" not in data and not bench:
        raise InputError(source, None, f"varies nothing: give at least one of {', '.join(PARAMETERS)}, [sensors] or [bench]")
    return Spread(name, source, params, sensors, description, bench)


def load_spread(name_or_file: str | Path = "default") -> Spread:
    """A production spread from a built-in name (``eol_cal/spreads/NAME.toml``) or a TOML file."""
    path = Path(name_or_file)
    if path.suffix == ".toml":
        return parse_spread(load_toml(path), str(path), path.stem)
    return _builtin(str(name_or_file))


@functools.lru_cache(maxsize=8)
def _builtin(name: str) -> Spread:
    try:
        text = resources.files("eol_cal.spreads").joinpath(f"{name}.toml").read_text(encoding="utf-8")
    except (FileNotFoundError, IsADirectoryError):
        known = sorted(p.name[:-5] for p in resources.files("eol_cal.spreads").iterdir() if p.name.endswith(".toml"))
        raise InputError(None, "spread", f"unknown spread {name!r}; known: {', '.join(known)}, or a .toml file") from None
    return parse_spread(tomllib.loads(text), f"spread {name}", name)
