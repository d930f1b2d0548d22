"""The in-memory capture that every reader produces and every analysis reads.

See ``docs/capture-format.md`` (capture format v1). All channels share one time base ``t``;
encoder and hall channels are levels at those sample times. Where a file stored a digital
channel as change events, the exact change times are kept in :attr:`Capture.events` as well,
so that angle reconstruction can use edge times finer than the sample period.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from collections.abc import Mapping

import numpy as np

#: canonical channel name -> canonical unit (pint syntax; "1" = dimensionless)
CANONICAL_CHANNELS: Mapping[str, str] = MappingProxyType(
    {
        "t": "s",
        "torque": "N*m",
        "enc_a": "1",
        "enc_b": "1",
        "hall": "1",
        "iq_ref": "A",
        "iqc": "A",
        "iq": "A",
        "id": "A",
        "ia": "A",
        "ib": "A",
        "ic": "A",
        "speed": "rpm",
        "temp": "degC",
    }
)

DIGITAL_CHANNELS = ("enc_a", "enc_b", "hall")
REQUIRED_METADATA = ("serial", "poles", "encoder_ppr")
TRUTH_PREFIX = "truth."


@dataclass(frozen=True, eq=False)
class Capture:
    """One continuous recording of one motor.

    Attributes
    ----------
    t : ndarray, float64
        Sample times (s), strictly increasing.
    channels : dict[str, ndarray]
        Canonical channel name -> samples on ``t`` in canonical SI units (``t`` itself is not
        in here). Digital channels (``enc_a``, ``enc_b``, ``hall``) are integer arrays.
    metadata : dict[str, str | int | float]
        Capture metadata (``serial``, ``poles``, ``encoder_ppr``, ...); never ``truth.*`` keys.
    truth : dict[str, str | int | float]
        Simulator truth, keys without the ``truth.`` prefix. Analyses must not read it;
        only tests and benchmarks judge results against it.
    events : dict[str, tuple[ndarray, ndarray]]
        Optional exact change events of digital channels: name -> (times (s), new levels).
    source : str
        Where the capture came from (file path or ``"<memory>"``), for error messages.
    """

    t: np.ndarray
    channels: dict[str, np.ndarray]
    metadata: dict[str, str | int | float] = field(default_factory=dict)
    truth: dict[str, str | int | float] = field(default_factory=dict)
    events: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    source: str = "<memory>"

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "t":
            return self.t
        return self.channels[name]

    def has(self, name: str) -> bool:
        return name == "t" or name in self.channels

    @property
    def serial(self) -> str:
        return str(self.metadata["serial"])

    @property
    def poles(self) -> int:
        return int(self.metadata["poles"])

    @property
    def encoder_ppr(self) -> int:
        return int(self.metadata["encoder_ppr"])

    @property
    def sample_rate(self) -> float:
        """Mean sample rate (Hz)."""
        return (len(self.t) - 1) / float(self.t[-1] - self.t[0])

    def iq_ref(self) -> np.ndarray:
        """Nominal q current i_qo (A) per sample: the channel, else the constant metadata value."""
        if "iq_ref" in self.channels:
            return self.channels["iq_ref"]
        return np.full(len(self.t), float(self.metadata["iq_ref"]))
