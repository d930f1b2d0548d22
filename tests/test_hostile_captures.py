"""Untrusted capture files (issue 16): hostile MDF4 structure, corrupt compressed data, 0 or 1
samples, non-physical values, a FIFO, a 100 000-column header, an offset unit on speed. Each
ends in one line naming the file (and the block, for MDF4) with exit 2, and one bad file never
costs the others' results."""

from __future__ import annotations

import dataclasses
import os
import struct
import time

import numpy as np
import pytest
from click.testing import CliRunner

from _capture_helpers import small_capture, with_channel
from cli.main import cli
from eol_cal.capture.io import read_capture, write_capture
from eol_cal.capture.mdf4_check import MAX_DZ_RATIO, check_mdf4_file
from eol_cal.errors import InputError
from eol_cal.sim.fuzz import mdf4_blocks, run_cli


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    mf4, csv = d / "good.mf4", d / "good.csv"
    write_capture(small_capture(), mf4)
    write_capture(small_capture(), csv)
    return mf4, csv


def _patched(src, dst, at: int, value: int, fmt: str = "<Q"):
    buf = bytearray(src.read_bytes())
    struct.pack_into(fmt, buf, at, value)
    dst.write_bytes(bytes(buf))
    return dst


def _block(data: bytes, kind: bytes) -> tuple[int, tuple]:
    blocks = mdf4_blocks(data)
    offset = next(o for o, b in sorted(blocks.items()) if b[0] == kind)
    return offset, blocks[offset]


def _refused(path, *words):
    res = CliRunner().invoke(cli, ["analyze", str(path)])
    assert res.exit_code == 2, res.output
    line = res.stderr.strip()
    assert "Traceback" not in res.output and len(line.splitlines()) == 1, line
    assert str(path) in line, line
    for w in words:
        assert w in line, line
    return line


@pytest.mark.parametrize("claim", [2**62, 2**31])
def test_dz_claiming_a_huge_original_length_is_refused_before_decoding(good, tmp_path, claim):
    """2^62 killed the process (SIGSEGV), 2^31 took 2 GB and 20 s: now refused by the ratio bound."""
    data = good[0].read_bytes()
    dz, (_, _, links) = _block(data, b"##DZ")
    bad = _patched(good[0], tmp_path / "dz.mf4", dz + 24 + 8 * len(links) + 8, claim)
    # in a child: if the check ever let this through, the test run itself must not die
    rc, _, err, seconds, _ = run_cli(["analyze", bad.name], tmp_path, timeout_s=30)
    assert rc == 2, err
    assert "Traceback" not in err and str(bad.name) in err and f"block ##DZ at 0x{dz:x}" in err, err
    assert f"more than {MAX_DZ_RATIO} times" in err


def test_link_back_to_its_own_block_is_refused_not_looped(good, tmp_path):
    data = good[0].read_bytes()
    cn, _ = _block(data, b"##CN")
    bad = _patched(good[0], tmp_path / "loop.mf4", cn + 24, cn)  # the channel's "next" is itself
    t0 = time.process_time()  # CPU seconds: a loop spins them however busy the machine is, a wait does not
    line = _refused(bad, f"block ##CN at 0x{cn:x}, link 0", "its own block")
    assert time.process_time() - t0 < 20, line


def test_cycle_through_another_block_and_a_link_outside_the_file(good, tmp_path):
    data = good[0].read_bytes()
    dg, (_, _, dg_links) = _block(data, b"##DG")
    cg = dg_links[1]
    bad = _patched(good[0], tmp_path / "cycle.mf4", cg + 24, dg)  # the CG's "next CG" -> its DG
    _refused(bad, "link 0")
    bad = _patched(good[0], tmp_path / "outside.mf4", dg + 24 + 8, len(data) + 64)
    _refused(bad, f"block ##DG at 0x{dg:x}, link 1", "not a block inside the file")


def test_every_single_bit_flip_in_compressed_data_is_refused_naming_the_block(good, tmp_path):
    data = good[0].read_bytes()
    dz, (_, length, links) = _block(data, b"##DZ")
    start = dz + 24 + 8 * len(links) + 24
    rng = np.random.default_rng(16)
    refused = 0
    for k, pos in enumerate(rng.integers(start, dz + length, 12)):
        buf = bytearray(data)
        buf[int(pos)] ^= 1 << int(rng.integers(0, 8))
        path = tmp_path / f"flip{k}.mf4"
        path.write_bytes(bytes(buf))
        with pytest.raises(InputError) as info:
            read_capture(path)
        assert info.value.file == str(path) and info.value.field == f"block ##DZ at 0x{dz:x}", info.value
        refused += 1
    assert refused == 12


def test_the_inflated_blocks_are_zlibs_and_a_flip_in_the_checksum_is_refused(good, tmp_path):
    """The checker inflates with ISA-L (isal, faster than zlib): the same bytes as zlib's, and the
    stream's adler-32 trailer still checked (a flip in it leaves the data intact: only the
    checksum can catch it)."""
    import zlib

    from eol_cal.capture.mdf4_check import check_mdf4_bytes

    data = good[0].read_bytes()
    dz, (_, length, links) = _block(data, b"##DZ")
    at = dz + 24 + 8 * len(links)
    original, compressed = struct.unpack_from("<QQ", data, at + 8)
    assert check_mdf4_bytes(data).inflated[dz] == zlib.decompress(data[at + 24:at + 24 + compressed])
    buf = bytearray(data)
    buf[at + 24 + compressed - 1] ^= 0x01  # the adler-32's last byte
    path = tmp_path / "adler.mf4"
    path.write_bytes(bytes(buf))
    with pytest.raises(InputError) as info:
        read_capture(path)
    assert info.value.field == f"block ##DZ at 0x{dz:x}" and "corrupt" in info.value.reason, info.value


