"""A classic CAN data frame as it goes on the wire (ISO 11898-1): its CRC-15, its stuff bits and its
length in bits, for the simulated bus's pacing (:class:`eol_cal.ecu.transport.PacedBus`).

A frame's length depends on its content: after five equal bits the transmitter inserts one of the
other level (bit stuffing, from the start of frame through the CRC sequence). The worst case,
:func:`eol_cal.ecu.transport.frame_bits`, is 24 stuff bits for an 8-byte frame; random data has
about 5.
"""

from __future__ import annotations

import functools

#: CAN's CRC-15 generator, x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1 (CRC-15/CAN)
CRC15_POLY = 0x4599
#: bits after the CRC sequence, never stuffed: CRC delimiter, ACK slot and delimiter, end of frame
#: (7) and the interframe space (3)
TAIL_BITS = 13


def _crc_table() -> tuple[int, ...]:
    """The register after eight zero bits from ``x << 7`` (a byte's step of :func:`crc15`)."""
    out = []
    for x in range(256):
        c = x << 7
        for _ in range(8):
            c = ((c << 1) ^ CRC15_POLY if c & 0x4000 else c << 1) & 0x7FFF
        out.append(c)
    return tuple(out)


_CRC_TABLE = _crc_table()


def crc15(value: int, length: int) -> int:
    """The CRC-15 of the ``length`` bits of ``value`` (most significant first), register starting
    at 0: the bits before the last whole bytes one at a time, then a byte a step."""
    crc = 0
    head = length % 8
    for i in range(length - 1, length - 1 - head, -1):
        top = ((crc >> 14) ^ (value >> i)) & 1
        crc = (crc << 1) & 0x7FFF
        if top:
            crc ^= CRC15_POLY
    for i in range(length - head - 8, -8, -8):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC_TABLE[((crc >> 7) ^ (value >> i)) & 0xFF]
    return crc


def frame_bitstream(arbitration_id: int, data: bytes, *, extended: bool = False, remote: bool = False,
                    dlc: int | None = None) -> tuple[int, int]:
    """The stuffable bits of a classic data (or remote) frame, start of frame through the CRC
    sequence: ``(bits as an integer, most significant first; how many)``. ``dlc``: the frame's data
    length code (default ``len(data)``); a remote frame carries no data field."""
    dlc = len(data) if dlc is None else dlc
    if extended:  # SOF, base ID, SRR (recessive), IDE (recessive), ID extension, RTR, r1, r0
        fields = [(0, 1), (arbitration_id >> 18, 11), (1, 1), (1, 1), (arbitration_id & 0x3FFFF, 18),
                  (int(remote), 1), (0, 2)]
    else:  # SOF, ID, RTR, IDE (dominant), r0
        fields = [(0, 1), (arbitration_id, 11), (int(remote), 1), (0, 2)]
    fields.append((dlc, 4))
    if not remote:
        fields.append((int.from_bytes(bytes(data), "big"), 8 * len(data)))
    value = length = 0
    for v, n in fields:
        value, length = (value << n) | (v & ((1 << n) - 1)), length + n
    return (value << 15) | crc15(value, length), length + 15


def _stuff_step(state: tuple[int, int], b: int) -> tuple[tuple[int, int], int]:
    """One bit through the transmitter's stuffing: ``((last level, equal bits in a row), stuff
    bits inserted)``; five equal bits insert one of the other level, which counts towards the next five."""
    last, run = state
    run = run + 1 if b == last else 1
    if run == 5:
        return (1 - b, 1), 1
    return (b, run), 0


def _stuff_table() -> dict[tuple[int, int], tuple[tuple[tuple[int, int], int], ...]]:
    """Per stuffing state, per byte: the state after its eight bits and the stuff bits inserted."""
    states = [(-1, 0)] + [(b, run) for b in (0, 1) for run in range(1, 5)]
    table = {}
    for state in states:
        row = []
        for x in range(256):
            s, n = state, 0
            for i in range(7, -1, -1):
                s, k = _stuff_step(s, (x >> i) & 1)
                n += k
            row.append((s, n))
        table[state] = tuple(row)
    return table


_STUFF_TABLE = _stuff_table()


def stuff_count(value: int, length: int) -> int:
    """Stuff bits a transmitter inserts into these ``length`` bits (most significant first): one of
    the other level after every five equal bits, the stuff bit counting towards the next five."""
    state, count = (-1, 0), 0
    head = length % 8
    for i in range(length - 1, length - 1 - head, -1):
        state, k = _stuff_step(state, (value >> i) & 1)
        count += k
    for i in range(length - head - 8, -8, -8):
        state, k = _STUFF_TABLE[state][(value >> i) & 0xFF]
        count += k
    return count


@functools.lru_cache(maxsize=4096)
def wire_bits(arbitration_id: int, data: bytes, extended: bool = False, remote: bool = False,
              dlc: int | None = None) -> int:
    """Bits a classic CAN frame occupies the bus for: its own stuff bits, the tail and the
    interframe space included (111 to 135 for a standard 8-byte data frame). Kept for frames sent
    again (flow control, padding, a block flashed twice)."""
    value, length = frame_bitstream(arbitration_id, data, extended=extended, remote=remote, dlc=dlc)
    return length + stuff_count(value, length) + TAIL_BITS
