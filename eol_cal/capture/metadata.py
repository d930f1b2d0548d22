"""Capture metadata as text (CSV ``# key: value`` lines, MDF4 header properties) and back.

Both file formats carry metadata values as text, so one encoding serves both and lets the
types ``int``, ``float`` and ``str`` round-trip:

- keys of the capture format have a fixed type (:data:`METADATA_TYPES`): ``poles = 6`` is an
  int however it is written, ``serial = 0001`` stays the string ``"0001"``;
- other keys (and every ``truth.*`` key) are read as int if they look like one, else float if
  they look like one, else string; a string that would be misread that way is written
  JSON-quoted (``"0001"``) and read back unquoted;
- a string with surrounding blanks, a line break or a leading quote is JSON-quoted as well.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping

from eol_cal.capture.ecu_state import METADATA_TYPES as ECU_STATE_TYPES
from eol_cal.capture.data import TRUTH_PREFIX
from eol_cal.errors import InputError

MetaValue = str | int | float

#: metadata keys of capture format v1 and their types
METADATA_TYPES: Mapping[str, type] = {
    "serial": str,
    "poles": int,
    "encoder_ppr": int,
    "kt": float,
    "iq_ref": float,
    "station": str,
    "operator": str,
    "created": str,
    "source": str,
    "comment": str,
    # the ECU's active block before and after the acquisition (eol_cal.capture.ecu_state)
    **ECU_STATE_TYPES,
}

KEY_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_INT_PATTERN = re.compile(r"^[+-]?[0-9]+$")


#: longest integer text read as a number (Python refuses to convert more than 4300 digits)
_MAX_INT_DIGITS = 100


def _infer(text: str) -> MetaValue:
    if _INT_PATTERN.match(text) and len(text) <= _MAX_INT_DIGITS:
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def _unquote(text: str) -> str | None:
    if len(text) >= 2 and text[0] == '"' and text[-1] == '"':
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            return None
        if isinstance(value, str):
            return value
    return None


def decode_value(key: str, text: str, file: str | None) -> MetaValue:
    """Typed metadata value from its text form (see the module docstring).

    Raises
    ------
    InputError
        A key of the capture format whose text is not of its type (``poles: six``).
    """
    text = text.strip()
    unquoted = _unquote(text)
    if unquoted is not None:
        return coerce_value(key, unquoted, file)
    want = METADATA_TYPES.get(key)
    if want is None:
        return _infer(text)
    return coerce_value(key, text, file)


def coerce_value(key: str, value: object, file: str | None) -> MetaValue:
    """Bring a metadata value (text, or a TOML value of a map file) to its key's type."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(file, key, f"metadata values must be a string, an integer or a number, got {value!r}")
    want = METADATA_TYPES.get(key)
    if want is None or isinstance(value, want) and not (want is float and isinstance(value, int)):
        return value
    if want is str:
        return str(value)
    if want is int:
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str) and _INT_PATTERN.match(value.strip()) and len(value.strip()) <= _MAX_INT_DIGITS:
            return int(value)
        raise InputError(file, key, f"must be an integer, got {value!r}")
    try:
        return float(value)
    except ValueError:
        raise InputError(file, key, f"must be a number, got {value!r}") from None


def encode_value(key: str, value: MetaValue, file: str | None = None) -> str:
    """Text form of a metadata value that :func:`decode_value` reads back to the same value."""
    if not isinstance(key, str) or not KEY_PATTERN.match(key):
        raise InputError(file, str(key), "metadata key must match [A-Za-z_][A-Za-z0-9_.-]*")
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(file, key, f"metadata value must be str, int or float, got {type(value).__name__}")
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    needs_quotes = (
        value != value.strip()
        or "\n" in value
        or "\r" in value
        or value.startswith('"')
        or (METADATA_TYPES.get(key) is None and not isinstance(_infer(value), str))
    )
    return json.dumps(value, ensure_ascii=False) if needs_quotes else value


def split_truth(
    items: Mapping[str, MetaValue],
) -> tuple[dict[str, MetaValue], dict[str, MetaValue]]:
    """Split file properties into (metadata, truth); truth keys lose their ``truth.`` prefix."""
    metadata: dict[str, MetaValue] = {}
    truth: dict[str, MetaValue] = {}
    for key, value in items.items():
        if key.startswith(TRUTH_PREFIX):
            truth[key[len(TRUTH_PREFIX) :]] = value
        else:
            metadata[key] = value
    return metadata, truth


def join_truth(metadata: Mapping[str, MetaValue], truth: Mapping[str, MetaValue]) -> dict[str, MetaValue]:
    """Inverse of :func:`split_truth`: one mapping with ``truth.``-prefixed simulator keys."""
    items = dict(metadata)
    items.update({TRUTH_PREFIX + key: value for key, value in truth.items()})
    return items
