"""What the client and the simulator say to a dyno, in the dyno's own terms but no vendor's numbers.

The *roles* below are the registers the end-of-line cycle needs (speed set point, enable, drive
state, capture window...), each with its group, its physical unit and, for codes and bit fields,
the names a register map gives raw values to. Where a role lives on a particular dyno (address,
holding or input table, type, scaling, byte and word order, raw codes) is data: a register map
file, :mod:`eol_cal.dyno.regmap` (``eol_cal/dyno/maps/default.toml`` is the eol-cal reference
dyno the simulator serves by default; ``vendor-b.toml`` a differently built one). Client and
simulator speak roles and semantic values (``DriveState.AT_SPEED``, rpm, N*m) and let the map
encode them.

Capture data are moved through a paged window: the client writes ``buf_channel`` and the first
sample of the page ``buf_offset``, then reads the page in blocks of at most the map's
``max_read_registers``. Analog channels carry one value per sample (the window's
``analog_type``); the packed digital channel one ``u16`` per sample (``enc_a``, ``enc_b`` and the
3-bit ``hall`` at the bits the map gives). Sample ``k`` of a capture was taken at ``k /
capture_rate`` seconds after the capture started.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from types import MappingProxyType
from collections.abc import Mapping

import numpy as np

#: |speed| at or below this counts as standstill (rpm): direction changes are allowed there
STANDSTILL_RPM = 1.0
#: the dyno reports "at speed" within max(SPEED_TOL_RPM, SPEED_TOL_REL * |set point|) (rpm)
SPEED_TOL_RPM = 1.0
SPEED_TOL_REL = 0.005


class Mode(enum.IntEnum):
    """``mode``: what the dyno regulates."""

    OFF = 0
    SPEED = 1  # dyno holds the speed set point; the DUT is loaded by ``dut_cmd``


class Switch(enum.IntEnum):
    """``enable``: the drive's run command."""

    OFF = 0
    ON = 1


class Direction(enum.IntEnum):
    """``direction``: the sign of the speed set point."""

    FORWARD = 0
    REVERSE = 1


class Command(enum.IntEnum):
    """``stop``, ``fault_reset``: act on the write, read back ``IDLE``."""

    IDLE = 0
    EXECUTE = 1


class CaptureCommand(enum.IntEnum):
    """``capture_start``: arm or abort a capture; reads back ``IDLE``."""

    IDLE = 0
    ARM = 1
    ABORT = 2


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


def fault_names(faults: int) -> list[str]:
    """The names of the set bits of a ``faults`` register (bits this layout does not name, in hex)."""
    names = [f.name or f"0x{int(f):04x}" for f in Fault if f & faults]  # iterating a Flag yields named members
    unknown = faults & ~sum(int(f) for f in Fault)
    return names + ([f"0x{unknown:04x}"] if unknown else [])


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


#: the analog capture channels a dyno may record (canonical channel names)
ANALOG_NAMES: tuple[str, ...] = ("torque", "iq_ref", "speed", "temp", "iqc", "iq", "id", "ia", "ib", "ic")
#: the fields of the packed digital channel and their widths (bits)
DIGITAL_FIELDS: Mapping[str, int] = MappingProxyType({"enc_a": 1, "enc_b": 1, "hall": 3})


def channel_bit(channel_id: int) -> int:
    """Bit of channel ``channel_id`` in ``capture_channels`` (bit ``id - 1``)."""
    return 1 << (channel_id - 1)


@dataclass(frozen=True)
class Role:
    """One register the cycle needs, independent of any dyno's layout.

    Attributes
    ----------
    name : str
        Key of the register in a map file (``[registers.NAME]``).
    group : str
        ``identification`` and ``status`` (read-only, written by the dyno), ``control``,
        ``transfer`` and ``sim`` (written by the client).
    unit : str
        Physical unit of the value the client and simulator use (a map's ``scale`` and
        ``offset`` convert the raw register to it).
    meaning : str
        What the value means.
    codes : type or None
        For code registers: the enum whose member names a map's ``codes`` table gives raw values.
    bits : type or None
        For bit fields: the flag enum whose member names a map's ``bits`` table gives bit numbers.
    text : bool
        ASCII text (``type = "str"``).
    required : bool
        A map must place it (the optional ones: ``map_version`` and the simulator's fault
        injection).
    """

    name: str
    group: str
    unit: str
    meaning: str
    codes: type[enum.IntEnum] | None = None
    bits: type[enum.IntFlag] | None = None
    text: bool = False
    required: bool = True

    @property
    def writable(self) -> bool:
        return self.group in ("control", "transfer", "sim")


