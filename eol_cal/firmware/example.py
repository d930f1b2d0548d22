"""A valid parameter block with plausible values, for the ECU simulator's flash, the fault
campaign's mutations, the tests and the benchmarks."""

from __future__ import annotations

import numpy as np

from eol_cal.firmware import block as B
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE


def example_block(serial: str = "SIM-0001", table_len: int = 256, sequence: int = 1, seed: int = 0) -> bytes:
    """A valid block with plausible values (paper motor, random smooth tables), packed."""
    rng = np.random.default_rng(seed)
    j = np.arange(table_len)
    phase = rng.uniform(-np.pi, np.pi)
    blk = B.ParamBlock(
        sequence=sequence, flags=B.FLAG_COMP_ENABLE | B.FLAG_INTERP_ENABLE, serial=serial,
        calibrated_at=1_790_000_000 + seed, poles=6, encoder_ppr=64, tick_hz=20000.0, kt=0.049,
        hall_angle=NOMINAL_HALL_ANGLE, c6=0.002, phase_c6=0.3,
        k6=0.00062, phase_k6=phase, lead_s=1e-4, iqc_limit=5.0,
        table_const=0.04 * np.sin(2 * np.pi * j / table_len + 0.3),
        table_per_amp=0.0127 * np.sin(2 * np.pi * j / table_len + phase))
    return B.pack(blk)
