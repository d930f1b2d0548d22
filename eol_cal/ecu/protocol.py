"""Firmware contract v1, section 3: every CAN/UDS constant and byte codec, spelled once.

Both the flashing client (:mod:`eol_cal.ecu.client`) and the ECU simulator
(:mod:`eol_cal.ecu.sim_ecu`) import from here, so a protocol byte can only disagree with
the contract in one place. Service IDs and NRC values come from udsoncan
(``udsoncan.services`` / ``udsoncan.Response.Code``) rather than being restated.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from dataclasses import dataclass

from udsoncan import MemoryLocation
from udsoncan import Response

# the contract's identifiers and check codes, read through this module by the client and the simulator
from eol_cal.firmware.contract import (  # noqa: F401
    CHECK_STATUS,
    DID_ACTIVE_BLOCK,
    DID_LAYOUTS,
    DID_SERIAL,
    DID_SW_VERSION,
    NO_BANK,
    RID_CHECK,
    RID_ERASE,
    STATUS_CRC_MISMATCH,
    STATUS_HEADER_INVALID,
    STATUS_VALID,
)

# --- CAN / ISO-TP (contract 3, first bullets) --------------------------------------------
TESTER_ID = 0x7E0
"""CAN ID tester -> ECU (11 bit)."""
ECU_ID = 0x7E8
"""CAN ID ECU -> tester (11 bit)."""
PADDING = 0xCC
"""Every frame is padded to :data:`FRAME_BYTES` with this byte."""
FRAME_BYTES = 8
BITRATE = 500_000
"""Nominal bus bit rate, bit/s."""
FC_BLOCK_SIZE = 0
FC_STMIN = 0

# --- Sessions and timing ------------------------------------------------------------------
SESSION_DEFAULT = 0x01
SESSION_PROGRAMMING = 0x02
SESSION_EXTENDED = 0x03
P2_S = 0.050
"""P2server_max, s (announced in the 0x10 response)."""
P2_STAR_S = 5.0
"""P2*server_max, s (announced in the 0x10 response)."""
S3_S = 5.0
"""Session timeout without a request, s."""

# --- Security access level 1 -----------------------------------------------------------------
SECURITY_LEVEL = 1
"""RequestSeed sub-function; SendKey is ``SECURITY_LEVEL + 1``."""
SEED_BYTES = 4
KEY_BYTES = 4
SECRET_BYTES = 16
LOCKOUT_ATTEMPTS = 3
"""The third wrong key in a row is answered NRC 0x36."""
LOCKOUT_S = 10.0
"""After the lock-out every RequestSeed gets NRC 0x37 for this long, s."""
DEV_SECRET = bytes(range(16))
"""The simulator's development secret. Never a default for a real ECU."""

# --- Memory addressing -------------------------------------------------------------------------
ADDRESS_BITS = 32
SIZE_BITS = 32
ALFID = 0x44
"""addressAndLengthFormatIdentifier: 4-byte word address, 4-byte byte count."""
MAX_READ_BYTES = 1024
"""Largest ReadMemoryByAddress the ECU serves, bytes."""
WORD_BYTES = 2
"""C28x memory is addressed in 16-bit words."""
ERASED_BYTE = 0xFF
"""An erased NOR-flash word reads 0xFFFF (contract section 1)."""

# --- Identifiers: the contract's (DID_*, RID_*, NO_BANK, imported above) and UDS's own --------------
ROUTINE_START = 0x01
RESET_HARD = 0x01
DOWNLOAD_DFI = 0x00
"""dataFormatIdentifier: no compression, no encryption."""

CHECK_STATUS_TEXT = {s.code: s.text for s in CHECK_STATUS.values()}

# --- Negative response codes: contract list, values from udsoncan ------------------------
NRC = Response.Code
CONTRACT_NRCS = (
    NRC.ServiceNotSupported,  # 0x11
    NRC.SubFunctionNotSupported,  # 0x12
    NRC.IncorrectMessageLengthOrInvalidFormat,  # 0x13
    NRC.ConditionsNotCorrect,  # 0x22
    NRC.RequestSequenceError,  # 0x24
    NRC.RequestOutOfRange,  # 0x31
    NRC.SecurityAccessDenied,  # 0x33
    NRC.InvalidKey,  # 0x35
    NRC.ExceedNumberOfAttempts,  # 0x36
    NRC.RequiredTimeDelayNotExpired,  # 0x37
    NRC.UploadDownloadNotAccepted,  # 0x70
    NRC.GeneralProgrammingFailure,  # 0x72
    NRC.WrongBlockSequenceCounter,  # 0x73
    NRC.RequestCorrectlyReceived_ResponsePending,  # 0x78
    NRC.SubFunctionNotSupportedInActiveSession,  # 0x7E
    NRC.ServiceNotSupportedInActiveSession,  # 0x7F
)

