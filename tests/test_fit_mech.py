"""End of line for revision 1.2 on the plant: the fit measures the fingerprint and the mechanical
orders, the table is a layout-2 block, the plant's ECU identifies in the pre-roll and compensates;
a motor whose fingerprint is too weak gets MECH_COMP_ENABLE off with the reason; a layout-1 block
and a layout-2 block with the bit off run as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec
from eol_cal.analysis.fit.motors import FitOptions, fit_motors
from eol_cal.analysis.fit.table import block_from_result, mech_off_reasons
from eol_cal.analysis.metrics import capture_ripple_pp
from eol_cal.firmware import block as B
from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE
from eol_cal.plant.profile import load_profile
from eol_cal.plant.simulate import simulate

from eol_cal.sim.mech_motors import BEST, MOTOR, station_runs, station_windows


@pytest.fixture(scope="module")
def calibrated():
    """Two plant motors calibrated as the station does (eol-default under the prepared block, fit)."""
    plants, runs = station_runs()
    fitted = fit_motors([r.capture for r in runs], FitOptions(spec=FitSpec(), capture_metrics=False,
                                                              estimator_options=BEST))
    return plants, runs, fitted.results


def test_the_fit_measures_the_fingerprint_and_the_orders(calibrated):
    plants, _, results = calibrated
    res = results[0]
    assert res.status == "ok"
    mech = res.mech
    assert mech is not None and mech.status == "ok" and mech.reasons == () and mech.dirs & 1
    assert mech.margin >= mech.threshold and mech.windows == (0,)
    # order 1: the rotor's unbalance (plus what the encoder's placement makes of it), with an interval
    o1 = mech.orders[0]
    assert abs(o1.c.value - plants[0].unb1) < 0.25 * plants[0].unb1 + 3 * o1.c.ci95
    assert 0 < o1.c.ci95 < 0.2 * o1.c.value
    # the fingerprint in electrical radians: the plant's placement errors are 0.1 deg mechanical (sigma)
    fp = np.asarray(mech.fingerprint)[0::2]
    assert 0.5 < np.std(fp) / np.radians(0.3) < 1.5


def test_a_weak_fingerprint_switches_mech_off_with_the_reason(calibrated):
    _, _, results = calibrated
    res = results[1]
    assert res.status == "ok" and res.mech is not None and res.mech.status == "off"
    assert any("too weak" in r for r in res.mech.reasons)
    blk = block_from_result(res, MOTOR, options=BEST)
    assert blk.layout_version == 2 and not blk.flags & FLAG_MECH_COMP_ENABLE
    assert mech_off_reasons(res, blk.flags) and B.check(B.pack(blk)).valid


def test_the_block_carries_the_firmwares_runtime_thresholds_not_the_switchs(calibrated):
    """The result's thresholds are end of line's switch on its prediction (a margin of 0, a cosine
    of 0.29); the block's ``id_margin`` and ``id_min_score`` are what the ECU must measure itself
    before it applies a frame (0.25, 0.5: docs/firmware-contract.md). The block once carried the
    switch's margin of 0 as ``id_margin``: the firmware's margin check then passed whatever it measured."""
    from eol_cal.firmware.mech_params import ID_MARGIN, ID_MIN_SCORE, SWITCH_MARGIN, SWITCH_MIN_SCORE

    _, _, results = calibrated
    mech = results[0].mech
    assert mech is not None and mech.threshold == SWITCH_MARGIN and mech.min_score == SWITCH_MIN_SCORE
    blk = block_from_result(results[0], MOTOR, options=BEST)
    assert blk.mech is not None and blk.flags & FLAG_MECH_COMP_ENABLE
    assert blk.mech.id_margin == np.float32(ID_MARGIN) and blk.mech.id_min_score == np.float32(ID_MIN_SCORE)
    assert blk.mech.id_margin > mech.threshold
    back = B.unpack(B.pack(blk))
    assert back.mech is not None and back.mech.id_margin == np.float32(ID_MARGIN)


@pytest.mark.slow  # a compensated plant run; the fit tests keep the module in the fast loop
def test_the_layout_2_block_identifies_in_the_pre_roll_and_cancels_order_1(calibrated):
    plants, _, results = calibrated
    six = [block_from_result(r, MOTOR, options=BEST, layout=1) for r in results]
    two = [block_from_result(r, MOTOR, options=BEST) for r in results]
    assert two[0].flags & FLAG_MECH_COMP_ENABLE
    point = load_profile("paper")
    a6 = simulate(plants, point, mode="compensated", blocks=six, seed=99)
    a2 = simulate(plants, point, mode="compensated", blocks=two, seed=99)
    # the strong motor: identified before the recording starts, all along
    assert a2[0].mech_active.min() == 1
    pp6, pp2 = capture_ripple_pp(a6[0].capture), capture_ripple_pp(a2[0].capture)
    assert pp2.filtered_pct < pp6.filtered_pct - 0.5 * (pp6.filtered_pct - pp6.no_mech1_pct)
    assert pp2.filtered_pct < 1.0
    # the weak motor's block has MECH_COMP_ENABLE off: never identified (its run is otherwise the
    # 6th-harmonic block's, bit for bit, when the batch's pre-roll is the same: the last test)
    assert a2[1].mech_active.max() == 0


def test_a_dyno_capture_of_windows_gives_the_same_frame_and_orders(calibrated):
    """The station's capture is one window per profile segment (the count lost between them): the
    windows are placed by the halls and the fingerprint; the orders agree with the continuous capture's."""
    _, runs, results = calibrated
    cap = runs[0].capture
    joined = station_windows(cap, load_profile("eol-default"))
    mech = fit_motors([joined], FitOptions(capture_metrics=False, estimator_options=BEST)).results[0].mech
    ref = results[0].mech
    assert mech is not None and ref is not None and mech.status == "ok" and sum(w is not None for w in mech.windows) >= 6
    o, r = mech.orders[0], ref.orders[0]
    assert abs(o.c.value - r.c.value) < 3 * (o.c.ci95 + r.c.ci95)
    assert abs(mech.margin - ref.margin) < 0.1


