"""A station's cycle configuration from its checked settings (:mod:`eol_cal.station.settings`).

``eol-cal run`` and ``eol-cal station`` both build their :class:`~eol_cal.station.run.StationConfig`
here, once per session: every key is loaded (limits and variant, profile, motor, bench, key)
before the dyno moves, each refusal naming the settings file or variable and the key. Per motor
only the serial and the operator change (:func:`for_motor`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any
from collections.abc import Callable

from eol_cal.errors import InputError
from eol_cal.station.run import StationConfig
from eol_cal.station.settings import StationSettings, load_named, master_of, register_map_of, seed_to_key_of

def station_record(settings: StationSettings, operator: str | None) -> dict[str, Any]:
    """The run record's ``station`` entries that the settings give (id, operator, addresses).

    The cycle adds profile, verify, rate, motor and bench itself.
    """
    return {"id": settings["station_id"], "operator": operator, "settings": settings.source,
            "dyno": None if settings["dyno.address"] is None else f"{settings.dyno_host}:{settings.dyno_port}",
            "can": {"interface": settings["can.interface"], "channel": settings["can.channel"],
                    "bitrate": settings["can.bitrate"]}}


def station_config(settings: StationSettings, *, operator: str | None = None, cache_dir: Path | None = None,
                   seed_to_key: Callable[[bytes], bytes] | None = None) -> StationConfig:
    """The configuration every motor of a session shares (its serial is set per motor).

    Parameters
    ----------
    settings : StationSettings
        Checked settings (:func:`eol_cal.station.settings.load_settings`).
    operator : str or None
        Who runs the station (into every record).
    cache_dir : Path or None
        The fit's cache directory (:attr:`StationConfig.cache_dir`).
    seed_to_key : callable, optional
        Security algorithm; default the settings' ``key_algo`` (with ``key_file``'s secret), else
        the contract's HMAC with ``key_file``.

    Raises
    ------
    InputError
        A key whose file or value cannot be used; names the settings file (or variable) and the key.
    """
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu.transport import open_bus
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.plant.profile import load_profile
    from eol_cal.records.limits import load_limits

    regmap = register_map_of(settings)
    limits = load_named(settings, "limits", lambda: load_limits(str(settings["limits"]), settings["variant"]))
    load_named(settings, "profile", lambda: load_profile(str(settings["profile"])))
    motor_name = str(settings["motor"])
    motor = load_named(settings, "motor", lambda: load_motor("paper", None if motor_name == "paper" else motor_name))
    mechanics = load_named(settings, "bench", lambda: mechanics_or_rigid(str(settings["bench"])))
    if seed_to_key is None:  # the settings' algorithm, tried on a made-up seed before the dyno moves
        if settings["key_file"] is None and settings["key_algo"] is None:
            raise InputError(settings.source, "key_file", "required: the flash step needs the ECU's secret (or key_algo)")
        seed_to_key = seed_to_key_of(settings)
    db = str(settings["db"])
    can = (settings["can.interface"], settings["can.channel"], settings["can.bitrate"], settings["can.config"])
    return StationConfig(
        serial="", dyno=DynoConfig(host=settings.dyno_host, port=settings.dyno_port, timeout=settings["dyno.timeout_s"],
                                     watchdog_ms=int(settings["dyno.watchdog_ms"]), register_map=regmap),
        open_bus=lambda: open_bus(*can), seed_to_key=seed_to_key, limits=limits, db=db if "://" in db else Path(db),
        report_dir=settings.path("report_dir"), profile=str(settings["profile"]), verify=str(settings["verify"]),
        spool_dir=settings.path("spool_dir"), rate_hz=int(settings["rate_hz"]), db_timeout_s=float(settings["db_timeout_s"]),
        station=station_record(settings, operator), cache_dir=cache_dir, motor=motor, mechanics=mechanics,
        estimator=None if settings["estimator"] is None else str(settings["estimator"]), master=master_of(settings),
        read_back=settings["flash.read_back"] == "before-crc", lead_in=settings["dyno.lead_in"],
    )


def for_motor(cfg: StationConfig, serial: str, **changes: Any) -> StationConfig:
    """The session's configuration for one motor: its serial, and any per-motor ``changes``
    (the demo's simulators: ``dyno``, ``open_bus``, ``station``). The station's master motor
    runs as kind ``master``."""
    is_master = cfg.master is not None and serial == cfg.master.serial
    kind = "master" if is_master else ("production" if cfg.kind == "master" else cfg.kind)
    return dataclasses.replace(cfg, serial=serial, **{"kind": kind, **changes})