NRC_HINT: dict[int, str] = {
    NRC.ServiceNotSupported: "the ECU does not implement this service",
    NRC.SubFunctionNotSupported: "the ECU does not implement this sub-function",
    NRC.IncorrectMessageLengthOrInvalidFormat: "the request had a wrong length or format",
    NRC.ConditionsNotCorrect: "conditions not correct (e.g. the target is the active bank)",
    NRC.RequestSequenceError: "request out of order (the ECU enforces the programming sequence)",
    NRC.RequestOutOfRange: "address, size, identifier or parameter out of range",
    NRC.SecurityAccessDenied: "security access required: the ECU is locked",
    NRC.InvalidKey: "wrong key: check the secret (key file) and the seed-to-key algorithm",
    NRC.ExceedNumberOfAttempts: "too many wrong keys: the ECU is now locked out",
    NRC.RequiredTimeDelayNotExpired: "the ECU is in its security lock-out delay; wait and retry",
    NRC.UploadDownloadNotAccepted: "download not accepted for this memory area",
    NRC.GeneralProgrammingFailure: "flash programming failed (a bit had to go from 0 to 1: bank not erased?)",
    NRC.WrongBlockSequenceCounter: "wrong TransferData block sequence counter",
    NRC.RequestCorrectlyReceived_ResponsePending: "response pending",
    NRC.SubFunctionNotSupportedInActiveSession: "sub-function not allowed in the active session",
    NRC.ServiceNotSupportedInActiveSession: "service not allowed in the active session",
}


def nrc_text(code: int) -> str:
    """Human text for a negative response code: ``0x33 SecurityAccessDenied: ...``."""
    name = NRC.get_name(code) or "unknown"
    hint = NRC_HINT.get(code, "")
    return f"NRC 0x{code:02X} {name}" + (f": {hint}" if hint else "")


def next_block_counter(bsc: int) -> int:
    """TransferData's blockSequenceCounter after ``bsc``: starts at 1, wraps 0xFF -> 0x00."""
    return (bsc + 1) & 0xFF


# --- Codecs ----------------------------------------------------------------------------------------
def session_timing_record(p2_s: float = P2_S, p2_star_s: float = P2_STAR_S) -> bytes:
    """sessionParameterRecord of the 0x10 response: P2 in ms, P2* in units of 10 ms."""
    return struct.pack(">HH", round(p2_s * 1000), round(p2_star_s * 100))


def security_key(secret: bytes, seed: bytes) -> bytes:
    """Contract key: ``HMAC-SHA256(secret, seed)[:4]``.

    Parameters
    ----------
    secret : bytes
        The ECU's 16-byte secret.
    seed : bytes
        The 4-byte seed from ``27 01``.
    """
    return hmac.new(secret, seed, hashlib.sha256).digest()[:KEY_BYTES]


def memory_location(word_address: int, size_bytes: int) -> MemoryLocation:
    """A udsoncan memory location in the contract's format (ALFID 0x44).

    Parameters
    ----------
    word_address : int
        C28x 16-bit word address.
    size_bytes : int
        Length in bytes.
    """
    return MemoryLocation(word_address, size_bytes, ADDRESS_BITS, SIZE_BITS)


def location_bytes(word_address: int, size_bytes: int) -> bytes:
    """``44 <addr u32 BE, words> <size u32 BE, bytes>`` as used in routine options."""
    loc = memory_location(word_address, size_bytes)
    return loc.alfid.get_byte() + loc.get_address_bytes() + loc.get_memorysize_bytes()


def parse_location(data: bytes) -> tuple[int, int, bytes]:
    """Parse ``44 <addr> <size>`` at the start of ``data``.

    Returns
    -------
    word_address, size_bytes, rest
        Word address, byte count and the bytes after the location.

    Raises
    ------
    ValueError
        Wrong ALFID or too few bytes.
    """
    if len(data) < 1 or data[0] != ALFID:
        raise ValueError("addressAndLengthFormatIdentifier must be 0x44")
    n_addr, n_size = ADDRESS_BITS // 8, SIZE_BITS // 8
    if len(data) < 1 + n_addr + n_size:
        raise ValueError("address and size truncated")
    loc = MemoryLocation.from_bytes(bytes(data[1 : 1 + n_addr]), bytes(data[1 + n_addr : 1 + n_addr + n_size]))
    return loc.address, loc.memorysize, bytes(data[1 + n_addr + n_size :])


@dataclass(frozen=True)
class ActiveBlock:
    """DID FD01: which bank the ECU runs from.

    Attributes
    ----------
    bank : int
        0, 1, or :data:`NO_BANK` (0xFF) when no bank is valid.
    sequence : int
        Write counter of the active block (0 with no bank).
    layout_version : int
    crc32 : int
    """

    bank: int
    sequence: int
    layout_version: int
    crc32: int

    FORMAT = ">BIHI"

    def pack(self) -> bytes:
        return struct.pack(self.FORMAT, self.bank, self.sequence, self.layout_version, self.crc32)

    @classmethod
    def unpack(cls, data: bytes) -> ActiveBlock:
        return cls(*struct.unpack(cls.FORMAT, bytes(data)))

    @classmethod
    def size(cls) -> int:
        return struct.calcsize(cls.FORMAT)

    @property
    def has_bank(self) -> bool:
        return self.bank != NO_BANK


def pack_layouts(layouts: tuple[int, ...]) -> bytes:
    """DID FD00: count u8 then one u16 per supported layout version."""
    return struct.pack(f">B{len(layouts)}H", len(layouts), *layouts)


def unpack_layouts(data: bytes) -> tuple[int, ...]:
    """Inverse of :func:`pack_layouts`; raises ValueError on a count/length mismatch."""
    if len(data) < 1 or len(data) != 1 + 2 * data[0]:
        raise ValueError("FD00 length does not match its count")
    return struct.unpack(f">{data[0]}H", bytes(data[1:]))
