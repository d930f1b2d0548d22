"""The plant's tick loop for a batch whose ECUs identify (layout 2): the identifier's background
evaluation runs out of the inner tick loop (``simulate._identifying_ticks``), so XLA can compile
that loop into one kernel. Every tick and background slice must be what the plain scan (tick, then
the background slice, every tick) gives, bit for bit, through identifications, evaluations and
revolution marks, across chunk boundaries; and the loop kernel must be compiled where the process
asks for it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("jax")

_COMPARE = textwrap.dedent("""
    import json, sys
    import jax
    import numpy as np
    from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.numerics.packing import unpack
    from eol_cal.plant import simulate as S
    from eol_cal.plant.ecu_model import true_block
    from eol_cal.plant.profile import constant
    from eol_cal.plant.tick import background
    from eol_cal.plant.variation import draw_motor

    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
    specs = [draw_motor(s) for s in range(3)]
    blocks = [true_block(s, flags=flags, mech=True) for s in specs]
    prof = constant(200.0, 0.3, iq=40.0)  # pre-roll: four revolutions at 200 rpm (1.2 s), 6 chunks in all

    def run():
        S._COMPILED.clear()
        carry = []
        res = S.simulate(specs, prof, mode="compensated", blocks=blocks, seed=2, carry_out=carry)
        arrays = [np.asarray(v) for r in res for v in (*r.capture.channels.values(), r.theta_r, r.theta_hat,
                                                         r.theta_enc, r.mech_active, r.theta_m)]
        state = unpack(carry[0].packing, carry[0].state)  # the scan's state, leaf by leaf
        return arrays + [np.asarray(x) for x in jax.tree_util.tree_leaves(state)], res

    new, res = run()

    def plain(cfg, p, one_tick, carry, xs, n_ticks):  # the scan as it was: tick, then background
        def body(c, x):
            c, y = one_tick(c, x)
            return background(cfg, p, c), y
        return jax.lax.scan(body, carry, xs)

    S._identifying_ticks = plain
    old, _ = run()
    same = len(new) == len(old) and all(a.dtype == b.dtype and a.tobytes() == b.tobytes() for a, b in zip(new, old))
    print(json.dumps({"same": same, "arrays": len(new),
                      "identified": [int(r.mech_active.min()) for r in res]}))
""")


def _run(script: str, env_flags: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if env_flags:
        env["XLA_FLAGS"] = env_flags
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # two plant programs compiled and 1.5 s of three motors run, in a process of its own
def test_the_split_loop_gives_the_plain_scan_bit_for_bit():
    # a process of its own with XLA's defaults: the suite may have let the CLI switch the loop
    # kernel on in this one (numerics.xla.configure_xla), where the plain scan keeps the library
    # kernels in its loop and the split loop's ticks run as one kernel, rounding differently
    got = _run(_COMPARE, "")
    assert got["identified"] == [1, 1, 1]  # every motor identified before the recording, and stays so
    assert got["arrays"] > 60
    assert got["same"]


_KERNEL = textwrap.dedent("""
    import json
    from eol_cal.numerics.xla import configure_xla
    assert configure_xla()  # before the process's first JAX computation
    import jax
    from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.plant import simulate as S
    from eol_cal.plant.ecu_model import true_block
    from eol_cal.plant.profile import constant
    from eol_cal.plant.variation import draw_motor

    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
    specs = [draw_motor(s) for s in range(3)]
    text = {}
    jit = jax.jit

    def spy(f, *a, **k):  # the chunk's program as XLA compiled it
        j = jit(f, *a, **k)
        def call(*args):
            if getattr(f, "__name__", "") == "chunk":
                text["hlo"] = j.lower(*args).compile().as_text()
            return j(*args)
        return call

    jax.jit = spy
    S.simulate(specs, constant(60.0, 0.05, iq=40.0), mode="compensated", pre_roll_s=0.0,
               blocks=[true_block(s, flags=flags, mech=True) for s in specs])
    n = S.chunk_ticks_for(len(specs))
    ys = f"f32[{n},{len(specs)},{len(S.OUT_COLUMNS)}]"  # the ticks' outputs, carried by the tick loop
    small = [line for line in text["hlo"].splitlines() if 'xla_cpu_small_call="true"' in line]
    print(json.dumps({"tick_loop_one_kernel": any(ys in line for line in small)}))
