"""Flashing client: keys, block files, identification, and the entry points of the sequence.

The layers: :mod:`.transport` (python-can, can-isotp, a guarded link), :mod:`.session` (the
udsoncan session: step names, bounded waits, retries, TesterPresent), :mod:`.sequence` (the
programming sequence of contract section 3). This module re-exports what callers use.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from eol_cal.capture.ecu_state import EcuState
from eol_cal.ecu import protocol as P
from eol_cal.ecu.sequence import FlashReport, flash_block
from eol_cal.ecu.session import ClientTiming, EcuError, SeedToKey, UdsSession, VerifyFailed
from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware.block_sanity import header_field
from eol_cal.infra.inputs import read_text

__all__ = ["ClientTiming", "EcuError", "EcuInfo", "FlashReport", "SeedToKey", "UdsSession", "VerifyFailed",
           "EcuCheck", "ecu_info", "ecu_state", "flash_block", "hmac_seed_to_key", "load_key_file", "preflight_ecu",
           "read_active_block", "session_state"]

log = logging.getLogger(__name__)


def hmac_seed_to_key(secret: bytes) -> SeedToKey:
    """The contract's algorithm: ``key = HMAC-SHA256(secret, seed)[:4]``."""
    if len(secret) != P.SECRET_BYTES:
        raise InputError(None, "secret", f"{len(secret)} bytes, the contract's secret has {P.SECRET_BYTES}")
    return lambda seed: P.security_key(secret, seed)


def load_key_file(path: str | Path) -> bytes:
    """Read a 16-byte security secret written as hex (whitespace and a ``0x`` prefix allowed)."""
    text = read_text(path, "key", encoding="ascii", max_bytes=4096)  # a FIFO or a device: refused unread
    cleaned = "".join(text.split())
    cleaned = cleaned[2:] if cleaned.lower().startswith("0x") else cleaned
    try:
        secret = bytes.fromhex(cleaned)
    except ValueError as exc:
        raise InputError(str(path), "key", "not hex") from exc
    if len(secret) != P.SECRET_BYTES:
        raise InputError(str(path), "key", f"{len(secret)} bytes, expected {P.SECRET_BYTES}")
    return secret


@dataclass
class EcuInfo:
    """What ``eol-cal ecu info`` reports.

    Attributes
    ----------
    serial, sw_version : str
    layouts : tuple of int
    active : protocol.ActiveBlock
    block : bytes or None
        The active block read back (None with no active bank).
    """

    serial: str
    sw_version: str
    layouts: tuple[int, ...]
    active: P.ActiveBlock
    block: bytes | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "serial": self.serial, "sw_version": self.sw_version, "layouts": list(self.layouts),
            "active": {"bank": None if not self.active.has_bank else self.active.bank,
                       "sequence": self.active.sequence, "layout_version": self.active.layout_version,
                       "crc32": f"{self.active.crc32:08x}"},
            "block": None,
        }
        if self.block is not None:
            chk = B.check(self.block)
            d["block"] = {"valid": chk.valid, "reasons": list(chk.reasons)}
            if chk.valid:
                blk = B.unpack(self.block, "ECU").to_dict()
                for name in ("table_const", "table_per_amp"):
                    blk.pop(name)
                d["block"].update(blk)
        return d


