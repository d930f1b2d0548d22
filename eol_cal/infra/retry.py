"""Retry with doubling back-off: the one rule every link of the station uses.

A request to a device (the dyno's Modbus registers, a page of its capture buffer, a UDS
request to the ECU) may fail for a reason that goes away: a dropped TCP connection, a timeout,
a bus that was busy. :func:`retry_call` (blocking) and :func:`retry_async` (asyncio) run the
request up to ``1 + retries`` times; before attempt ``n`` (n >= 1) they call ``before_retry``
(close the connection so a late answer to a timed-out request is not taken for the next one,
count a reconnect, log) and wait ``delay_s * 2**(n-1)`` seconds. Only the exception types
listed in ``retry_on`` are retried; anything else (a refusal, a programming error) goes up at
once. When every attempt failed, :class:`RetriesExhausted` carries the number of attempts and
the last error; the caller turns it into its own error with the device's name.

How to use it for a new link (e.g. the UDS session)::

    from eol_cal.infra.retry import RetriesExhausted, retry_call

    def attempt(n: int) -> Response:       # n = 0, 1, ... (0: first try)
        if not link.open:
            link.open_again()
        return link.request(...)

    try:
        response = retry_call(attempt, retries=3, delay_s=0.05,
                              retry_on=(TimeoutError, ConnectionError),
                              before_retry=lambda n, exc: link.close())
    except RetriesExhausted as exc:
        raise MyDeviceError(f"{where}: {what} failed after {exc.attempts} attempts: {exc.last}") from None

The delay doubles on purpose: a device that is rebooting or a switch that is re-learning
needs more time with every failure, and the sum stays bounded (``delay_s * (2**retries - 1)``).
"""

from __future__ import annotations

import asyncio
import time
from typing import TypeVar
from collections.abc import Awaitable, Callable

T = TypeVar("T")

#: ``before_retry(n, exc)``: called before attempt ``n`` (1-based count of retries) with the
#: exception that ended the previous attempt
BeforeRetry = Callable[[int, BaseException], None]


class RetriesExhausted(Exception):
    """Every attempt failed with a retryable error.

    Attributes
    ----------
    attempts : int
        Attempts made (``1 + retries``).
    last : BaseException
        The error of the last attempt.
    """

    def __init__(self, attempts: int, last: BaseException) -> None:
        super().__init__(f"failed after {attempts} attempts: {last or type(last).__name__}")
        self.attempts = attempts
        self.last = last


def backoff_delays(retries: int, delay_s: float) -> list[float]:
    """The waits (s) before retry 1, 2, ... ``retries``: ``delay_s``, doubling each time."""
    if retries < 0 or delay_s < 0:
        raise ValueError(f"retries ({retries}) and delay ({delay_s} s) must not be negative")
    return [delay_s * 2.0**n for n in range(retries)]


def retry_call(
    fn: Callable[[int], T],
    *,
    retries: int,
    delay_s: float,
    retry_on: tuple[type[BaseException], ...],
    before_retry: BeforeRetry | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> T:
    """Call ``fn(attempt)`` until it returns, retrying the errors ``retry_on``.

    Parameters
    ----------
    fn : callable
        One attempt; receives the attempt number (0 for the first).
    retries : int
        Retries after the first attempt (0: one attempt only).
    delay_s : float
        Wait before the first retry (s); doubles for each further one.
    retry_on : tuple of exception types
        Errors that are worth another attempt; any other error propagates at once.
    before_retry : callable, optional
        ``before_retry(n, exc)`` before retry ``n`` (1-based), e.g. to close the connection.
    sleep : callable
        The wait (s); a test may pass a fake clock.

    Returns
    -------
    What ``fn`` returned.

    Raises
    ------
    RetriesExhausted
        When all ``1 + retries`` attempts failed with a retryable error.
    """
    for attempt, delay in enumerate(backoff_delays(retries, delay_s)):
        try:
            return fn(attempt)
        except retry_on as exc:
            if before_retry is not None:
                before_retry(attempt + 1, exc)
            sleep(delay)
    try:
        return fn(retries)
    except retry_on as exc:
        raise RetriesExhausted(retries + 1, exc) from exc


async def retry_async(
    fn: Callable[[int], Awaitable[T]],
    *,
    retries: int,
    delay_s: float,
    retry_on: tuple[type[BaseException], ...],
    before_retry: BeforeRetry | None = None,
) -> T:
    """:func:`retry_call` for a coroutine: ``await fn(attempt)``, waiting with ``asyncio.sleep``."""
    for attempt, delay in enumerate(backoff_delays(retries, delay_s)):
        try:
            return await fn(attempt)
        except retry_on as exc:
            if before_retry is not None:
                before_retry(attempt + 1, exc)
            await asyncio.sleep(delay)
    try:
        return await fn(retries)
    except retry_on as exc:
        raise RetriesExhausted(retries + 1, exc) from exc
