"""Station settings: one TOML file per end-of-line station, every key also an environment variable.

A station is set up once by the test engineer who commissions it and then runs unchanged for
months, so every key is checked before the dyno moves: a typo in a path, an address or an
interface name is an :class:`~eol_cal.errors.InputError` naming the file, the key and the reason,
never a half-run cycle. The file's keys (docs/station.md, "First real station")::

    station_id = "L3-EOL-02"
    limits = "limits.toml"          # paths are relative to this file
    variant = "EPS-STD"
    db = "records.sqlite"           # or postgresql://user@host:5432/eol
    report_dir = "reports"
    key_file = "ecu.key"
    key_algo = "oem-eps"            # optional: the OEM's seed-to-key (entry point or MODULE:FUNC)
    [dyno]
    address = "192.0.2.10"          # Modbus TCP; port 502 when none is given
    register_map = "default"        # a shipped map's name or a map file (docs/dyno.md)
    [can]
    interface = "pcan"
    channel = "PCAN_USBBUS1"
    bitrate = 500000

Environment variables override the file key by key: ``EOL_CAL_`` + the key's dotted path in
capitals with ``_`` for the dot (``EOL_CAL_DYNO_ADDRESS``, ``EOL_CAL_CAN_CHANNEL``), so that a
line's deployment can set what differs per station without editing the file. An empty variable
counts as unset. The caller's own values (a command's options) override both, key by key.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from collections.abc import Callable, Collection, Mapping

import can

from eol_cal.infra.address import MODBUS_PORT, parse_modbus_address  # noqa: F401 - MODBUS_PORT: the port a bare address gets
from eol_cal.errors import InputError
from eol_cal.infra.inputs import check_regular, load_toml
from eol_cal.msa.master import MASTER_QUANTITIES

if TYPE_CHECKING:
    from eol_cal.dyno.regmap import RegisterMap
    from eol_cal.msa.master import MasterSettings

ENV_PREFIX = "EOL_CAL_"

#: where a value given by the caller (a command's option) is said to come from
COMMAND_LINE = "command line"


def env_name(key: str) -> str:
    """The environment variable of a settings key: ``dyno.address`` -> ``EOL_CAL_DYNO_ADDRESS``."""
    return ENV_PREFIX + key.replace(".", "_").upper()


#: ``flash.read_back``: read the block back before its CRC is written, or leave it to the ECU's check
READ_BACK_CHOICES = ("before-crc", "off")
#: ``dyno.lead_in``: turn the shaft for the ECU's settling after each reset before its capture
#: (:func:`eol_cal.firmware.settling.lead_in_plan`: an identification at its own speed), all of it
#: at the capture's first point (``at-point``), or capture at once
LEAD_IN_CHOICES = ("settle", "at-point", "off")


@dataclass(frozen=True)
class Key:
    """One settings key: its dotted name, its TOML type, and its default (``None``: required)."""

    name: str
    kind: type
    default: object = None
    required: bool = False
    is_path: bool = False
    choices: tuple[str, ...] = ()
    bounds: tuple[float, float] | None = None

    @property
    def env(self) -> str:
        return env_name(self.name)


KEYS: tuple[Key, ...] = (
    Key("station_id", str, required=True),
    Key("limits", str, required=True, is_path=True),
    Key("variant", str),
    Key("db", str, required=True),
    Key("report_dir", str, "reports", is_path=True),
    Key("spool_dir", str, is_path=True),
    Key("key_file", str, is_path=True),  # required unless key_algo needs no secret
    Key("key_algo", str),  # the OEM's seed-to-key: an entry point name or MODULE:FUNC (eol_cal.ecu.keyalgo)
    Key("profile", str, "eol-default"),
    Key("verify", str, "point", choices=("point", "full")),
    Key("estimator", str),  # None: the variant's (limits file), else paper|best|NAMES|0xMASK
    Key("motor", str, "paper"),
    Key("bench", str, "paper"),
    Key("rate_hz", int, 10000, bounds=(1, 1_000_000)),
    Key("db_timeout_s", float, 5.0, bounds=(0.0, 600.0)),
    Key("dyno.address", str, required=True),
    Key("dyno.register_map", str, "default"),
    Key("dyno.timeout_s", float, 1.0, bounds=(0.01, 60.0)),
    # the dyno stops by itself when the station is silent this long (its register is a u16 of ms)
    Key("dyno.watchdog_ms", int, 2000, bounds=(100, 60_000)),
    # the shaft turns for the ECU's settling after each reset (pitch learning, the mechanical
    # identification) before the capture counts (docs/station.md, "Lead-in"); off on a dyno that
    # holds the motor at speed long enough by itself
    Key("dyno.lead_in", str, "settle", choices=LEAD_IN_CHOICES),
    # the block read back before its CRC is written (docs/flashing.md), or the ECU's CRC check alone
    # (contract: the read-back is optional); a takt choice of the line's, recorded per block
    Key("flash.read_back", str, "before-crc", choices=READ_BACK_CHOICES),
    Key("can.interface", str),
    Key("can.channel", str),
    Key("can.bitrate", int, bounds=(10_000, 8_000_000)),
    Key("can.config", str, is_path=True),
    # statistics: the fewest values a capability index or control limit is given from (docs/spc.md)
    Key("min_n", int, 25, bounds=(2, 1_000_000)),
    # the master motor (docs/station.md, "Master motor"; eol_cal.msa.master): its serial, how often
    # it runs, its reference values and the tolerances around them (display units)
    Key("master.serial", str),
    Key("master.every_h", float, bounds=(0.01, 10_000.0)),
    Key("master.shifts", str),
    Key("master.timezone", str),
    *(Key(f"master.{part}.{q}", float) for part in ("reference", "tolerance") for q in MASTER_QUANTITIES),
)


@dataclass(frozen=True)
class StationSettings:
    """The checked settings of one station; paths are absolute, the dyno port is filled in.

    Attributes
    ----------
    source : str
        The settings file (or ``"environment"`` when every key came from the environment).
    values : dict
        Every key of :data:`KEYS` by its dotted name, after defaults and the environment.
    origin : dict
        Where each value came from: ``"file"``, ``"env"`` or ``"default"``.
    dyno_host, dyno_port : str, int
        The dyno's Modbus TCP address.
    """

    source: str
    values: Mapping[str, object]
    origin: Mapping[str, str]
    dyno_host: str
    dyno_port: int

    def __getitem__(self, name: str) -> object:
        return self.values[name]

    def where(self, name: str) -> str:
        """The file, ``$VARIABLE`` or ``command line`` that a key's value came from (for error messages)."""
        origin = self.origin.get(name)
        return f"${env_name(name)}" if origin == "env" else COMMAND_LINE if origin == "given" else self.source

    def path(self, name: str) -> Path | None:
        """A path-valued key as a :class:`~pathlib.Path` (``None`` when unset)."""
        value = self.values[name]
        return None if value is None else Path(str(value))