def read_bank(s: UdsSession, bank: int, step: str) -> bytes:
    """The block in ``bank`` (ReadMemoryByAddress): its header, then as many bytes as the header's
    ``table_len`` and layout say; only the header when that is not a table length (an erased bank)."""
    base = B.BANK_WORD_ADDR[bank]
    head = s.read_memory(base, B.HEADER_BYTES, step)
    table_len = int.from_bytes(head[B.field_offset("table_len"):B.field_offset("table_len") + 2], "little")
    layout = int.from_bytes(head[B.field_offset("layout_version"):B.field_offset("layout_version") + 2], "little")
    if not B.table_len_ok(table_len):
        return head
    size = B.block_bytes(table_len, layout if layout in B.LAYOUTS else 1)
    return head + s.read_memory(base + B.HEADER_BYTES // P.WORD_BYTES, size - B.HEADER_BYTES, step)


def _read_active_block(s: UdsSession, active: P.ActiveBlock) -> bytes:
    data = read_bank(s, active.bank, "read active block (23)")
    if len(data) == B.HEADER_BYTES:
        raise EcuError("read active block (23)", f"bank {active.bank} header: " + "; ".join(B.check(data).reasons))
    return data


def ecu_info(bus: can.BusABC, *, read_block: bool = True, timing: ClientTiming = ClientTiming()) -> EcuInfo:
    """Identify the ECU and (optionally) read back its active block. Needs no security access."""
    with UdsSession(bus, timing=timing) as s:
        s.session(P.SESSION_EXTENDED)
        try:
            info = EcuInfo(serial=s.read_did(P.DID_SERIAL), sw_version=s.read_did(P.DID_SW_VERSION),
                           layouts=tuple(s.read_did(P.DID_LAYOUTS)), active=s.read_did(P.DID_ACTIVE_BLOCK))
            if read_block and info.active.has_bank:
                info.block = _read_active_block(s, info.active)
        finally:
            s.leave()
    return info


def read_active_block(bus: can.BusABC, *, timing: ClientTiming = ClientTiming()) -> bytes:
    """The active block's bytes read back from the ECU; :class:`EcuError` when no bank is active."""
    info = ecu_info(bus, read_block=True, timing=timing)
    if info.block is None:
        raise EcuError("read active block", "the ECU has no valid block (FD01 bank 0xFF)")
    return info.block


def _active_state(s: UdsSession, serial: str | None) -> EcuState:
    """FD01 and the active block's flags (from its header, ReadMemoryByAddress)."""
    active = s.read_did(P.DID_ACTIVE_BLOCK)
    if not active.has_bank:
        return EcuState(None, serial=serial)
    head = s.read_memory(B.BANK_WORD_ADDR[active.bank], B.HEADER_BYTES, "read the active block's header (23)")
    return EcuState(active.bank, active.sequence, f"{active.crc32:08x}", B.flag_names(int(header_field(head, "flags"))),
                    serial)


def ecu_state(bus: can.BusABC, *, timing: ClientTiming = ClientTiming()) -> EcuState:
    """What the ECU runs now: its serial (F18C), active bank, sequence, CRC (FD01) and the block's
    flags. Extended session, no security access; nothing is written."""
    with UdsSession(bus, timing=timing) as s:
        return session_state(s)


def session_state(s: UdsSession) -> EcuState:
    """:func:`ecu_state` on a session already open, which stays open (the station's flash ahead reads
    it first, as the calibration capture's state after its last window, then goes on to program)."""
    s.session(P.SESSION_EXTENDED)
    return _active_state(s, s.read_did(P.DID_SERIAL))


@dataclass
class EcuCheck:
    """What :func:`preflight_ecu` found.

    Attributes
    ----------
    state : EcuState or None
        The ECU's serial and active block (None: the ECU did not answer).
    key_accepted : bool or None
        The security key was accepted (None: not tried, the ECU did not answer).
    problems : list of str
        Each failure, one line.
    """

    state: EcuState | None
    key_accepted: bool | None
    problems: list[str]

    def to_dict(self) -> dict[str, Any]:
        return {"state": None if self.state is None else self.state.to_dict(), "key_accepted": self.key_accepted,
                "problems": list(self.problems)}


def preflight_ecu(bus: can.BusABC, seed_to_key: SeedToKey | None, *,
                  timing: ClientTiming = ClientTiming()) -> EcuCheck:
    """Check the ECU before anything is written to it: it answers, its identity and active block,
    and that it accepts the security key (27 01/02 in the extended session; no programming
    session, no erase). Failures are returned, not raised; every wait is bounded by ``timing``."""
    with UdsSession(bus, seed_to_key=seed_to_key, timing=timing) as s:
        try:
            s.session(P.SESSION_EXTENDED)
            state = _active_state(s, s.read_did(P.DID_SERIAL))
        except EcuError as exc:
            return EcuCheck(None, None, [f"ECU not reachable: {exc}"])
        problems: list[str] = []
        try:
            s.unlock()
            accepted = True
        except (EcuError, InputError) as exc:
            accepted = False
            problems.append(f"security key not accepted: {exc}")
        try:  # back to the default session: the ECU drops the unlocked state with it
            s.call("default session (10 01)", s.client.change_session, P.SESSION_DEFAULT, retry=False)
        except EcuError as exc:
            log.debug("leaving the session: %s", exc)
    return EcuCheck(state, accepted, problems)
