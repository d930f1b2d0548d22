"""The dyno's Modbus register map, defined once for the client, the simulator and the docs.

One flat space of 16-bit registers (PDU addresses, 0-based) is served to both "read holding
registers" (FC 3) and "read input registers" (FC 4); writes use FC 6 / FC 16. Entries marked
read-only refuse writes with Modbus exception 2 (illegal data address).

Encoding: every register is big-endian on the wire (Modbus). 32-bit values (``u32``, ``f32``)
take two registers with the HIGH word at the LOWER address ("ABCD", pymodbus'
``word_order="big"``); ``f32`` is IEEE-754 binary32; ``str`` is ASCII, two characters per
register (first character in the high byte), NUL-padded.

Capture data are moved through a paged window: the client writes the channel selector
``buf_channel`` and the first sample of the page ``buf_offset`` (one FC 16 write), then reads the
page at ``WINDOW_ADDR`` ... ``WINDOW_ADDR + WINDOW_REGS - 1`` in blocks of at most
``MAX_READ_REGS`` registers (the Modbus PDU limit). Analog channels carry one ``f32`` per sample
(two registers, same word order as above, ``WINDOW_REGS // 2`` samples per page); the packed
digital channel carries one ``u16`` per sample (``enc_a`` bit 0, ``enc_b`` bit 1, ``hall`` bits
2-4; ``WINDOW_REGS`` samples per page). Sample ``k`` of a capture was taken at ``k /
capture_rate`` seconds after the capture started.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping

import numpy as np

MAP_VERSION = 1

#: registers per Modbus read request (FC 3/4 limit: 125 registers = 250 data bytes)
MAX_READ_REGS = 125
#: registers per Modbus write request (FC 16 limit: 123 registers)
MAX_WRITE_REGS = 123
#: |speed| at or below this counts as standstill (rpm): direction changes are allowed there
STANDSTILL_RPM = 1.0
#: the capture window
WINDOW_ADDR = 0x8000
WINDOW_REGS = 0x8000

#: registers each value type occupies
TYPE_REGS: Mapping[str, int] = MappingProxyType({"u16": 1, "i16": 1, "u32": 2, "f32": 2})


@dataclass(frozen=True)
class Register:
    """One entry of the register map.

    Attributes
    ----------
    name : str
        Identifier used by client and simulator.
    address : int
        First register (0-based PDU address).
    type : str
        ``u16``, ``i16``, ``u32``, ``f32``, ``str`` (ASCII, ``count`` registers) or ``words``
        (``count`` raw registers, the capture window).
    unit : str
        Physical unit of the decoded value (``""`` for codes, counts and bit fields).
    access : str
        ``rw`` (control, written by the client) or ``r`` (status, written by the dyno only).
    meaning : str
        What the value means; codes and bits are listed here.
    count : int
        Registers occupied (derived from ``type``; given for ``str``).
    group : str
        Section of the map (``identification``, ``control``, ``status``, ``transfer``, ``sim``).
    """

    name: str
    address: int
    type: str
    unit: str
    access: str
    meaning: str
    group: str
    count: int = 0

    def __post_init__(self) -> None:
        if self.type in TYPE_REGS:
            object.__setattr__(self, "count", TYPE_REGS[self.type])
        if self.count < 1:
            raise ValueError(f"register {self.name}: count must be >= 1")

    @property
    def writable(self) -> bool:
        return self.access == "rw"


class Mode(enum.IntEnum):
    """``mode``: what the dyno regulates."""

    OFF = 0
    SPEED = 1  # dyno holds the speed set point; the DUT is loaded by ``dut_cmd``


class DutCmdKind(enum.IntEnum):
    """``dut_cmd_kind``: how ``dut_cmd`` is meant."""

    TORQUE = 0  # N*m shaft torque the DUT's ECU is asked to produce
    IQ = 1  # A, nominal q current i_qo commanded to the DUT's ECU


class DriveState(enum.IntEnum):
    DISABLED = 0
    RAMPING = 1
    AT_SPEED = 2
    STOPPING = 3
    TRIPPED = 4


class CaptureState(enum.IntEnum):
    IDLE = 0
    ARMED = 1
    RUNNING = 2
    READY = 3
    ERROR = 4


class Fault(enum.IntFlag):
    """``faults`` bits (latched until ``fault_reset``)."""

    OVER_SPEED = 1 << 0
    TORQUE_SENSOR = 1 << 1
    COMM_WATCHDOG = 1 << 2
    CAPTURE = 1 << 3
    INTERLOCK = 1 << 4
    DRIVE = 1 << 5


class Interlock(enum.IntFlag):
    """``interlocks`` bits; 1 = condition met. The drive enables only with all of ``ALL``."""

    GUARD_CLOSED = 1 << 0
    ESTOP_RELEASED = 1 << 1
    DUT_CLAMPED = 1 << 2
    COUPLING_OK = 1 << 3
    ALL = GUARD_CLOSED | ESTOP_RELEASED | DUT_CLAMPED | COUPLING_OK


class SimFault(enum.IntEnum):
    """``sim_fault`` codes (simulator only): faults injected on demand."""

    NONE = 0
    DISCONNECT = 1  # drop every connection and refuse requests for ``sim_fault_arg`` ms
    OVER_SPEED = 2  # over-speed trip: drive trips, capture aborts
    TORQUE_SENSOR = 3  # torque transducer fault: capture aborts with bad data flagged


#: capture channels: id -> (canonical channel name, value type in the window)
ANALOG_CHANNELS: Mapping[int, str] = MappingProxyType(
    {
        1: "torque",
        2: "iq_ref",
        3: "speed",
        4: "temp",
        5: "iqc",
        6: "iq",
        7: "id",
        8: "ia",
        9: "ib",
        10: "ic",
    }
)
#: the packed digital channel (enc_a bit 0, enc_b bit 1, hall bits 2..4)
DIGITAL_CHANNEL_ID = 16
#: bit in ``capture_channels`` for a channel id
def channel_bit(channel_id: int) -> int:
    return 1 << (channel_id - 1)


REGISTERS: tuple[Register, ...] = (
    # identification
    Register("map_version", 0, "u16", "", "r", f"register map version ({MAP_VERSION})", "identification"),
    Register("dut_serial", 1, "str", "", "r", "serial of the motor on the dyno (16 ASCII characters, NUL-padded)", "identification", count=8),
    Register("dut_poles", 9, "u16", "", "r", "poles P of the motor on the dyno", "identification"),
    Register("dut_encoder_ppr", 10, "u16", "", "r", "encoder pulses per mechanical revolution (channel A)", "identification"),
    Register("dut_kt", 11, "f32", "N*m/A", "r", "torque constant of the motor on the dyno", "identification"),
    Register("max_speed", 13, "f32", "rpm", "r", "over-speed trip threshold", "identification"),
    Register("tick_hz", 15, "u32", "Hz", "r", "internal sample clock; capture_rate must divide it", "identification"),
    # control
    Register("mode", 100, "u16", "", "rw", "0 off, 1 speed control (the dyno holds the speed set point, the DUT is loaded by dut_cmd); other values refused", "control"),
    Register("enable", 101, "u16", "", "rw", "1 enable the drive (refused unless all interlocks are met and no fault is latched), 0 disable", "control"),
    Register("stop", 102, "u16", "", "rw", "write 1: ramp to zero speed, then disable; reads back 0", "control"),
    Register("direction", 103, "u16", "", "rw", "0 forward (positive speed), 1 reverse; changes refused above 1 rpm (STANDSTILL_RPM) while enabled", "control"),
    Register("speed_setpoint", 104, "f32", "rpm", "rw", "speed set point magnitude (>= 0); the sign comes from direction", "control"),
    Register("ramp", 106, "f32", "rpm/s", "rw", "speed ramp rate (> 0)", "control"),
    Register("dut_cmd_kind", 108, "u16", "", "rw", "0: dut_cmd is a shaft torque (N*m), 1: dut_cmd is the nominal q current i_qo (A)", "control"),
    Register("dut_cmd", 109, "f32", "N*m or A", "rw", "load command passed to the DUT's ECU (unit per dut_cmd_kind)", "control"),
    Register("capture_rate", 111, "u32", "Hz", "rw", "capture sample rate; must divide tick_hz", "control"),
    Register("capture_length", 113, "u32", "samples", "rw", "samples to capture (1 ... 4 000 000)", "control"),
    Register("capture_start", 115, "u16", "", "rw", "write 1: arm the capture (it runs once the speed is within tolerance); write 2: abort; reads back 0", "control"),
    Register("fault_reset", 116, "u16", "", "rw", "write 1: clear latched faults (drive stays disabled); reads back 0", "control"),
    Register("watchdog_ms", 117, "u16", "ms", "rw", "communication watchdog: with no request for this long while enabled the dyno stops and latches COMM_WATCHDOG (0 = off)", "control"),
    # status
    Register("speed", 200, "f32", "rpm", "r", "actual shaft speed (signed)", "status"),
    Register("torque", 202, "f32", "N*m", "r", "actual shaft torque (positive when the DUT drives the dyno)", "status"),
    Register("temperature", 204, "f32", "degC", "r", "DUT winding temperature", "status"),
    Register("faults", 206, "u16", "", "r", "latched fault bits: 0 over-speed, 1 torque sensor, 2 comm watchdog, 3 capture, 4 interlock, 5 drive", "status"),
    Register("interlocks", 207, "u16", "", "r", "interlock bits, 1 = met: 0 guard closed, 1 e-stop released, 2 DUT clamped, 3 coupling ok", "status"),
    Register("drive_state", 208, "u16", "", "r", "0 disabled, 1 ramping, 2 at speed, 3 stopping, 4 tripped", "status"),
    Register("capture_state", 209, "u16", "", "r", "0 idle, 1 armed, 2 running, 3 ready, 4 error", "status"),
    Register("capture_count", 210, "u32", "samples", "r", "samples in the capture buffer (valid when capture_state is ready)", "status"),
    Register("capture_channels", 212, "u16", "", "r", "channels in the buffer: bit (id-1) for channel id (see the channel table)", "status"),
    Register("heartbeat", 213, "u16", "", "r", "counts up every 10 ms while the dyno controller runs (wraps)", "status"),
    Register("capture_seq", 214, "u16", "", "r", "number of captures completed since power-up (wraps); changes when a new buffer is ready", "status"),
    # capture data transfer
    Register("buf_channel", 300, "u16", "", "rw", "channel id of the window page (see the channel table)", "transfer"),
    Register("buf_offset", 301, "u32", "samples", "rw", "sample index of the first sample in the window page", "transfer"),
    Register("window", WINDOW_ADDR, "words", "", "r", f"capture window page: {WINDOW_REGS} registers, f32 per sample (analog) or u16 per sample (digital); read in blocks of <= {MAX_READ_REGS}", "transfer", count=WINDOW_REGS),
    # simulator only
    Register("sim_fault", 400, "u16", "", "rw", "simulator only: write a fault to inject: 1 disconnect, 2 over-speed trip, 3 torque-sensor fault", "sim"),
    Register("sim_fault_arg", 401, "u16", "ms", "rw", "simulator only: disconnect duration for sim_fault 1", "sim"),
)

BY_NAME: Mapping[str, Register] = MappingProxyType({r.name: r for r in REGISTERS})


def _check_map() -> None:
    # Overlaps would silently alias two values; fail at import instead.
    spans = sorted((r.address, r.address + r.count, r.name) for r in REGISTERS)
    for (a0, a1, n0), (b0, _b1, n1) in zip(spans, spans[1:]):
        if b0 < a1:
            raise AssertionError(f"register map: {n0} overlaps {n1}")


_check_map()


def encode(name: str, value: float | int | str) -> list[int]:
    """Register words for one value of register ``name`` (see the module doc for the encoding)."""
    reg = BY_NAME[name]
    if reg.type == "u16":
        v = int(value)
        if not 0 <= v <= 0xFFFF:
            raise ValueError(f"{name}: {value} out of u16 range")
        return [v]
    if reg.type == "i16":
        v = int(value)
        if not -0x8000 <= v <= 0x7FFF:
            raise ValueError(f"{name}: {value} out of i16 range")
        return [v & 0xFFFF]
    if reg.type == "u32":
        v = int(value)
        if not 0 <= v <= 0xFFFFFFFF:
            raise ValueError(f"{name}: {value} out of u32 range")
        return [v >> 16, v & 0xFFFF]
    if reg.type == "f32":
        w = np.asarray([value], dtype=">f4").view(">u2")
        return [int(w[0]), int(w[1])]
    raw = str(value).encode("ascii")[: 2 * reg.count].ljust(2 * reg.count, b"\0")
    return [int(x) for x in np.frombuffer(raw, dtype=">u2")]


def decode(name: str, words: list[int]) -> float | int | str:
    """Value of register ``name`` from its register words."""
    reg = BY_NAME[name]
    if len(words) != reg.count:
        raise ValueError(f"{name}: expected {reg.count} registers, got {len(words)}")
    if reg.type == "u16":
        return int(words[0])
    if reg.type == "i16":
        return int(words[0]) - 0x10000 if words[0] & 0x8000 else int(words[0])
    if reg.type == "u32":
        return (int(words[0]) << 16) | int(words[1])
    if reg.type == "f32":
        return float(np.asarray(words, dtype=">u2").view(">f4")[0])
    return np.asarray(words, dtype=">u2").tobytes().rstrip(b"\0").decode("ascii", "replace")


def span(first: str, last: str) -> tuple[int, int]:
    """(address, count) covering registers ``first`` ... ``last`` inclusive, for one block read."""
    a = BY_NAME[first].address
    b = BY_NAME[last]
    return a, b.address + b.count - a


def unpack_block(address: int, words: list[int], names: tuple[str, ...]) -> dict[str, float | int | str]:
    """Decode several registers out of one block read that started at ``address``."""
    out = {}
    for n in names:
        r = BY_NAME[n]
        i = r.address - address
        out[n] = decode(n, list(words[i : i + r.count]))
    return out


def f32_to_words(values: np.ndarray) -> np.ndarray:
    """Samples (float) -> register words (uint16, two per sample, high word first)."""
    return np.ascontiguousarray(np.asarray(values, dtype=">f4")).view(">u2").astype(np.uint16)


def words_to_f32(words: np.ndarray) -> np.ndarray:
    """Register words (two per sample, high word first) -> samples (float64)."""
    return np.asarray(words, dtype=">u2").view(">f4").astype(np.float64)


def pack_digital(enc_a: np.ndarray, enc_b: np.ndarray | None, hall: np.ndarray) -> np.ndarray:
    """Digital levels -> one u16 word per sample (enc_a bit 0, enc_b bit 1, hall bits 2..4)."""
    w = np.asarray(enc_a, dtype=np.uint16) & 1
    if enc_b is not None:
        w = w | ((np.asarray(enc_b, dtype=np.uint16) & 1) << 1)
    return (w | ((np.asarray(hall, dtype=np.uint16) & 7) << 2)).astype(np.uint16)


def unpack_digital(words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One u16 word per sample -> (enc_a, enc_b, hall) integer levels."""
    w = np.asarray(words, dtype=np.int64)
    return w & 1, (w >> 1) & 1, (w >> 2) & 7