def _flatten(table: Mapping[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in table.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, name + "."))
        else:
            out[name] = v
    return out


def _read_toml(path: Path) -> dict[str, object]:
    return load_toml(path)


def _from_env(key: Key, text: str, where: str) -> object:
    if key.kind is str:
        return text
    try:
        return key.kind(text)
    except ValueError as exc:
        raise InputError(where, key.name, f"{text!r} is not {'an integer' if key.kind is int else 'a number'}") from exc


def _check_value(key: Key, value: object, where: str) -> object:
    # bool is an int to Python, never a rate or a port to a station
    ok = isinstance(value, key.kind) and not isinstance(value, bool)
    if key.kind is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        raise InputError(where, key.name, f"expected {key.kind.__name__}, got {type(value).__name__} {value!r}")
    if key.kind is str and not str(value).strip():
        raise InputError(where, key.name, "empty")
    if key.choices and value not in key.choices:
        raise InputError(where, key.name, f"{value!r} is not one of {', '.join(key.choices)}")
    if key.bounds is not None and not key.bounds[0] <= float(value) <= key.bounds[1]:  # type: ignore[arg-type]
        raise InputError(where, key.name, f"{value} out of range {key.bounds[0]:g}..{key.bounds[1]:g}")
    return value


def parse_dyno_address(text: str, where: str) -> tuple[str, int]:
    """``HOST`` or ``HOST:PORT`` -> (host, port), port 502 (Modbus TCP) when none is given."""
    try:
        return parse_modbus_address(text, "dyno.address")
    except InputError as exc:
        raise InputError(where, "dyno.address", exc.reason) from exc


def _check_path(key: Key, value: object, where: str) -> object:
    """A path-valued key (or a database file) that no file can have (a NUL, a name or path too
    long) refused here, naming it, not as ValueError where it is first resolved or opened."""
    from eol_cal.infra.address import path_problem

    if (key.is_path or key.name == "db") and (why := path_problem(str(value))) is not None:
        raise InputError(where, key.name, why)
    return value


def _resolve(key: Key, value: object, base: Path) -> object:
    """A path-valued key relative to ``base``; so is a database that is a file, not a URL."""
    if key.is_path or (key.name == "db" and "://" not in str(value)):
        return str((base / str(value)).resolve())
    return value