_ROLE_LIST: tuple[Role, ...] = (
    Role("map_version", "identification", "",
         "register map version; the map file's map_version is what the client expects", required=False),
    Role("dut_serial", "identification", "", "serial of the motor on the dyno (ASCII, NUL-padded)", text=True),
    Role("dut_poles", "identification", "", "poles P of the motor on the dyno"),
    Role("dut_encoder_ppr", "identification", "", "encoder pulses per mechanical revolution (channel A)"),
    Role("dut_kt", "identification", "N*m/A", "torque constant of the motor on the dyno"),
    Role("max_speed", "identification", "rpm", "over-speed trip threshold"),
    Role("tick_hz", "identification", "Hz", "internal sample clock; capture_rate must divide it"),
    Role("mode", "control", "",
         "what the dyno regulates: off, or speed (it holds the speed set point, the DUT is loaded by dut_cmd); "
         "other values refused", codes=Mode),
    Role("enable", "control", "",
         "the drive's run command: on (refused unless all interlocks are met and no fault is latched) or off", codes=Switch),
    Role("stop", "control", "", "execute: ramp to zero speed, then disable; reads back idle", codes=Command),
    Role("direction", "control", "",
         "forward (positive speed) or reverse; changes refused above 1 rpm (STANDSTILL_RPM) while enabled", codes=Direction),
    Role("speed_setpoint", "control", "rpm", "speed set point magnitude (>= 0); the sign comes from direction"),
    Role("ramp", "control", "rpm/s", "speed ramp rate (> 0)"),
    Role("dut_cmd_kind", "control", "",
         "torque: dut_cmd is a shaft torque (N*m); iq: dut_cmd is the nominal q current i_qo (A)", codes=DutCmdKind),
    Role("dut_cmd", "control", "N*m or A", "load command passed to the DUT's ECU (unit per dut_cmd_kind)"),
    Role("capture_rate", "control", "Hz", "capture sample rate; must divide tick_hz"),
    Role("capture_length", "control", "samples", "samples to capture (1 ... 4 000 000)"),
    Role("capture_start", "control", "",
         "arm: the capture runs once the speed is within tolerance; abort; reads back idle", codes=CaptureCommand),
    Role("fault_reset", "control", "", "execute: clear latched faults (drive stays disabled); reads back idle", codes=Command),
    Role("watchdog_ms", "control", "ms",
         "communication watchdog: with no request for this long while enabled the dyno stops and latches comm_watchdog "
         "(0 = off)"),
    Role("speed", "status", "rpm", "actual shaft speed (signed)"),
    Role("torque", "status", "N*m",
         "actual shaft torque (positive when the DUT drives the dyno); NaN when the transducer failed"),
    Role("temperature", "status", "degC", "DUT winding temperature"),
    Role("faults", "status", "", "latched fault bits", bits=Fault),
    Role("interlocks", "status", "", "interlock bits, 1 = met", bits=Interlock),
    Role("drive_state", "status", "", "state of the drive", codes=DriveState),
    Role("capture_state", "status", "", "state of the capture", codes=CaptureState),
    Role("capture_count", "status", "samples",
         "samples in the capture buffer: all of them when capture_state is ready; while running, those recorded so far "
         "(0 on a dyno that does not say)"),
    Role("capture_channels", "status", "", "channels in the buffer: bit (id-1) for channel id (see the channel table)"),
    Role("heartbeat", "status", "", "counts up every 10 ms while the dyno controller runs (wraps)"),
    Role("capture_seq", "status", "", "number of captures completed since power-up (wraps); changes when a new buffer is ready"),
    Role("buf_channel", "transfer", "", "channel id of the window page (see the channel table)"),
    Role("buf_offset", "transfer", "samples", "sample index of the first sample in the window page"),
    Role("sim_bench", "identification", "",
         "simulator only: the torque path its plant simulated in the last capture (16 hex characters, "
         "eol_cal.domain.bench_mechanics.model_digest; empty before one); a real dyno leaves it out", text=True,
         required=False),
    Role("sim_fault", "sim", "", "simulator only: write a fault to inject", codes=SimFault, required=False),
    Role("sim_fault_arg", "sim", "ms", "simulator only: disconnect duration for sim_fault disconnect", required=False),
)

ROLES: Mapping[str, Role] = MappingProxyType({r.name: r for r in _ROLE_LIST})
#: the groups in the order the docs list them
GROUPS: tuple[str, ...] = ("identification", "control", "status", "transfer", "sim")


def pack_digital(enc_a: np.ndarray, enc_b: np.ndarray | None, hall: np.ndarray,
                 bits: Mapping[str, int]) -> np.ndarray:
    """Digital levels -> one u16 word per sample, each field at its bit in ``bits``."""
    w = (np.asarray(enc_a, dtype=np.uint16) & 1) << bits["enc_a"]
    if enc_b is not None:
        w = w | ((np.asarray(enc_b, dtype=np.uint16) & 1) << bits["enc_b"])
    return (w | ((np.asarray(hall, dtype=np.uint16) & 7) << bits["hall"])).astype(np.uint16)


def unpack_digital(words: np.ndarray, bits: Mapping[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One u16 word per sample -> (enc_a, enc_b, hall) integer levels."""
    w = np.asarray(words, dtype=np.int64)
    return (w >> bits["enc_a"]) & 1, (w >> bits["enc_b"]) & 1, (w >> bits["hall"]) & 7
