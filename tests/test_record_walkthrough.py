"""Issue 20's walkthrough, as a new station engineer on a PostgreSQL line would do it (and on
SQLite): a mis-scanned serial, a dead dyno and a wrong key, then a passing run, a re-test, and
restoring the calibration before the re-test; a loopback station (pymodbus dyno simulator on the
plant, ISO-TP ECU simulator with its flash in a file).

What the records must say: refusals are kept with their own Pareto but are no motor result
(first-pass yield 1.0, latest status pass, no ``lot diff`` change); each block flashed is
archived byte for byte as the ECU's bank holds it; ``ecu restore --bank previous`` refuses the
prepare block; ``ecu restore --calibration previous`` brings the earlier calibration back.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

from click.testing import CliRunner
import pytest

from cli.main import cli
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.firmware import block as B
from eol_cal.plant.presets import paper
from eol_cal.sim.loopback import loopback_station
from eol_cal.records.query import query_records
from test_station_run import files, run_args, wait_stopped  # noqa: F401 - the module's fixtures

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop

SERIAL = "W-0001"


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(files, st, serial, db, tmp_path, *extra, dyno=None):  # noqa: F811
    args = run_args(files, st, serial, db, tmp_path / "reports", *extra)
    if dyno is not None:
        args[args.index("--dyno") + 1] = dyno
    res = CliRunner().invoke(cli, args)
    wait_stopped(st.dyno.sim)
    return res.exit_code, json.loads(res.stdout)["record"]


def _zeroed(data: bytes) -> bytes:
    """A block without its sequence and CRC (what a re-flash as a new sequence changes)."""
    import dataclasses

    blk = B.unpack(data, "block")
    return B.pack(dataclasses.replace(blk, sequence=1))[:-4]


def _banks(flash: Path, n: int) -> dict[int, bytes]:
    f = NorFlash(flash)
    return {bank: f.read(bank, 0, n) for bank in (0, 1)}


def test_refusals_are_no_motor_result_the_archive_is_the_ecu_and_restore_brings_back_the_calibration(
        records_db, files, tmp_path):  # noqa: F811
    db = str(records_db)
    wrong = tmp_path / "wrong.hex"
    wrong.write_text("00" * 16)
    runner = CliRunner()
    with loopback_station(SERIAL, 1, tmp_path / "sim", spec_for=lambda req: paper(SERIAL)) as st:
        bus = ["-i", "remote", "-c", st.can_channel]
        key = ["--key-file", str(files["key"])]
        # three refusals: nothing is written to the ECU
        assert _run(files, st, "W-0007", db, tmp_path)[0] == 2  # the label mis-scanned
        assert _run(files, st, SERIAL, db, tmp_path, dyno=f"127.0.0.1:{_closed_port()}")[0] == 2  # dyno address typo
        assert _run(files, st, SERIAL, db, tmp_path, "--key-file", str(wrong))[0] == 2  # the wrong key file
        assert select_active(NorFlash(st.flash_file))[1] is None  # the ECU is as blank as it came
        code, first = _run(files, st, SERIAL, db, tmp_path)
        assert code == 0, (first["verdict"], first["reasons"], first["error"])

        # the archive is the truth: each block as flashed is the bank's bytes, block show says what ecu info says
        blocks = {b["role"]: b for b in first["blocks"]}
        banks = _banks(st.flash_file, B.BANK_BYTES)
        for b in blocks.values():
            assert Path(b["path"]).read_bytes() == banks[b["bank"]][:b["bytes"]]
        assert blocks["prepare"]["bank"] != blocks["calibrated"]["bank"]
        res = runner.invoke(cli, ["ecu", "info", *bus, "--json"])
        shown = json.loads(runner.invoke(cli, ["block", "show", blocks["calibrated"]["path"], "--json"]).stdout)
        active = json.loads(res.stdout)["active"]
        assert (shown["block"]["sequence"], shown["crc32_stored"]) == (active["sequence"], f"0x{active['crc32']}")

        # lot semantics: one motor, passed on its first measured run; the refusals apart, with their reasons
        stats = json.loads(runner.invoke(cli, ["lot", "stats", "--db", db, "--json"]).stdout)
        assert (stats["runs"], stats["motors"], stats["first_pass_yield"]) == (1, 1, 1.0)
        assert stats["verdicts"] == {"pass": 1, "fail": 0, "error": 0} and stats["pareto"] == []
        assert stats["refusals"]["runs"] == 3 and sorted(p["cause"] for p in stats["refusals"]["pareto"]) == [
            "dyno_unreachable", "key_refused", "wrong_serial"]
        summary = json.loads(runner.invoke(cli, ["records", "--db", db, "--json"]).stdout)["summary"]
        assert (summary["motors"], summary["motors_pass"], summary["kinds"]["refusal"]) == (1, 1, 3)

        # a refit of the passing run changes nothing
        from eol_cal.lot.refit import refit_capture

        row = refit_capture([first["captures"]["before"]["path"]], str(files["limits"]))
        rows = tmp_path / "refit.jsonl"
        rows.write_text(json.dumps(row) + "\n")
        diff = json.loads(runner.invoke(cli, ["lot", "diff", "--db", db, str(rows), "--json"]).stdout)
        assert (diff["compared"], diff["changes"]) == (1, [])

        # a re-test: the other bank now holds its prepare block, not the first calibration
        code, second = _run(files, st, SERIAL, db, tmp_path)
        assert code == 0 and second["blocks"][0]["sequence"] == 3 and second["blocks"][1]["sequence"] == 4
        res = runner.invoke(cli, ["ecu", "restore", "--bank", "previous", *bus, *key, "--db", db,
                                  "--save", str(tmp_path / "bank.bin")])
        assert res.exit_code == 2 and "holds no compensation" in res.output, res.output
        assert f"prepare block of run {second['run_id']}" in res.output and "--calibration previous" in res.output
        assert select_active(NorFlash(st.flash_file))[0].sequence == 4  # nothing was written

        # the calibration before the re-test, found through the records, flashed as sequence 5
        res = runner.invoke(cli, ["ecu", "restore", "--serial", SERIAL, "--calibration", "previous", "--db", db, *bus,
                                  *key, "--report-dir", str(tmp_path / "reports"), "--json"])
        assert res.exit_code == 0, res.output
        doc = json.loads(res.stdout)
        earlier = Path(blocks["calibrated"]["path"]).read_bytes()
        now = select_active(NorFlash(st.flash_file))[1]
        assert _zeroed(now) == _zeroed(earlier) and B.unpack(now, "ECU").sequence == 5 == doc["sequence"]
        # the CRC covers the sequence: the earlier calibration's block with the new sequence is the ECU's, CRC and all
        import dataclasses

        resequenced = B.pack(dataclasses.replace(B.unpack(earlier, "archive"), sequence=5))
        assert now == resequenced and f"{B.check(now).crc_stored:08x}" == doc["crc32"]
        rec = doc["record"]
        assert rec["kind"] == "restore" and rec["restored_from"]["run_id"] == first["run_id"]
        assert Path(rec["blocks"][0]["path"]).read_bytes() == now and rec["ecu_active"]["block"] == "restored"

    # the records: one motor, first pass 1.0, latest status pass; the restore kept as such
    records = query_records(records_db)
    assert [r.kind for r in records] == ["refusal"] * 3 + ["production"] * 2 + ["restore"]
    stats = json.loads(runner.invoke(cli, ["lot", "stats", "--db", db, "--json"]).stdout)
    assert (stats["runs"], stats["motors"], stats["first_pass_yield"]) == (2, 1, 1.0)