def _check_values(settings: StationSettings) -> None:
    """The keys whose values alone can be wrong, checked as the options are: the estimator, the
    database address, the CAN configuration file (a cycle started with ``estimator = "foo"``,
    ``db = "."`` or a garbage ``can.config`` and failed at its first use of them)."""
    from eol_cal.infra.address import records_db

    if settings["estimator"] is not None:
        from eol_cal.firmware.options import parse_options

        parse_options(str(settings["estimator"]), settings.where("estimator"), "estimator")
    if settings["db"] is not None:
        try:
            records_db(str(settings["db"]), "db", writing=True)
        except InputError as exc:
            raise InputError(settings.where("db"), "db",
                             exc.reason if exc.file is None else f"{exc.file}: {exc.reason}") from None
    if settings["can.config"] is not None:
        from eol_cal.ecu.transport import bus_config

        try:
            bus_config(settings["can.interface"], settings["can.channel"], settings["can.bitrate"],
                       str(settings["can.config"]))
        except InputError as exc:
            raise InputError(settings.where("can.config"), "can.config", f"{settings['can.config']}: {exc.reason}") from None


def load_settings(path: str | Path | None, environ: Mapping[str, str] | None = None,
                  validators: Mapping[str, Callable[[StationSettings], None]] | None = None, *,
                  given: Mapping[str, object] | None = None, fallbacks: Mapping[str, object] | None = None,
                  optional: Collection[str] = ()) -> StationSettings:
    """Read, merge and check a station's settings.

    Each key's value comes from, highest first: ``given``, the environment, the file,
    ``fallbacks``, the key's default.

    Parameters
    ----------
    path : path or None
        The station's TOML file; ``None``: every required key must come from the environment
        (or ``given``).
    environ : mapping, optional
        The environment (default ``os.environ``); ``EOL_CAL_*`` variables override file keys.
    validators : mapping, optional
        Further checks by name, each called with the merged settings and raising
        :class:`~eol_cal.errors.InputError` (the station module adds the ones that load the
        limits, the profile, the motor and the key, so that they run before the dyno moves).
    given : mapping, optional
        Values the caller was given explicitly (a command's options), by dotted key; relative
        paths are relative to the working directory. Checked like the file's.
    fallbacks : mapping, optional
        Values the caller uses where neither the file nor the environment sets a key (the
        demo's limits and database); relative paths are relative to the working directory.
    optional : collection of str
        Required keys the caller supplies itself when unset (the demo's dyno, bus and key);
        they stay ``None``.

    Returns
    -------
    StationSettings

    Raises
    ------
    InputError
        An unknown key (a typo would otherwise be silently ignored), a wrong type, a value out
        of range, a missing required key or a missing file; the file and the key are named.
    """
    environ = os.environ if environ is None else environ
    given, fallbacks = dict(given or {}), dict(fallbacks or {})
    source = str(path) if path is not None else "environment"
    base = Path(path).resolve().parent if path is not None else Path.cwd()
    file_values = _flatten(_read_toml(Path(path))) if path is not None else {}
    known = {k.name: k for k in KEYS}
    for name in [*file_values, *given, *fallbacks]:
        if name not in known:
            where = source if name in file_values else COMMAND_LINE
            raise InputError(where, name, f"unknown key (known: {', '.join(sorted(known))})")
    values: dict[str, object] = {}
    origin: dict[str, str] = {}
    for key in KEYS:
        root = base
        if given.get(key.name) is not None:
            value, where, origin[key.name], root = given[key.name], COMMAND_LINE, "given", Path.cwd()
        elif environ.get(key.env, "") != "":  # an empty variable is an unset one
            value, where, origin[key.name] = _from_env(key, environ[key.env], f"${key.env}"), f"${key.env}", "env"
            root = Path.cwd()
        elif key.name in file_values:
            value, where, origin[key.name] = file_values[key.name], source, "file"
        elif fallbacks.get(key.name) is not None:
            value, where, origin[key.name], root = fallbacks[key.name], COMMAND_LINE, "default", Path.cwd()
        elif key.required and key.name not in optional:
            raise InputError(source, key.name, f"required (in the file or as ${key.env})")
        else:
            values[key.name], origin[key.name] = key.default, "default"
            if key.is_path and key.default is not None:
                values[key.name] = str(base / str(key.default))
            continue
        values[key.name] = _resolve(key, _check_path(key, _check_value(key, value, where), where), root)
    if values["key_file"] is None and values["key_algo"] is None and "key_file" not in optional:
        raise InputError(source, "key_file", f"required (in the file or as ${env_name('key_file')}), unless key_algo "
                                             "names an OEM algorithm that needs no secret")
    settings = StationSettings(source, values, origin, "", 0)
    for name in ("limits", "key_file", "can.config"):
        p = values[name]
        if p is not None:
            try:
                check_regular(str(p))
            except InputError as exc:  # missing, a directory, a FIFO: said with the key that names it
                reason = "no such file" if not os.path.exists(str(p)) else exc.reason
                raise InputError(settings.where(name), name, f"{reason}: {p}") from None
    _check_values(settings)
    if values["can.interface"] is None and values["can.config"] is None and "can.interface" not in optional:
        raise InputError(source, "can.interface", "no CAN interface: set can.interface (and can.channel) or can.config")
    interface = values["can.interface"]
    # udp_multicast sends frames out through the network card: never a station's ECU bus
    if interface is not None and (interface not in can.interfaces.VALID_INTERFACES or interface == "udp_multicast"):
        raise InputError(settings.where("can.interface"), "can.interface",
                         f"{interface!r} is not a python-can interface this tool drives")
    host, port = ("", 0) if values["dyno.address"] is None else \
        parse_dyno_address(str(values["dyno.address"]), settings.where("dyno.address"))
    settings = StationSettings(source, values, origin, host, port)
    for check in (validators or {}).values():
        check(settings)
    return settings


