"""The ECU state in a capture's metadata (ecu_before.* / ecu_after.*): written and read back by
both formats, malformed records refused, simulated captures carrying the state they simulate."""

from __future__ import annotations

import dataclasses

import pytest

from eol_cal.capture import read_capture, write_capture
from eol_cal.capture.ecu_state import EcuState, Trace, check_trace, trace_of, with_ecu_state
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.errors import InputError

BEFORE = EcuState(1, 7, "00c0ffee", "COMP_ENABLE|INTERP_ENABLE", "0042")
AFTER = EcuState(0, 8, "12345678", "INTERP_ENABLE", "0042")


def small():
    return synthetic_capture(rpm=60.0, seconds=0.5, fs=5000.0, serial="E-1", seed=4)


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
@pytest.mark.parametrize("states", [(BEFORE, AFTER), (EcuState(None), EcuState(None, serial="E-1")),
                                    (EcuState(None, serial="12"), BEFORE)])
def test_ecu_state_round_trips_through_both_formats(tmp_path, suffix, states):
    c = small()
    c = dataclasses.replace(c, metadata=with_ecu_state(c.metadata, *states))
    path = tmp_path / f"c{suffix}"
    write_capture(c, path)
    back = read_capture(path)
    # digits-only CRC and serial stay text, the sequence an integer
    assert trace_of(back.metadata, str(path)) == Trace(*states)
    assert {k: v for k, v in back.metadata.items() if k.startswith("ecu_")} == {
        k: v for k, v in c.metadata.items() if k.startswith("ecu_")}


def test_the_metadata_keys_are_the_documented_ones():
    assert BEFORE.to_metadata("ecu_before") == {
        "ecu_before.bank": "1", "ecu_before.sequence": 7, "ecu_before.crc32": "00c0ffee",
        "ecu_before.flags": "COMP_ENABLE|INTERP_ENABLE", "ecu_before.serial": "0042"}
    assert EcuState(None).to_metadata("ecu_after") == {"ecu_after.bank": "none"}


@pytest.mark.parametrize(("lines", "field", "reason"), [
    (["ecu_before.bank: 2", "ecu_after.bank: none"], "ecu_before.bank", "must be 0, 1 or none"),
    (["ecu_before.bank: 1", "ecu_before.crc32: 00c0ffee", "ecu_before.flags: none", "ecu_after.bank: none"],
     "ecu_before.sequence", "missing"),
    (["ecu_before.bank: 1", "ecu_before.sequence: 3", "ecu_before.crc32: xyz", "ecu_before.flags: none",
      "ecu_after.bank: none"], "ecu_before.crc32", "8 hex digits"),
    (["ecu_before.serial: M-1", "ecu_after.bank: none"], "ecu_before.bank", "missing"),
    (["ecu_before.bank: none", "ecu_after.bank: 0", "ecu_after.sequence: x", "ecu_after.crc32: 00000000",
      "ecu_after.flags: none"], "ecu_after.sequence", "integer"),
])
def test_a_malformed_ecu_record_is_refused_when_read(tmp_path, lines, field, reason):
    path = tmp_path / "bad.csv"
    write_capture(small(), path)
    text = path.read_text().replace("# ecu_before.bank: none\n# ecu_after.bank: none\n", "")
    path.write_text("".join(f"# {line}\n" for line in lines) + text)
    with pytest.raises(InputError) as err:
        read_capture(path)
    assert err.value.file == str(path) and err.value.field == field and reason in err.value.reason


def test_check_trace_refuses_and_allows():
    f = "x.mf4"
    assert check_trace(Trace(AFTER, AFTER), f) == []
    assert check_trace(Trace(EcuState(None), EcuState(None)), f) == []
    with pytest.raises(InputError, match="untraced"):
        check_trace(Trace(None, None), f)
    assert "untraced" in check_trace(Trace(None, None), f, allow_untraced=True)[0]
    with pytest.raises(InputError, match="under compensation"):
        check_trace(Trace(BEFORE, BEFORE), f, allow_untraced=True)
    assert "under compensation" in check_trace(Trace(BEFORE, BEFORE), f, allow_compensated=True)[0]
    for trace in (Trace(BEFORE, AFTER), Trace(AFTER, None)):  # never allowed
        with pytest.raises(InputError) as err:
            check_trace(trace, f, allow_untraced=True, allow_compensated=True)
        assert err.value.file == f
    # the serial alone does not make another block
    assert check_trace(Trace(AFTER, dataclasses.replace(AFTER, serial=None)), f) == []


def test_simulated_captures_carry_the_state_they_simulate():
    from eol_cal.firmware import block as B
    from eol_cal.plant.presets import preset_spec
    from eol_cal.plant.ecu_model import simulated_ecu_state, true_block

    spec = preset_spec("paper")
    assert simulated_ecu_state(spec, "raw", None) == EcuState(None)
    est = simulated_ecu_state(spec, "estimated", None)
    comp = simulated_ecu_state(spec, "compensated", None)
    assert est.flags == "INTERP_ENABLE" and comp.flags == "COMP_ENABLE|INTERP_ENABLE" and est.bank == comp.bank == 0
    image = B.pack(true_block(spec))
    assert comp.crc32 == f"{B.check(image).crc_stored:08x}" and est.crc32 != comp.crc32
    # a layout-2 block's state from its image, packed once and kept (the same CRC every time)
    from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR

    blk = true_block(spec, flags=B.FLAG_COMP_ENABLE | B.FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE,
                     mech=True)
    want = f"{B.check(B.pack(blk)).crc_stored:08x}"
    assert simulated_ecu_state(spec, "compensated", blk).crc32 == want == simulated_ecu_state(spec, "compensated", blk).crc32
    assert blk.image == B.pack(blk) and simulated_ecu_state(spec, "estimated", blk).crc32 != want
    # the analytic model: the raw encoder angle, no block
    assert trace_of(small().metadata) == Trace(EcuState(None), EcuState(None))


def test_an_ecu_of_another_serial_is_refused():
    """The dyno ran motor M-0007 while the ECU on the bus said M-0001: its block and hall table are another motor's."""
    f = "c.mf4"
    ecu = dataclasses.replace(AFTER, serial="M-0001")
    with pytest.raises(InputError, match=r"c\.mf4.*ecu_before\.serial.*M-0001 \(F18C\).*M-0007"):
        check_trace(Trace(ecu, ecu), f, serial="M-0007", allow_untraced=True, allow_compensated=True)
    assert check_trace(Trace(ecu, ecu), f, serial="M-0001") == []
    unread = dataclasses.replace(AFTER, serial=None)  # a simulated capture: no F18C read
    assert check_trace(Trace(unread, unread), f, serial="M-0007") == []
