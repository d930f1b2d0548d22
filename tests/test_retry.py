"""The one retry-with-backoff rule (eol_cal.infra.retry): attempts, doubling waits, what is not retried."""

import asyncio

import pytest

from eol_cal.infra.retry import RetriesExhausted, backoff_delays, retry_async, retry_call


def test_retries_with_doubling_waits_then_succeeds():
    waits, seen, calls = [], [], []

    def attempt(n):
        calls.append(n)
        if n < 2:
            raise ConnectionError(f"drop {n}")
        return "ok"

    out = retry_call(attempt, retries=3, delay_s=0.1, retry_on=(ConnectionError,),
                     before_retry=lambda n, exc: seen.append((n, str(exc))), sleep=waits.append)
    assert out == "ok" and calls == [0, 1, 2]
    assert waits == pytest.approx([0.1, 0.2]) and seen == [(1, "drop 0"), (2, "drop 1")]


def test_exhausted_carries_attempts_and_last_error():
    waits = []
    with pytest.raises(RetriesExhausted) as info:
        retry_call(lambda n: (_ for _ in ()).throw(TimeoutError(f"t{n}")), retries=2, delay_s=0.5,
                   retry_on=(TimeoutError,), sleep=waits.append)
    assert info.value.attempts == 3 and str(info.value.last) == "t2" and waits == [0.5, 1.0]


def test_other_errors_are_not_retried():
    calls = []

    def attempt(n):
        calls.append(n)
        raise ValueError("refused")

    with pytest.raises(ValueError):
        retry_call(attempt, retries=5, delay_s=0.0, retry_on=(ConnectionError,), sleep=lambda s: None)
    assert calls == [0]


def test_async_variant():
    calls = []

    async def attempt(n):
        calls.append(n)
        if n == 0:
            raise OSError("reset")
        return n

    assert asyncio.run(retry_async(attempt, retries=1, delay_s=0.0, retry_on=(OSError,))) == 1
    assert calls == [0, 1]
    with pytest.raises(ValueError):
        backoff_delays(-1, 0.1)
