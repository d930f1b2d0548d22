"""A classic CAN frame's length on the wire (eol_cal/ecu/wire.py): the CRC-15 of ISO 11898-1, the
stuff bits of the frame's own content, the fields in their places. The simulated bus paces each
frame by it (tests/test_ecu_pacing.py)."""

from __future__ import annotations

import random

import pytest

from eol_cal.ecu.wire import crc15, frame_bits, frame_bitstream, stuff_count, wire_bits


def _bits(value: int, length: int) -> list[int]:
    return [(value >> i) & 1 for i in range(length - 1, -1, -1)]


def _stuffed(bits: list[int]) -> list[int]:
    """The transmitter's rule written out bit by bit: after five equal bits, one of the other level."""
    out: list[int] = []
    for b in bits:
        out.append(b)
        if len(out) >= 5 and len(set(out[-5:])) == 1:
            out.append(1 - b)
    return out


def _destuffed(bits: list[int]) -> list[int]:
    out, run, last, skip = [], 0, -1, False
    for b in bits:
        if skip:
            assert b != last, "a stuff bit must be of the other level"
            skip, last, run = False, b, 1
            continue
        out.append(b)
        run = run + 1 if b == last else 1
        last = b
        skip = run == 5
    return out


def test_the_crc_is_crc15_can_by_its_catalogue_check_value():
    # CRC-15/CAN (poly 0x4599, init 0, no reflection, no final xor): check value 0x059E over "123456789"
    assert crc15(int.from_bytes(b"123456789", "big"), 72) == 0x059E
    # odd lengths (the frame is no whole number of bytes): the same as one bit at a time
    rng = random.Random(5)
    for length in range(1, 140):
        value = rng.getrandbits(length)
        crc = 0
        for b in _bits(value, length):
            top = ((crc >> 14) & 1) ^ b
            crc = (crc << 1) & 0x7FFF
            crc ^= 0x4599 if top else 0
        assert crc15(value, length) == crc, length


@pytest.mark.parametrize(("extended", "remote", "dlc", "length"), [
    (False, False, 8, 1 + 11 + 3 + 4 + 64 + 15),
    (False, False, 0, 1 + 11 + 3 + 4 + 15),
    (True, False, 8, 1 + 11 + 2 + 18 + 3 + 4 + 64 + 15),
    (False, True, 8, 1 + 11 + 3 + 4 + 15),  # a remote frame: its DLC, no data field
])
def test_the_fields_are_where_the_standard_puts_them(extended, remote, dlc, length):
    value, n = frame_bitstream(0x7E0 if not extended else 0x18DA10F1, bytes(range(dlc)), extended=extended,
                               remote=remote)
    assert n == length
    bits = _bits(value, n)
    assert bits[0] == 0  # start of frame, dominant
    if not extended:
        assert bits[1:12] == _bits(0x7E0, 11)
        assert bits[12:15] == [int(remote), 0, 0]  # RTR, IDE dominant, r0
        assert bits[15:19] == _bits(dlc, 4)
    else:
        assert bits[1:12] == _bits(0x18DA10F1 >> 18, 11)
        assert bits[12:14] == [1, 1]  # SRR and IDE recessive
        assert bits[14:32] == _bits(0x18DA10F1 & 0x3FFFF, 18)
        assert bits[35:39] == _bits(dlc, 4)
    if not remote:
        assert bits[n - 15 - 8 * dlc:n - 15] == _bits(int.from_bytes(bytes(range(dlc)), "big"), 8 * dlc)
    assert value & 0x7FFF == crc15(value >> 15, n - 15)


def test_the_stuff_bits_are_the_transmitters_and_the_length_within_the_worst_case():
    rng = random.Random(11)
    for _ in range(3000):
        extended = rng.random() < 0.3
        ident = rng.getrandbits(29 if extended else 11)
        # runs of equal bytes as well as random ones: 0x00 and 0xFF stuff the most
        data = bytes(rng.choice((0, 0xFF, 0xCC, rng.getrandbits(8))) for _ in range(rng.randrange(9)))
        value, n = frame_bitstream(ident, data, extended=extended)
        bits = _bits(value, n)
        on_wire = _stuffed(bits)
        assert stuff_count(value, n) == len(on_wire) - n
        assert _destuffed(on_wire) == bits
        assert not any(len(set(on_wire[i:i + 6])) == 1 for i in range(len(on_wire) - 5))
        total = wire_bits(ident, data, extended)
        assert total == len(on_wire) + 13  # CRC delimiter, ACK slot and delimiter, EOF, interframe space
        if not extended:
            assert frame_bits(len(data), stuffing=False) <= total <= frame_bits(len(data))


def test_random_data_is_stuffed_far_less_than_the_worst_case():
    rng = random.Random(3)
    lengths = [wire_bits(0x7E8, rng.randbytes(8)) for _ in range(2000)]
    assert max(lengths) < frame_bits(8) == 135
    assert 113 < sum(lengths) / len(lengths) < 120  # about 5 stuff bits a frame, against 24 at worst
