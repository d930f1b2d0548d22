"""Station configurations the tests run the cycle on (what a library caller would pass)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from eol_cal.sim import FIXTURES


def settings_refused_config(tmp_path: Path) -> Any:
    """A station configuration whose estimator options cannot be flashed (a library caller's
    settings): its cycle ends at the pre-flight as a refusal (code ``settings``), before it opens
    the ECU's bus (which raises) or reaches the dyno (a closed port on 127.0.0.1)."""
    import socket

    from eol_cal.dyno.client import DynoConfig
    from eol_cal.records.limits import load_limits
    from eol_cal.station.run import StationConfig

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def no_bus() -> Any:
        raise AssertionError("the ECU's bus was opened")

    return StationConfig(serial="S-1", dyno=DynoConfig(port=port, timeout=0.05, retries=0), open_bus=no_bus,
                         seed_to_key=lambda seed: seed, limits=load_limits(FIXTURES / "limits.toml"),
                         db=tmp_path / "r.sqlite", report_dir=tmp_path / "reports", spool_dir=tmp_path / "spool",
                         estimator="bogus", cache_dir=None)
