"""What a what-if lot is (:mod:`eol_cal.station.whatif`): its plan, sent to the workers as plain
values."""

from __future__ import annotations

import hashlib
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: motors per task (each runs the station's cycle on the plant in-process, one after the other)
SIM_BATCH = 8
#: the records' station of a lot is this prefix and the lot's name (``lot stats --station sim:NAME``)
STATION_PREFIX = "sim:"
#: namespace of the run ids of simulated runs (uuid5 of the lot's name and the motor's number)
_RUN_NS = uuid.UUID("6f0c1b1e-25a5-4c1e-9d25-0000000000e5")


@dataclass(frozen=True)
class LotPlan:
    """What a simulated lot is: everything a task needs, as plain values (sent to the workers).

    Attributes
    ----------
    name : str
        The lot's name (the records' station is ``sim:NAME``, serials ``NAME-000123``).
    spread : str
        The production spread: a built-in name or a TOML file (:func:`eol_cal.plant.spread.load_spread`).
    limits_file, variant : str, str or None
        The limits the runs are judged by (:func:`eol_cal.records.limits.load_limits`).
    motors : int
        Motors in the lot.
    seed : int
        Motor ``i`` is drawn with seed ``seed + i``.
    profile : str
        The calibration capture's test profile (built-in name or TOML file).
    preset, bench : str
        The plant preset the spread varies and the dyno bench the fit divides out (as the station's).
    batch : int
        Motors per batch (a task).
    """

    name: str
    spread: str
    limits_file: str
    variant: str | None
    motors: int
    seed: int = 0
    profile: str = "eol-default"
    preset: str = "paper"
    bench: str = "paper"
    batch: int = SIM_BATCH

    @property
    def station(self) -> str:
        return STATION_PREFIX + self.name

    def serial(self, i: int) -> str:
        return f"{self.name}-{i:06d}"

    def run_id(self, i: int) -> str:
        return uuid.uuid5(_RUN_NS, f"{self.name}/{i}").hex

    def batches(self) -> list[list[int]]:
        return [list(range(k, min(k + self.batch, self.motors))) for k in range(0, self.motors, self.batch)]

    def fingerprint(self) -> dict[str, Any]:
        """What makes the lot's runs what they are (stored with each run; a resumed lot must match)."""
        return {"lot": self.name, "spread": _file_or_name(self.spread), "limits": _file_or_name(self.limits_file),
                "variant": self.variant, "seed": self.seed, "profile": _file_or_name(self.profile),
                "preset": self.preset, "bench": self.bench, "batch": self.batch}


def _file_or_name(name: str) -> str:
    """A built-in name, or a file's name with the SHA-256 of its bytes (a changed file is another lot)."""
    p = Path(name)
    if p.suffix.lower() == ".toml" and p.is_file():
        return f"{p.name} sha256:{hashlib.sha256(p.read_bytes()).hexdigest()[:16]}"
    return name
