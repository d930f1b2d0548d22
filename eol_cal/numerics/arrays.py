"""Type names for code that runs on numpy and on JAX alike (the plant's scan, the mechanics,
angle wrapping): annotations only, nothing here runs."""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Union

import numpy as np

if TYPE_CHECKING:
    import jax

#: a numpy array, a JAX array (traced or not) or a Python/numpy scalar; units as documented
#: where it is used
Array = Union[np.ndarray, "jax.Array", float]
#: the array namespace a function computes with: ``numpy`` or ``jax.numpy``
ArrayModule = ModuleType
