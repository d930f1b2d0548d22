"""Golden vectors of layout 2 (contract revision 1.2): blocks, check routine, the identifier tick by
tick, and the mechanical-order compensation. Consumed by :mod:`eol_cal.firmware.golden`.

Files (``firmware_params/MECH.md``, "Proving an implementation"):

* ``blocks_v2.csv``: valid layout-2 blocks: header and mechanical scalars, the exact image;
* ``block_checks_v2.csv``: layout-2 images and the check routine's status;
* ``mech_configs.csv``: each ``mech_*.csv`` scenario's block and standstill bound, and the
  constants ``eol_mech_init`` derives (DELTA, INV_DELTA, KM, EF per direction) as binary32 hex;
* ``mech_<scenario>.csv``: tick, enc_a, enc_b, hall, i_qo (inputs); the estimator's status and
  pitch-sample flag, the identifier's active, r, events, score, margin, and i_qc (outputs);
* ``mech_compensator.csv``: i_qc with the mechanical part on, for counts, offsets, angles, speeds
  and currents over each block of ``blocks_v2.csv``.

The blocks carry the true fingerprint of the kinematic model's encoder
(:func:`eol_cal.firmware.kinematics.fingerprint_of`, the model's pulse numbering is the block's
frame), so each scenario's offset ``r`` is known (:func:`eol_cal.firmware.kinematics.pulse_at`).
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,union-attr,index,return-value"
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from eol_cal.firmware import block as B
from eol_cal.firmware import compensator
from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
from eol_cal.firmware.estimator import EstimatorConfig
from eol_cal.firmware.kinematics import (
    SensorErrors,
    draw_sensor_errors,
    encoder_hall_signals,
    fingerprint_of,
    hall_angle_of,
    speed_profile_angle,
)
from eol_cal.firmware.mech import MechConsts, block_mech_tables, mech_sum
from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, make_mech_tables, unused_mech
from eol_cal.firmware.mech_run import run_mech
from eol_cal.firmware.vectors import VectorSet, f32hex, scenario_rows_in_parallel
from eol_cal.domain.motor_params import load_motor

TICK_HZ = 20000.0
#: the flags of an identifying block: compensation, the interpolated angle, every estimator option, MECH_COMP_ENABLE
FLAGS_MECH = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
#: the constant i_qo (A) the scenarios run at
I_QO = 20.0
#: a scenario's drawn sensors: block id -> (seed, scale of the edge errors)
SENSORS = {"mech_a": (31, 1.0), "mech_weak": (32, 0.05), "mech_fwd_only": (33, 1.0)}


def sensors(block_id: str) -> SensorErrors:
    """The drawn sensor errors a golden block was measured on (64 PPR, the plant's spread)."""
    seed, scale = SENSORS[block_id]
    err = draw_sensor_errors(np.random.default_rng(seed), 64)
    return err._replace(edge_error=np.asarray(err.edge_error) * scale)


def golden_blocks_v2() -> list[tuple[str, B.ParamBlock]]:
    """The valid layout-2 blocks: the true fingerprint of each drawn encoder, orders 1..3, thresholds."""
    motor = load_motor("paper")
    out = []
    specs = [
        # id, table_len, fp_dirs, orders (c, phase_c, k, phase_k), iqc_limit, sequence
        ("mech_a", 256, FP_FORWARD | FP_REVERSE, ((0.009, 0.002, 0.001), (0.7, -1.2, 2.5), (2e-5, 0.0, 4e-6), (1.9, 0.0, -0.4)),
         6.5, 3),
        ("mech_weak", 64, FP_FORWARD | FP_REVERSE, ((0.012, 0.0, 0.0), (-2.2, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
         6.5, 4),
        ("mech_fwd_only", 16, FP_FORWARD, ((0.004, 0.003, 0.0), (3.0, 0.1, 0.0), (0.0, 1e-5, 0.0), (0.0, 1.0, 0.0)),
         0.5, 0xFFFFFFFE),
    ]
    for k, (bid, n, dirs, (c, pc, kk, pk), lim, seq) in enumerate(specs):
        err = sensors(bid)
        fp, gp = fingerprint_of(err, motor.poles)
        tc6, tp6 = compensator.make_tables(0.004 + 0.002 * k, 0.3 * k, 0.0006, -0.2, motor.kt, n)
        mtc, mtp = make_mech_tables(c, pc, kk, pk, motor.kt)
        if not dirs & FP_REVERSE:
            fp = fp.copy()
            fp[1::2] = 0.0  # not measured
        mech = unused_mech(motor.N_enc).replace(
            fp_dirs=dirs, grid_phase=gp, mech_c=c, mech_phase_c=pc, mech_k=kk, mech_phase_k=pk,
            mech_table_const=mtc, mech_table_per_amp=mtp, fingerprint=fp)
        out.append((bid, B.ParamBlock(
            sequence=seq, flags=FLAGS_MECH, serial=f"EPS-MECH-{k}", calibrated_at=1_767_225_600 + 86_400 * k,
            poles=motor.poles, encoder_ppr=motor.N_enc, tick_hz=motor.f_pwm, kt=motor.kt,
            hall_angle=hall_angle_of(err), c6=0.004 + 0.002 * k, phase_c6=0.3 * k, k6=0.0006, phase_k6=-0.2,
            lead_s=1.0 / (2 * math.pi * motor.current_bw_hz), iqc_limit=lim, table_const=tc6, table_per_amp=tp6,
            mech=mech)))
    return out


def golden_block(block_id: str) -> B.ParamBlock:
    return dict(golden_blocks_v2())[block_id]


Signals = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class MechScenario:
    """One identifier scenario: the block, the motion, injected faults.

    segments : (seconds, rpm_start, rpm_end); theta0 : mechanical angle at tick 0 (rad);
    jitter_deg : white noise on the angle the sensors are sampled at (mechanical degrees, seeded);
    inject : edits the sampled levels (a slip, a hall glitch), given the true angle and the sensors.
    """

    block_id: str
    segments: tuple[tuple[float, float, float], ...]
    theta0: float
    description: str
    jitter_deg: float = 0.0
    inject: Callable[[np.ndarray, Signals, SensorErrors], Signals] | None = None
    standstill_s: float = 1.0

    def theta_m(self) -> np.ndarray:
        return speed_profile_angle(self.segments, TICK_HZ, self.theta0)

    def signals(self) -> Signals:
        err = sensors(self.block_id)
        theta = self.theta_m()
        if self.jitter_deg:
            rng = np.random.default_rng(4242)
            theta = theta + np.radians(self.jitter_deg) * rng.standard_normal(theta.size)
        a, b, h = encoder_hall_signals(theta, 6, 64, err)
        if self.inject is not None:
            a, b, h = self.inject(self.theta_m(), (a.copy(), b.copy(), h.copy()), err)
        return a, b, h


def _slip(at_s: float) -> Callable[[np.ndarray, Signals, SensorErrors], Signals]:
    """From the middle of the quadrature count at ``at_s`` the encoder levels hold while the rotor
    turns one whole pitch (a pulse lost on both channels): the levels then agree again, no step is
    seen, and the count lags the rotor by 4 (a slipped count the estimator cannot see)."""
    def inject(theta: np.ndarray, sig: Signals, err: SensorErrors) -> Signals:
        a, b, h = sig
        i0 = int(at_s * TICK_HZ)
        phase = 2 * b + (a ^ b)
        changes = np.flatnonzero(phase[i0:] != phase[i0]) + i0
        mid = (i0 + int(changes[0])) // 2  # the middle of the current count
        i1 = mid + int(np.argmax(theta[mid:] >= theta[mid] + 2 * math.pi / 64))
        a[mid:i1], b[mid:i1] = a[mid], b[mid]
        return a, b, h
    return inject


def _hall_glitch(at_s: float) -> Callable[[np.ndarray, Signals, SensorErrors], Signals]:
    """One tick of hall state 7 at ``at_s``: a hall fault."""
    def inject(theta: np.ndarray, sig: Signals, err: SensorErrors) -> Signals:
        a, b, h = sig
        h[int(at_s * TICK_HZ)] = 7
        return a, b, h
    return inject


_PP = 2 * math.pi / 3  # one pole pair, mechanical

SCENARIOS: dict[str, MechScenario] = {
    "mech_pole_pair_0.csv": MechScenario("mech_a", ((0.7, 300.0, 300.0),), 0.41,
                                         "300 rpm forward from under pole pair 0: identified after three revolutions"),
    "mech_pole_pair_1.csv": MechScenario("mech_a", ((0.7, 300.0, 300.0),), 0.41 + _PP + 0.05,
                                         "300 rpm forward from under pole pair 1"),
    "mech_pole_pair_2.csv": MechScenario("mech_a", ((0.7, 300.0, 300.0),), 0.41 + 2 * _PP + 0.13,
                                         "300 rpm forward from under pole pair 2"),
    "mech_reverse.csv": MechScenario("mech_a", ((0.75, -300.0, -300.0),), 5.0,
                                     "300 rpm in reverse: identified on the reverse fingerprint"),
    "mech_reverse_fwd_only.csv": MechScenario("mech_fwd_only", ((0.75, -300.0, -300.0),), 2.0,
                                              "300 rpm in reverse with a block that has the forward fingerprint only: "
                                              "never identified"),
    "mech_speed_change.csv": MechScenario("mech_a", ((0.3, 300.0, 300.0), (0.15, 300.0, 200.0), (0.95, 200.0, 200.0)), 3.3,
                                          "300 rpm, a ramp to 200 rpm (no samples while the speed changes), 200 rpm"),
    "mech_noise.csv": MechScenario("mech_a", ((1.3, 300.0, 300.0),), 1.7,
                                   "300 rpm with timing noise on the encoder (0.002 mechanical degrees), a hall "
                                   "fault (state 7 for a tick) after identification: withdrawn, identified again",
                                   jitter_deg=0.002, inject=_hall_glitch(0.75)),
    "mech_slip.csv": MechScenario("mech_a", ((1.5, 300.0, 300.0),), 0.9,
                                  "300 rpm, identified, then the count slips a whole pulse unseen: the hall fraction "
                                  "withdraws the compensation within a revolution, identified again one pulse on",
                                  inject=_slip(0.75)),
    "mech_weak.csv": MechScenario("mech_weak", ((0.8, 300.0, 300.0),), 0.2,
                                  "300 rpm, an encoder whose fingerprint is too weak (edge errors 0.005 degrees): "
                                  "evaluated, never identified, no mechanical current"),
}

#: the scenario files' ulp classes: the identification's cosine and margin on a target whose
#: division and square root are the C28x's (estimate + two Newton steps, :mod:`fpu_c28x`); the
#: largest difference the twin measures over every scenario (``tests/test_fpu_classes.py``
#: recomputes it); every other column exact (the decisions do not change, measured likewise)
SCENARIO_ULP = {"score": 5, "margin": 5}

SCENARIO_COLUMNS = ("tick", "enc_a", "enc_b", "hall", "i_qo", "status", "learn", "active", "r", "events",
                    "score", "margin", "i_qc")
CONFIG_COLUMNS = ("file", "block_id", "standstill_ticks", "DELTA", "INV_DELTA", "KM", "EF_0", "EF_1")
COMP_COLUMNS = ("block_id", "q", "r", "theta_hat", "omega_hat", "i_qo", "i_qc")


def _config_row(name: str, sc: MechScenario) -> list[str]:
    blk = golden_block(sc.block_id)
    cfg = EstimatorConfig.from_block(blk, standstill_s=sc.standstill_s)
    mc = MechConsts.of(cfg)
    tb = block_mech_tables(blk)
    return [name, sc.block_id, str(cfg.standstill_ticks), f32hex(mc.DELTA), f32hex(mc.INV_DELTA), f32hex(mc.KM),
            f32hex(tb.EF[0]), f32hex(tb.EF[1])]


def scenario_rows(sc: MechScenario) -> list[list[str]]:
    """Rows of one scenario file: inputs and the numpy reference's outputs, tick by tick."""
    a, b, h = sc.signals()
    out = run_mech(golden_block(sc.block_id), a, b, h, I_QO, standstill_s=sc.standstill_s)
    iq = f32hex(I_QO)
    # Python ints (tolist) formatted: the same text as numpy scalars', without a conversion per field
    ints = [np.asarray(x).tolist() for x in (a, b, h, out.status, out.learn, out.active, out.r, out.events)]
    bits = [x.view(np.uint32).tolist() for x in (out.score, out.margin, out.i_qc)]
    return [[str(i), str(ai), str(bi), str(hi), iq, str(st), str(le), str(ac), str(r), str(ev), f"{sc:08x}", f"{mg:08x}",
             f"{ic:08x}"]
            for i, (ai, bi, hi, st, le, ac, r, ev, sc, mg, ic) in enumerate(zip(*ints, *bits, strict=True))]


def compensator_rows(seed: int = 1202) -> list[list[str]]:
    """i_qc with the mechanical part on: random counts, offsets, angles (some beside a wrap),
    speeds and currents over each layout-2 block."""
    rows = []
    rng = np.random.default_rng(seed)
    for bid, blk in golden_blocks_v2():
        cfg = EstimatorConfig.from_block(blk)
        mc = MechConsts.of(cfg)
        tb = block_mech_tables(blk)
        n = 300
        q = rng.integers(0, mc.M, n).astype(np.int32)
        r = rng.integers(0, mc.N, n).astype(np.int32)
        q[:4], r[:4] = (0, mc.M - 1, 1, mc.M - 2), (0, mc.N - 1, mc.N - 1, 0)
        th = rng.uniform(-1.0, 7.3, n).astype(np.float32)
        th[4:8] = np.float32([0.0, 2 * math.pi - 1e-6, -1e-7, 6.2831855])
        om = rng.uniform(-800, 800, n).astype(np.float32)
        iq = rng.uniform(-70, 70, n).astype(np.float32)
        sm = mech_sum(mc, tb, r, q, th, om, iq)
        out = compensator.i_qc(th, om, iq, blk.table_const, blk.table_per_amp, blk.lead_s, blk.iqc_limit,
                               mech_on=np.ones(n, bool), mech_sum=sm)
        for k in range(n):
            rows.append([bid, str(int(q[k])), str(int(r[k])), f32hex(th[k]), f32hex(om[k]), f32hex(iq[k]), f32hex(out[k])])
    return rows


def block_rows() -> list[list[str]]:
    rows = []
    for bid, b in golden_blocks_v2():
        image = B.pack(b)
        m = b.mech
        rows.append([bid, str(b.sequence), str(b.flags), str(b.table_len), str(b.block_bytes), str(m.fp_len),
                     str(m.fp_dirs), f32hex(m.grid_phase), f32hex(m.id_min_score), f32hex(m.id_margin),
                     f32hex(m.id_frac_tol), str(B.check(image).crc_stored), image.hex()])
    return rows


BLOCK_COLUMNS = ("id", "sequence", "flags", "table_len", "block_bytes", "fp_len", "fp_dirs", "grid_phase",
                 "id_min_score", "id_margin", "id_frac_tol", "crc32", "image")


def check_cases() -> list[tuple[str, bytes, int]]:
    """(id, image, expected status) of the check routine on layout-2 images."""
    blocks = golden_blocks_v2()
    img = B.pack(blocks[0][1])
    small = B.pack(blocks[2][1])
    n_small = blocks[2][1].table_len
    V, C, H = B.STATUS_VALID, B.STATUS_CRC_MISMATCH, B.STATUS_HEADER_INVALID

    def patch(image: bytes, name: str, value: int, fix_crc: bool = True) -> bytes:
        buf = bytearray(image)
        n = int.from_bytes(image[96:98], "little")
        fmt_size = {"u16": 2, "u32": 4}[B.FIELDS_BY_VERSION[2][name]["type"]]
        off = B.field_offset(name, n, 2)
        buf[off:off + fmt_size] = value.to_bytes(fmt_size, "little")
        return B.with_crc(bytes(buf), version=2) if fix_crc else bytes(buf)

    ext = bytearray(img)
    ext[B.field_offset("fingerprint", blocks[0][1].table_len, 2) + 9] ^= 0x04
    crc_v1_place = bytearray(small)
    v1_crc_at = B.field_offset("crc32", n_small, 1)
    crc_v1_place[v1_crc_at:v1_crc_at + 4] = B.crc32(small[:v1_crc_at]).to_bytes(4, "little")
    return [
        ("valid_mech_a", img, V),
        ("valid_mech_fwd_only_in_erased_tail", small + b"\xff" * 600, V),
        ("valid_reserved2_nonzero", patch(small, "reserved2", 7), V),
        ("valid_mech_table_len_other", patch(small, "mech_table_len", 64), V),
        ("block_bytes_of_layout_1", patch(small, "block_bytes", B.block_bytes(n_small, 1)), H),
        ("layout_1_image_says_2", _as_layout_2(B.pack(replace(blocks[2][1], mech=None, layout_version=1,
                                                               flags=FLAG_COMP_ENABLE))), H),
        ("extension_truncated", small[:-40], H),
        ("crc_extension_bit_flipped", bytes(ext), C),
        ("crc_at_layout_1_place", bytes(crc_v1_place), C),
        ("sequence_0", patch(small, "sequence", 0), H),
    ]


def vector_sets() -> dict[str, VectorSet]:
    """Every layout-2 vector set, by file name (configs before the scenarios)."""
    sets = {
        "blocks_v2.csv": VectorSet(BLOCK_COLUMNS, block_rows(),
                                   "valid layout-2 blocks: header and mechanical scalars (floats binary32 hex), "
                                   "crc32 decimal, the exact image"),
        "block_checks_v2.csv": VectorSet(("id", "image_bytes", "status", "image"),
                                         [[cid, str(len(im)), str(st), im.hex()] for cid, im, st in _checked(check_cases())],
                                         "check routine on layout-2 images: expected status, avail_bytes = image_bytes"),
        "mech_configs.csv": VectorSet(CONFIG_COLUMNS, [_config_row(n, sc) for n, sc in SCENARIOS.items()],
                                      "configuration of each mech_*.csv scenario (block of blocks_v2.csv, standstill "
                                      "bound) and the constants eol_mech_init derives"),
        "mech_compensator.csv": VectorSet(COMP_COLUMNS, compensator_rows(),
                                          "i_qc = eol_comp_iqc_mech(theta_hat, omega_hat, i_qo, ...) with the mechanical "
                                          "part on at count q and offset r, tables of blocks_v2.csv row block_id",
                                          {"i_qc": {"abs": 1e-3, "unit": "A"}}),
    }
    rows = scenario_rows_in_parallel(_rows_of, list(SCENARIOS), lambda n: sum(s[0] for s in SCENARIOS[n].segments))
    for name, sc in SCENARIOS.items():
        sets[name] = VectorSet(SCENARIO_COLUMNS, rows[name], sc.description, ulp=SCENARIO_ULP)
    return sets


def _rows_of(name: str) -> list[list[str]]:
    """:func:`scenario_rows` of scenario file ``name`` (a worker process's task)."""
    return scenario_rows(SCENARIOS[name])


def _as_layout_2(image: bytes) -> bytes:
    """A layout-1 image whose header says layout 2 (its CRC recomputed where layout 1 has it)."""
    return B.with_crc(image[:2] + (2).to_bytes(2, "little") + image[4:], version=1)


def _checked(cases: list[tuple[str, bytes, int]]) -> list[tuple[str, bytes, int]]:
    for cid, image, status in cases:
        got = B.check(image).status
        if got != status:
            raise AssertionError(f"layout-2 check case {cid}: reference gives {got}, case expects {status}")
    return cases