@pytest.mark.slow  # two plant runs
def test_a_layout_1_block_runs_exactly_as_revision_1_1(calibrated):
    """The plant's ECU with a layout-1 block and with the same block as layout 2, MECH off: the
    identifier does not run and every sample is the same."""
    plants, _, results = calibrated
    one = block_from_result(results[0], MOTOR, options=BEST, layout=1)
    off = dataclasses.replace(block_from_result(results[0], MOTOR, options=BEST),
                              flags=one.flags)  # layout 2, MECH_COMP_ENABLE clear
    point = load_profile("paper")
    (r1,) = simulate(plants[0], point, mode="compensated", blocks=one, seed=5)
    (r2,) = simulate(plants[0], point, mode="compensated", blocks=off, seed=5)
    for name in ("torque", "iqc", "enc_a"):
        np.testing.assert_array_equal(r1.capture[name], r2.capture[name])


def test_the_fit_angle_is_corrected_by_the_fingerprint(calibrated):
    """Issue 34: the offline angle carries the encoder's pitch errors (0.24 deg electrical RMS on this
    motor); corrected by the fingerprint the fit measures it is within a third of that of the
    plant's true angle, on every segment."""
    from eol_cal.analysis.fit.capture import motor_inputs

    _, runs, _ = calibrated
    run = runs[0]
    (mi,) = motor_inputs([run.capture], estimator_options=BEST)
    assert mi.angle_correction.startswith("fingerprint (8 of 8 segments")
    for s, o in enumerate(mi.info):
        true = np.asarray(run.theta_r)[o.start:o.stop]
        for theta, bound in ((mi.angles[0].theta_r[o.start:o.stop], None), (mi.segments.theta[s], "corrected")):
            d = np.unwrap(np.angle(np.exp(1j * (np.asarray(theta) - true))))
            rms = float(np.std(d))
            if bound is None:
                raw = rms
            else:
                assert rms < raw / 3, (s, rms, raw)