def load_named(settings: StationSettings, name: str, load: Callable[[], object]) -> object:
    """Run ``load``; its InputError is re-said with the settings key it came from.

    A loader's own field may itself be a settings key (the limits file's ``variant``): then
    that key is the one named.
    """
    try:
        return load()
    except InputError as exc:
        key = exc.field if exc.field in settings.values else name
        raise InputError(settings.where(key), key, f"{exc}") from exc


def check_station(settings: StationSettings) -> None:
    """Load everything the settings name (limits and variant, profile, motor, bench, key).

    Called by :func:`load_settings`'s callers before the dyno moves; a bad limits file or key
    file is refused here with the settings key named, not halfway through the first motor.
    """
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.plant.profile import load_profile
    from eol_cal.records.limits import load_limits

    load_named(settings, "limits", lambda: load_limits(str(settings["limits"]), settings["variant"]))  # type: ignore[arg-type]
    master_of(settings)
    load_named(settings, "profile", lambda: load_profile(str(settings["profile"])))
    motor = str(settings["motor"])
    load_named(settings, "motor", lambda: load_motor("paper", None if motor == "paper" else motor))
    load_named(settings, "bench", lambda: mechanics_or_rigid(str(settings["bench"])))
    if settings["key_file"] is not None or settings["key_algo"] is not None:  # else the caller's own (the demo's)
        seed_to_key_of(settings)
    register_map_of(settings)


def seed_to_key_of(settings: StationSettings) -> Callable[[bytes], bytes]:
    """The settings' seed-to-key algorithm (``key_algo`` with ``key_file``'s secret, else the
    contract's HMAC with it), loaded and tried once: a refusal names the key it came from."""
    from eol_cal.ecu.keyalgo import seed_to_key_from

    key_file, key_algo = settings["key_file"], settings["key_algo"]
    name = "key_algo" if key_algo is not None else "key_file"
    return load_named(settings, name, lambda: seed_to_key_from(None if key_file is None else str(key_file),  # type: ignore[return-value]
                                                               None if key_algo is None else str(key_algo),
                                                               file_field="key_file", algo_field="key_algo"))


def settings_paths(settings: StationSettings) -> tuple[list[str], list[str], list[str], list[str]]:
    """What the settings make a station read and write: (input files, output files, output
    directories, records databases), for the check that no output is an input or a database
    (``cli.paths.check_more``).

    Inputs: the settings file, limits, key file, CAN configuration, and the motor, bench,
    profile and register map where they are files. Outputs: none of their own (the database is
    not an output: no output may land on it or the files SQLite keeps beside it, whichever
    option, setting or default named it). Directories: reports and spool.
    """
    reads = [settings.source] if settings.source != "environment" else []
    reads += [str(settings[k]) for k in ("limits", "key_file", "can.config") if settings[k] is not None]
    for key in ("motor", "bench", "profile", "dyno.register_map"):
        value = settings[key]
        if value is not None and Path(str(value)).is_file():
            reads.append(str(value))
    db = settings["db"]
    dirs = [str(settings[k]) for k in ("report_dir", "spool_dir") if settings[k] is not None]
    return reads, [], dirs, [str(db)] if db is not None else []


def register_map_of(settings: StationSettings) -> RegisterMap:
    """The dyno's register map the settings name (``dyno.register_map``: a shipped map's name, or
    a map file, relative to the settings file); a bad map names the settings key."""
    from eol_cal.dyno.mapfile import load_register_map

    spec = str(settings["dyno.register_map"])
    if (spec.endswith(".toml") or "/" in spec) and settings.source != "environment" and not Path(spec).is_absolute():
        spec = str(Path(settings.source).resolve().parent / spec)
    return load_named(settings, "dyno.register_map", lambda: load_register_map(spec))  # type: ignore[return-value]


def master_of(settings: StationSettings) -> MasterSettings | None:
    """The station's master motor (keys ``master.*``), or None when ``master.serial`` is unset; a
    key that does not fit is refused naming the settings file (or variable) and the key."""
    from eol_cal.msa.master import master_settings

    return master_settings(settings.values, settings.where)
