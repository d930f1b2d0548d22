"""Which UDS message answers the request sent (one rule, :func:`answers`), and the tester's
connection that hands udsoncan only that answer (:class:`MatchingConnection`).

Real ECUs answer late: the answer to a request the tester gave up on arrives while it waits
for the next one (a RoutineControl answer 0x71 while it waited for ECUReset's 0x51 turned a
good flash into an ERROR). :class:`MatchingConnection` discards any message that does not answer
the request sent and goes on waiting within the same P2/P2* (udsoncan would raise on the first
message of another service).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from udsoncan import Request, Response, services

from eol_cal.ecu.transport import TesterConnection

log = logging.getLogger(__name__)

#: request bytes after the service ID that a positive answer repeats (its echo): a late answer
#: of the same service to another request differs there
_ECHO_BYTES = {
    services.DiagnosticSessionControl: 1, services.ECUReset: 1, services.SecurityAccess: 1,
    services.TesterPresent: 1, services.ReadDataByIdentifier: 2, services.RoutineControl: 3,
    services.TransferData: 1,
}
_SUPPRESS_BIT = 0x80  # ISO 14229-1: bit 7 of a sub-function asks for no positive answer


def _read_size(request: bytes) -> int | None:
    """The byte count a ReadMemoryByAddress request asks for (its answer carries no echo)."""
    if len(request) < 2:
        return None
    fmt = request[1]
    n_addr, n_size = fmt & 0x0F, fmt >> 4
    end = 2 + n_addr + n_size
    return int.from_bytes(request[2 + n_addr:end], "big") if len(request) >= end and n_size else None


def answers(request: bytes, message: bytes) -> bool:
    """Whether ``message`` (received) answers ``request`` (the payload sent).

    It does when it is the request's negative answer (``7F SID``), or its positive answer whose
    echo of the request matches (session, reset type, security level, DID, routine, block
    counter) and, for ReadMemoryByAddress, which carries as many bytes as were asked for. A
    malformed message is left to udsoncan, which reports it. An answer of another service, or
    a late one of the same service to another request, does not.
    """
    if not request or not message:  # nothing sent (udsoncan's own use), or empty: udsoncan reports it
        return True
    response = Response.from_payload(message)
    if not response.valid or response.service is None:
        return True
    if response.service.request_id() != request[0]:
        return False
    if not response.positive:
        return True
    n = _ECHO_BYTES.get(response.service, 0)
    sent, echoed = bytearray(request[1:1 + n]), bytearray(message[1:1 + n])
    if n and response.service.use_subfunction():
        sent[0] &= ~_SUPPRESS_BIT & 0xFF
        echoed[0] &= ~_SUPPRESS_BIT & 0xFF
    if sent != echoed:
        return False
    if response.service is services.ReadMemoryByAddress:
        size = _read_size(request)
        return size is None or len(message) - 1 == size
    return True


def _no_answer_expected(request: bytes) -> bool:
    """A request whose sub-function asks for no positive answer (ISO 14229-1, bit 7)."""
    if len(request) < 2:
        return False
    service = Request.from_payload(request).service
    return service is not None and service.use_subfunction() and bool(request[1] & _SUPPRESS_BIT)


class MatchingConnection(TesterConnection):
    """:class:`TesterConnection` that hands udsoncan only the answer to the request it sent.

    A message that does not answer it (:func:`answers`: a late answer to an earlier request,
    a duplicate) is logged, counted in :attr:`stale_answers` and dropped, and the wait goes on
    until the deadline udsoncan gave (P2, or P2* after a 0x78): a stale answer never extends it.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._request = b""
        self.stale_answers = 0

    def specific_send(self, payload: bytes, timeout: float | None = None) -> None:
        if not _no_answer_expected(payload):  # a TesterPresent 3E 80 from the keep-alive thread
            self._request = bytes(payload)  # must not change what a waiting request expects
        super().specific_send(payload, timeout)

    def specific_wait_frame(self, timeout: float | None = None) -> bytes | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            message = super().specific_wait_frame(left)  # TimeoutException at the deadline
            if message is None or answers(self._request, message):
                return message
            self.stale_answers += 1
            log.info("discarded a message that does not answer request %s: %s (a late or repeated answer)",
                     self._request[:4].hex(" "), message[:8].hex(" "))
