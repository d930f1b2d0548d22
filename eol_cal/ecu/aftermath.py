"""After a failed or interrupted flash (:mod:`eol_cal.ecu.sequence`): where the sequence was
(:class:`FlashProgress`), the bank just written erased again where it must be (:func:`erase_again`),
and what the ECU boots now, for the message and for what the exception carries
(:func:`aftermath`, :func:`mark`, :func:`clean_up`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any
from collections.abc import Callable

from eol_cal.ecu import protocol as P
from eol_cal.ecu.session import SESSION_LOST_NRCS, EcuError, UdsSession
from eol_cal.errors import EolCalError
from eol_cal.firmware import block as B
from eol_cal.infra.interrupts import raise_if_received


#: the steps that change the ECU's flash: none starts after the command received a signal
WRITING_STEPS = frozenset({"erase", "download", "CRC (36)"})


@dataclass
class FlashProgress:
    """Where the flash sequence is, for the message of a failure."""

    steps: list[str]
    callback: Callable[[str], None] | None
    bank: int | None = None
    sequence: int = 0
    tail: str = "none"  # none | sent | written
    reset_sent: bool = False
    image: bytes = b""  # the block with its sequence and CRC, once built

    def step(self, name: str) -> str:
        self.steps.append(name)
        if self.callback is not None:
            self.callback(name)
        if name in WRITING_STEPS:
            # a signal whose exception was swallowed (a finalizer, a thread of the command) still
            # stops the flash before it erases or writes: the rollback of the caller runs
            raise_if_received(f"flash ({name})")
        return name

    @property
    def current(self) -> str:
        return self.steps[-1] if self.steps else "start"


def erase_again(s: UdsSession, base: int) -> str:
    """Erase the bank just written, re-entering the programming session if it was lost.

    Requests are repeated only while the ECU was heard less than S3 ago. Returns ``erased``,
    ``refused`` (an NRC or a dead link: not erased) or ``unknown`` (the erase went out and
    stayed unanswered: the ECU may still carry it out).
    """
    try:
        try:
            s.routine("erase again", P.RID_ERASE, base, B.BANK_BYTES)
        except EcuError as exc:
            if exc.nrc not in SESSION_LOST_NRCS:
                raise
            s.enter_programming()
            s.routine("erase again", P.RID_ERASE, base, B.BANK_BYTES)
    except EcuError as exc:
        return "unknown" if exc.cause == "timeout" and exc.step == "erase again" else "refused"
    return "erased"


def aftermath(s: UdsSession, prog: FlashProgress, base: int, rollback: bool) -> tuple[str, str]:
    """Clean up after a failure.

    Returns what the ECU boots, for the message, and in one word: ``previous``, ``new`` or
    ``maybe new`` (the exception's :attr:`ecu_boots`).
    """
    if prog.bank is None or prog.tail == "none":
        if rollback:
            s.leave()
        return "the previous block stays active", "previous"
    new = f"bank {prog.bank} (sequence {prog.sequence})"
    if prog.reset_sent:
        return f"the ECU was reset: it boots the new, checked block in {new}", "new"
    erased = erase_again(s, base) if rollback and not s.ecu_gone else "refused"
    if erased == "erased":
        s.leave()
        return f"{new} erased again: the previous block stays active", "previous"
    if erased == "unknown":
        return (f"{new} may still hold the complete new block, checked before its CRC was written (the erase "
                "sent to remove it went unanswered): if so, the ECU boots it at its next reset"), "maybe new"
    held = "holds" if prog.tail == "written" else "may hold"
    return (f"{new} {held} the complete new block, checked before its CRC was written: "
            "the ECU boots it at its next reset"), "new" if prog.tail == "written" else "maybe new"


def boots_of(prog: FlashProgress, word: str) -> dict[str, Any]:
    """The :attr:`ecu_boots` an exception of :func:`~eol_cal.ecu.sequence.flash_block` carries."""
    return {"boots": word, "bank": prog.bank, "sequence": prog.sequence if prog.bank is not None else None}


def mark(exc: BaseException, prog: FlashProgress, word: str) -> None:
    """What an exception of :func:`~eol_cal.ecu.sequence.flash_block` carries: ``ecu_boots`` and, once the CRC went out
    (the bank may hold the complete block), ``flashed_image``: the bytes it holds."""
    exc.ecu_boots = boots_of(prog, word)  # type: ignore[attr-defined]
    exc.flashed_image = prog.image if prog.tail != "none" else None  # type: ignore[attr-defined]


def clean_up(s: UdsSession, prog: FlashProgress, base: int, exc: EolCalError) -> None:
    """After a failure of the sequence: :func:`aftermath` with the bank erased again where it
    must be, what the ECU boots added to ``exc``'s message, and :func:`mark`."""
    outcome, word = aftermath(s, prog, base, rollback=True)
    exc.args = (f"{exc}; {outcome}",)
    mark(exc, prog, word)
