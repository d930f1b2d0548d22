"""The one rule for numbers in the tool's JSON: JSON has no NaN or infinity, so they become null."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def json_safe(x: Any) -> Any:
    """``x`` with non-finite floats as ``None`` and numpy scalars as Python ones, through dicts and lists.

    Scalars that must be floats in the document are passed as ``json_safe(float(x))``.
    """
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x
