"""Register reads (function codes 3 and 4) coded in one ``struct`` call, for pymodbus 3.16.

pymodbus codes a read's registers one ``struct`` call each: the response's ``encode`` appends 125
two-byte strings to a growing bytes object, its ``decode`` unpacks them one by one (and formats
all of them for a debug line, logged or not). A motor's captures are ~9 500 such reads; coded
in one call the station's CPU for them fell by a fifth to a quarter and the simulated dyno's by
up to a fifth (``bench/bench_dyno.py``, 2026-12-01). These subclasses give the same bytes and the same
register lists (``tests/test_dyno_pdu.py``); they enter through pymodbus's own extension points:
:func:`fast_reads` on a client (``register``), :data:`SERVER_PDUS` on a server (``custom_pdu``).

A server may also answer some reads without its datastore (:func:`server_pdus`): the dyno
simulator serves its capture window's pages from the buffer itself, where pymodbus's simulator
datastore would check each of a read's 125 registers' flags in a Python loop, copy the page into
its register list and out again.
"""

from __future__ import annotations

import struct
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
)

if TYPE_CHECKING:
    from pymodbus.client.base import ModbusBaseClient, ModbusBaseSyncClient
    from pymodbus.datastore import ModbusServerContext
    from pymodbus.pdu import ModbusPDU


class _OneCall:
    """A read response's coding in one ``struct`` call (mixed in before pymodbus's class)."""

    registers: Sequence[int]
    function_code: int
    dev_id: int
    transaction_id: int

    def encode(self) -> bytes:
        return struct.pack(f">B{len(self.registers)}H", 2 * len(self.registers), *self.registers)

    def decode(self, data: bytes) -> None:
        # pymodbus's checks: a byte count beyond the frame is refused (and an odd one, which its
        # loop would read past)
        n = int(data[0])
        if n >= len(data) or n % 2:
            raise ModbusIOException(f"byte_count {n} > length of packet {len(data)}", function_code=self.function_code)
        self.registers = list(struct.unpack_from(f">{n // 2}H", data, 1))

    def __str__(self) -> str:
        # pymodbus formats every decoded PDU for its debug log whether or not anyone listens; the
        # registers' values are in its log's frame line just before
        return f"{type(self).__name__}(dev_id={self.dev_id}, transaction_id={self.transaction_id}, " \
               f"{len(self.registers)} registers)"


class HoldingResponse(_OneCall, ReadHoldingRegistersResponse):
    """:class:`ReadHoldingRegistersResponse` coded in one ``struct`` call."""


class InputResponse(_OneCall, ReadInputRegistersResponse):
    """:class:`ReadInputRegistersResponse` coded in one ``struct`` call."""


#: ``read(function_code, address, count)``: a read's registers, an exception code, or None where the
#: datastore answers it (:func:`server_pdus`)
DirectRead = Callable[[int, int, int], Awaitable["list[int] | ExcCodes | None"]]


class _Answered:
    """A server's register read answered by :class:`HoldingResponse` or :class:`InputResponse`
    (pymodbus's ``datastore_update`` but for the response's class; mixed in before its request)."""

    function_code: int
    address: int
    count: int
    transaction_id: int
    direct: DirectRead | None = None

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        direct = None if self.direct is None else await self.direct(self.function_code, self.address, self.count)
        values = direct if direct is not None else \
            await context.async_getValues(device_id, self.function_code, self.address, self.count)
        if isinstance(values, ExcCodes):
            return ExceptionResponse(self.function_code, values)
        response = HoldingResponse if self.function_code == 3 else InputResponse
        return response(registers=values, dev_id=device_id, transaction_id=self.transaction_id)


class HoldingRequest(_Answered, ReadHoldingRegistersRequest):
    """A server's read of holding registers answered by :class:`HoldingResponse`."""


class InputRequest(_Answered, ReadInputRegistersRequest):
    """A server's read of input registers answered by :class:`InputResponse`."""


#: a pymodbus server's ``custom_pdu``: its register reads answered in one ``struct`` call each
SERVER_PDUS: list[type[ModbusPDU]] = [HoldingRequest, InputRequest]


def server_pdus(direct: DirectRead) -> list[type[ModbusPDU]]:
    """:data:`SERVER_PDUS` whose reads ask ``direct`` first (one server's: bound to its classes).

    ``direct(function_code, address, count)`` returns the registers, or an exception code, of the
    reads it serves itself, and None for the others, which the server's datastore answers.
    """
    return [type(cls.__name__, (cls,), {"direct": staticmethod(direct)}) for cls in SERVER_PDUS]


def fast_reads(client: ModbusBaseClient | ModbusBaseSyncClient) -> None:
    """Let a pymodbus client decode register reads in one ``struct`` call each."""
    client.register(HoldingResponse)
    client.register(InputResponse)