""")


@pytest.mark.slow  # a process of its own that compiles a plant program (CONTRIBUTING.md, "Fast or slow")
def test_the_tick_loop_of_an_identifying_batch_compiles_into_one_kernel():
    # where the process lets XLA compile small loops into one kernel (numerics.xla.configure_xla),
    # the tick loop of a layout-2 batch is one (no scatter, no library kernel inside): ~1.5x per tick
    got = _run(_KERNEL, "")
    assert got["tick_loop_one_kernel"]


_ROUNDING = textwrap.dedent("""
    import dataclasses, sys
    import numpy as np
    where, loop = sys.argv[1], sys.argv[2] == "loop"
    if loop:
        from eol_cal.numerics.xla import configure_xla
        assert configure_xla()  # before the process's first JAX computation
    from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.firmware.mech_params import make_mech_tables
    from eol_cal.plant.ecu_model import true_block
    from eol_cal.plant.profile import constant
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
    specs = [draw_motor(s) for s in range(3)]
    blocks = [true_block(s, flags=flags, mech=True) for s in specs]
    prof = constant(200.0, 0.3, iq=40.0)  # after the default pre-roll (1.2 s): every motor identified

    def run(name, bl):
        res = simulate(specs, prof, mode="compensated", blocks=bl, seed=2)
        np.savez(f"{where}/{name}.npz", **{f"{k}{i}": v for i, r in enumerate(res) for k, v in (
            ("iq", r.capture.channels["iq"]), ("iqc", r.capture.channels["iqc"]),
            ("torque", r.capture.channels["torque"]), ("mech_active", r.mech_active))})

    run("loop" if loop else "default", blocks)
    if not loop:  # real changes the tolerance must not let through: motor 0's mechanical order 1
        m, kt = blocks[0].mech, specs[0].motor.kt
        c = (0.0, *m.mech_c[1:])
        tc, tp = make_mech_tables(c, m.mech_phase_c, (0.0,) * 3, (0.0,) * 3, kt)
        run("dropped", [dataclasses.replace(blocks[0], mech=m.replace(mech_c=c, mech_table_const=tc,
                                                                      mech_table_per_amp=tp)), *blocks[1:]])
        run("flipped", [dataclasses.replace(blocks[0], mech=m.replace(mech_table_const=-m.mech_table_const,
                                                                      mech_table_per_amp=-m.mech_table_per_amp)),
                        *blocks[1:]])
""")

#: How far a layout-2 run under numerics.xla.configure_xla (the tick loop one kernel) may lie from
#: the same run under XLA's defaults (float32 rounding of another fusion, carried through the ticks),
#: per motor: the compensation's state identical; i_qc within 0.02 A everywhere (seen 0.007 A); i_q
#: within 0.05 A rms (seen 0.017 A); the transducer's mean within 1e-4 and its p-p within 10 % (seen
#: 4e-5 and 2 %: one 0.5 mN*m step of its resolution). Dropping a motor's order 1 from its table
#: moves i_qc by 0.26 A, i_q by 0.19 A rms and the p-p by +73 %; a wrong sign 0.52 A, 0.37 A, +155 %.
IQC_TOL_A, IQ_RMS_TOL_A, TQ_MEAN_REL, TQ_PP_REL = 0.02, 0.05, 1e-4, 0.10


def _rounding_apart(a: dict, b: dict, n: int) -> list[str]:
    """What lies beyond the tolerance between two runs' arrays (empty: within it)."""
    bad = []
    for i in range(n):
        def d(k: str, i: int = i) -> np.ndarray:
            return np.asarray(a[f"{k}{i}"], np.float64) - np.asarray(b[f"{k}{i}"], np.float64)

        tq_a, tq_b = a[f"torque{i}"], b[f"torque{i}"]
        checks = {
            "mech_active": np.array_equal(a[f"mech_active{i}"], b[f"mech_active{i}"]),
            "iqc": np.abs(d("iqc")).max() <= IQC_TOL_A,
            "iq": np.sqrt(np.mean(d("iq") ** 2)) <= IQ_RMS_TOL_A,
            "torque mean": abs(tq_a.mean() - tq_b.mean()) <= TQ_MEAN_REL * abs(tq_a.mean()),
            "torque p-p": abs(np.ptp(tq_a) - np.ptp(tq_b)) <= TQ_PP_REL * np.ptp(tq_a),
        }
        bad += [f"motor {i}: {k}" for k, ok in checks.items() if not ok]
    return bad


@pytest.mark.slow  # three motors, 1.5 s each, four runs in two processes of their own
def test_the_loop_kernel_rounds_a_layout_2_run_within_the_stated_tolerance(tmp_path):
    # configure_xla (the CLI, the benchmarks, a refit worker) compiles the tick loop into one
    # kernel, which rounds the float32 arithmetic differently from XLA's defaults: not bit for
    # bit, but within IQC_TOL_A & co.; a dropped or sign-flipped mechanical order is not
    for mode in ("default", "loop"):
        env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        subprocess.run([sys.executable, "-c", _ROUNDING, str(tmp_path), mode], env=env, timeout=900, check=True)
    runs = {name: dict(np.load(tmp_path / f"{name}.npz")) for name in ("default", "loop", "dropped", "flipped")}
    ref = runs["default"]
    assert all(ref[f"mech_active{i}"].min() == 1 for i in range(3))  # identified before the recording
    assert not all(np.array_equal(ref[f"iq{i}"], runs["loop"][f"iq{i}"]) for i in range(3))  # two programs ran
    assert _rounding_apart(ref, runs["loop"], 3) == []
    for wrong in ("dropped", "flipped"):
        assert {"motor 0: iqc", "motor 0: iq", "motor 0: torque p-p"} <= set(_rounding_apart(ref, runs[wrong], 3))