def test_one_bad_file_does_not_cost_the_others_results(good, tmp_path):
    data = good[0].read_bytes()
    dz, (_, _, links) = _block(data, b"##DZ")
    buf = bytearray(data)
    buf[dz + 24 + 8 * len(links) + 24 + 100] ^= 0x10
    bad = tmp_path / "bad.mf4"
    bad.write_bytes(bytes(buf))
    res = CliRunner().invoke(cli, ["analyze", "--json", str(bad), str(good[0])])
    assert res.exit_code == 2
    import json

    doc = json.loads(res.stdout)
    assert [c["file"] for c in doc["captures"]] == [str(good[0])]
    assert [e["file"] for e in doc["errors"]] == [str(bad)] and "block ##DZ" in doc["errors"][0]["field"]


@pytest.mark.parametrize("n", [0, 1])
def test_mdf4_with_0_or_1_samples_is_refused_cleanly(tmp_path, n):
    c = small_capture()
    short = dataclasses.replace(c, t=c.t[:n], channels={k: v[:n] for k, v in c.channels.items()}, events={})
    path = tmp_path / f"n{n}.mf4"
    write_capture(short, path)
    _refused(path, f"{n} samples")


def test_truncated_and_patched_lengths_are_refused(good, tmp_path):
    data = good[0].read_bytes()
    for n in (0, 10, 64, 100, len(data) // 2, len(data) - 1):
        path = tmp_path / f"trunc{n}.mf4"
        path.write_bytes(data[:n])
        _refused(path)
    cn, _ = _block(data, b"##CN")
    _refused(_patched(good[0], tmp_path / "len.mf4", cn + 8, 2**62), f"block ##CN at 0x{cn:x}", "past the end")
    _refused(_patched(good[0], tmp_path / "links.mf4", cn + 16, 2**40), f"block ##CN at 0x{cn:x}", "links")


def test_structure_check_passes_the_tools_own_files(good):
    layout = check_mdf4_file(good[0])
    assert {b.kind for b in layout.blocks.values()} >= {"HD", "DG", "CG", "CN", "DZ"}
    assert layout.decoded_bytes > 0


def test_a_file_over_the_read_whole_size_is_mapped_and_reads_the_same(good, tmp_path, monkeypatch):
    """Files up to READ_WHOLE_BYTES are read whole, larger ones mapped: the same capture, and the
    same refusal of a bad file, either way."""
    from eol_cal.capture import mdf4_check

    bad = _patched(good[0], tmp_path / "len.mf4", _block(good[0].read_bytes(), b"##CN")[0] + 8, 2**62)
    read = read_capture(good[0])
    with pytest.raises(InputError) as whole:
        read_capture(bad)
    monkeypatch.setattr(mdf4_check, "READ_WHOLE_BYTES", 0)
    mapped = read_capture(good[0])
    with pytest.raises(InputError) as by_map:
        read_capture(bad)
    assert str(whole.value) == str(by_map.value)
    assert np.array_equal(read.t, mapped.t) and list(read.channels) == list(mapped.channels)
    assert all(np.array_equal(read[n], mapped[n]) for n in read.channels) and read.metadata == mapped.metadata


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
def test_a_1e308_torque_sample_is_refused_at_validation(tmp_path, suffix):
    c = small_capture()
    torque = np.array(c["torque"])
    torque[100] = 1e308
    path = tmp_path / f"huge{suffix}"
    write_capture(with_channel(c, "torque", torque), path)
    _refused(path, "'torque'", "outside the physical bounds", "sample 100")
    out = tmp_path / "fit.json"
    res = CliRunner().invoke(cli, ["fit", str(path), "-o", str(out)])
    assert res.exit_code == 2 and "outside the physical bounds" in res.stderr and not out.exists()


def test_fifo_named_csv_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    rc, _, err, seconds, _ = run_cli(["analyze", "pipe.csv"], tmp_path, timeout_s=30)
    assert rc == 2 and "pipe.csv" in err and "FIFO" in err and "Traceback" not in err, err


def test_degc_on_speed_is_one_line_naming_file_and_channel(good, tmp_path):
    text = good[1].read_text().replace("speed [rpm]", "speed [degC]")
    path = tmp_path / "degc.csv"
    path.write_text(text)
    _refused(path, "'speed'", "degC")


def test_100000_column_header_is_parsed_in_linear_time(tmp_path):
    """The duplicate-name check was quadratic (over 60 s); the refusal now comes at once."""
    n = 100_000
    path = tmp_path / "wide.csv"
    path.write_text("# serial: W\n" + ",".join(f"c{i}" for i in range(n)) + "\n" + ",".join("0" for _ in range(n)) + "\n")
    t0 = time.process_time()
    _refused(path, "c0")
    assert time.process_time() - t0 < 20  # a hang guard in CPU seconds (not wall: a loaded machine), not a speed claim
    dup = tmp_path / "dup.csv"
    dup.write_text("t,torque," + ",".join(f"c{i}" for i in range(n)) + ",torque\n" + ",".join("0" for _ in range(n + 3)) + "\n")
    _refused(dup, "'torque'", "named twice")
