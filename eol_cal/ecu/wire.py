"""A classic CAN data frame as it goes on the wire (ISO 11898-1): its CRC-15, its stuff bits and its
length in bits (:func:`wire_bits`), and the ECU simulator's bus paced by it to a bit rate
(:class:`PacedBus`).

A frame's length depends on its content: after five equal bits the transmitter inserts one of the
other level (bit stuffing, from the start of frame through the CRC sequence). The worst case,
:func:`frame_bits`, is 24 stuff bits for an 8-byte frame; random data has
about 5.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time

import can

from eol_cal.ecu import protocol as P

log = logging.getLogger(__name__)

#: CAN's CRC-15 generator, x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1 (CRC-15/CAN)
CRC15_POLY = 0x4599
#: bits after the CRC sequence, never stuffed: CRC delimiter, ACK slot and delimiter, end of frame
#: (7) and the interframe space (3)
TAIL_BITS = 13


@functools.cache
def _crc_table() -> tuple[int, ...]:
    """The register after eight zero bits from ``x << 7`` (a byte's step of :func:`crc15`)."""
    out = []
    for x in range(256):
        c = x << 7
        for _ in range(8):
            c = ((c << 1) ^ CRC15_POLY if c & 0x4000 else c << 1) & 0x7FFF
        out.append(c)
    return tuple(out)


def crc15(value: int, length: int) -> int:
    """The CRC-15 of the ``length`` bits of ``value`` (most significant first), register starting
    at 0: the bits before the last whole bytes one at a time, then a byte a step."""
    crc, table = 0, _crc_table()
    head = length % 8
    for i in range(length - 1, length - 1 - head, -1):
        top = ((crc >> 14) ^ (value >> i)) & 1
        crc = (crc << 1) & 0x7FFF
        if top:
            crc ^= CRC15_POLY
    for i in range(length - head - 8, -8, -8):
        crc = ((crc << 8) & 0x7FFF) ^ table[((crc >> 7) ^ (value >> i)) & 0xFF]
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


@functools.cache
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


def stuff_count(value: int, length: int) -> int:
    """Stuff bits a transmitter inserts into these ``length`` bits (most significant first): one of
    the other level after every five equal bits, the stuff bit counting towards the next five."""
    state, count, table = (-1, 0), 0, _stuff_table()
    head = length % 8
    for i in range(length - 1, length - 1 - head, -1):
        state, k = _stuff_step(state, (value >> i) & 1)
        count += k
    for i in range(length - head - 8, -8, -8):
        state, k = table[state][(value >> i) & 0xFF]
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


def frame_bits(dlc: int = P.FRAME_BYTES, *, stuffing: bool = True) -> int:
    """Bits on the wire for one classic CAN 2.0A data frame, interframe space included, at most
    (the bound a flash's bus time is estimated with; a frame's own length is
    :func:`wire_bits`).

    The ``34 + 8*dlc`` stuffable bits (SOF, 11-bit ID, RTR, IDE, r0, DLC, data, CRC) and the
    :data:`TAIL_BITS`; with ``stuffing`` the worst-case stuff bits ``(34 + 8*dlc - 1) // 4``
    (Davis et al., 2007), which makes 135 bits for an 8-byte frame.
    """
    stuffable = 34 + 8 * dlc
    bits = stuffable + TAIL_BITS
    if stuffing:
        bits += (stuffable - 1) // 4
    return bits


def isotp_min_frames(payload_bytes: int) -> int:
    """Fewest CAN frames that carry one ISO-TP message of ``payload_bytes`` (classic CAN, normal addressing).

    7 bytes fit a single frame; otherwise a first frame carries 6 and each consecutive frame 7,
    plus the receiver's one flow-control frame (BS = 0).
    """
    if payload_bytes <= 7:
        return 1
    return 1 + -(-(payload_bytes - 6) // 7) + 1


class PacedBus(can.BusABC):
    """A bus wrapper that gives every frame, sent or received, its time on a CAN bus of
    ``bitrate`` (the ECU simulator's bus: a virtual bus carries frames as fast as the CPU allows).

    Both directions share one medium: a frame occupies the bus for its own length in bits
    (:func:`wire_bits`: the stuff bits of its content, not the worst case of
    :func:`frame_bits`) / ``bitrate`` seconds after the previous one, sent or received, has left it. A sent
    frame goes into a transmit queue, as into a CAN controller's, and reaches the other side when
    its time on the bus is over (frames sent back to back follow each other at the bit rate, the
    sender's own sleeps not adding up); a received frame is handed on when its time is over.

    Parameters
    ----------
    inner : can.BusABC
        The real (virtual) bus.
    bitrate : int
        bit/s (the contract's bus: 500000).
    """

    def __init__(self, inner: can.BusABC, bitrate: int) -> None:
        if bitrate <= 0:
            raise ValueError(f"bit rate {bitrate} must be positive")
        self.inner = inner
        self.bitrate = int(bitrate)
        self._lock = threading.Lock()
        self._free_at = 0.0
        self.busy_s = 0.0
        """Seconds the frames have occupied the bus so far."""
        self._tx: queue.SimpleQueue[tuple[float, can.Message] | None] = queue.SimpleQueue()
        self._tx_thread = threading.Thread(target=self._transmit, name="paced-bus-tx", daemon=True)
        self._tx_thread.start()
        super().__init__(channel=getattr(inner, "channel_info", "paced"))
        self.channel_info = f"paced {self.bitrate} bit/s ({getattr(inner, 'channel_info', '')})"

    def _slot(self, msg: can.Message, ready: float) -> float:
        """When ``msg``, ready to go at ``ready`` (monotonic s), has left the bus."""
        seconds = (frame_bits(msg.dlc) if msg.is_fd  # not modelled: CAN FD's data phase has a bit rate of its own
                   else wire_bits(msg.arbitration_id, bytes(msg.data), msg.is_extended_id, msg.is_remote_frame,
                                  msg.dlc)) / self.bitrate
        with self._lock:
            done = max(ready, self._free_at) + seconds
            self._free_at = done
            self.busy_s += seconds
        return done

    @staticmethod
    def _sleep_until(t: float) -> None:
        wait = t - time.monotonic()
        if wait > 0:
            time.sleep(wait)

    def _transmit(self) -> None:
        while True:
            item = self._tx.get()
            if item is None:
                return
            done, msg = item
            self._sleep_until(done)
            try:
                self.inner.send(msg)
            except Exception as exc:  # noqa: BLE001 - a closed bus: the frame is lost, as on a dead link
                log.debug("paced bus: frame not sent: %s", exc)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._tx.put((self._slot(msg, time.monotonic()), msg))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        if msg is not None:
            # on the bus from when the sender handed it over, not from when this thread got to it
            age = time.time() - msg.timestamp if msg.timestamp else 0.0
            now = time.monotonic()
            self._sleep_until(self._slot(msg, now - age if 0.0 <= age < 1.0 else now))
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self._tx.put(None)
        self._tx_thread.join(1.0)
        self.inner.shutdown()