def markdown_table() -> str:
    """The register map as Markdown tables, one per group (``docs/dyno.md`` embeds this text)."""
    titles = {
        "identification": "Identification (read-only)",
        "control": "Control (read/write)",
        "status": "Status (read-only)",
        "transfer": "Capture data transfer",
        "sim": "Simulator only (fault injection)",
    }
    lines: list[str] = []
    for group, title in titles.items():
        lines += [f"### {title}", "", "| address | name | type | regs | unit | access | meaning |", "|---|---|---|---|---|---|---|"]
        for r in REGISTERS:
            if r.group == group:
                addr = f"{r.address}" if r.count == 1 else f"{r.address}-{r.address + r.count - 1}"
                lines.append(f"| {addr} | `{r.name}` | {r.type} | {r.count} | {r.unit} | {r.access} | {r.meaning} |")
        lines.append("")
    lines += ["### Capture channels (`buf_channel`)", "", "| id | channel | window type | unit |", "|---|---|---|---|"]
    from eol_cal.capture.model import CANONICAL_CHANNELS

    for cid, name in ANALOG_CHANNELS.items():
        lines.append(f"| {cid} | `{name}` | f32 | {CANONICAL_CHANNELS[name]} |")
    lines.append(f"| {DIGITAL_CHANNEL_ID} | `enc_a` bit 0, `enc_b` bit 1, `hall` bits 2-4 | u16 | 1 |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown_table(), end="")
