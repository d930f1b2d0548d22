"""numpy for one motor's scalars (:data:`SCALAR_NP`): the tick-by-tick references' ``xp``.

The firmware's steps (:mod:`eol_cal.firmware.estimator_step`, :mod:`eol_cal.firmware.mech_tick`)
are written once with ``xp`` operations; on one motor's numpy scalars this module stands in for
numpy without the 0-d array round trips of ``np.where`` & co., computing exactly what numpy
computes (tests/test_mech_scalar.py), and a step may take a Python branch where ``xp is SCALAR_NP``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from eol_cal.firmware.estimator_config import I32
from eol_cal.numerics.arrays import Array, ArrayModule

if TYPE_CHECKING:
    from collections.abc import Callable

T = TypeVar("T")

_I32_ZERO, _I32_ONE = cast(Array, I32(0)), cast(Array, I32(1))


def _int32_of(x: Array, _bool: type = np.bool_, _i32: type = np.int32) -> Array:
    """``np.int32(x)`` without numpy's construction for a flag or an int32 already (~20 a tick):
    the same value and type. Also a dtype (``.dtype``), as ``np.int32`` is."""
    t = type(x)
    if t is _bool:
        return _I32_ONE if x else _I32_ZERO
    if t is _i32:
        return x
    return _i32(x)


_int32_of.dtype = np.dtype(np.int32)  # type: ignore[attr-defined]


class _ScalarNumpy:
    """numpy for one motor's scalars, minus the 0-d array round trips of ``np.where`` & co.

    Selections and min/max pick one of their (already binary32) operands, ``take`` indexes and
    ``asarray`` leaves a numpy scalar of the asked dtype as it is, so the arithmetic and its
    results are those of ``xp=numpy`` exactly; the tick-by-tick references (:func:`run`,
    :func:`eol_cal.firmware.mech_run.run_mech`) use it for speed only. ``numpy_of`` gives numpy
    back where a step works on whole arrays (the identifier's evaluation).
    """

    int32 = staticmethod(_int32_of)
    float32 = np.float32
    floor = staticmethod(np.floor)
    zeros = staticmethod(np.zeros)
    zeros_like = staticmethod(np.zeros_like)

    @staticmethod
    def asarray(x: Array, dtype: Any = None) -> Array:
        if dtype is not None and not isinstance(dtype, type):
            dtype = dtype.dtype  # int32 above
        has = getattr(x, "dtype", None)  # a numpy scalar or array: as it is when its dtype is the one asked
        if has is not None and (dtype is None or has == dtype):
            return x
        return np.asarray(x, dtype)

    @staticmethod
    def take(a: np.ndarray, i: Array) -> Array:
        return a[cast(Any, i)]

    @staticmethod
    def bitwise_and(x: Array, y: Array) -> Array:
        return cast(Any, x) & y

    @staticmethod
    def where(c: Array, x: Array, y: Array) -> Array:
        return x if c else y

    @staticmethod
    def minimum(x: Array, y: Array) -> Array:
        return x if x < y else y

    @staticmethod
    def maximum(x: Array, y: Array) -> Array:
        return x if x > y else y

    @staticmethod
    def abs(x: Array) -> Array:
        return -x if x < 0 else x


#: typed as a module: it stands in for numpy wherever ``xp`` is
SCALAR_NP = cast(ArrayModule, _ScalarNumpy())


def numpy_of(xp: ArrayModule) -> ArrayModule:
    """``xp`` for a step on whole arrays: numpy for :data:`SCALAR_NP`, else ``xp`` itself."""
    return np if xp is SCALAR_NP else xp


def scalar_of(xp: ArrayModule) -> ArrayModule:
    """``xp`` for a step on one motor's scalars: :data:`SCALAR_NP` for numpy, else ``xp`` itself
    (the tick-by-tick references pass numpy, the plant traces ``jax.numpy``)."""
    return SCALAR_NP if xp is np else xp


def when(flag: Array, yes: Callable[[], T], no: Callable[[], T], xp: ArrayModule, batch_axis: str | None) -> T:
    """``yes()`` where ``flag``, else ``no()``, for a step whose ``no()`` gives, bit for bit, what
    ``yes()``'s own selects would keep when ``flag`` is false (so the choice only saves work).

    One motor's scalars (:data:`SCALAR_NP`): a Python branch. A member of a batch ``jax.vmap``-ped
    with ``axis_name=batch_axis``: ``jax.lax.cond`` on whether any member's ``flag`` is set (a
    branch on one member's value would compute both sides under ``vmap``). Otherwise ``yes()``.
    """
    if xp is SCALAR_NP:
        return yes() if flag else no()
    if batch_axis is None:
        return yes()
    import jax
    import jax.numpy as jnp

    return jax.lax.cond(jax.lax.psum(jnp.asarray(flag, jnp.int32), batch_axis) > 0, yes, no)
