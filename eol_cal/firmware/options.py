"""The estimator options a block carries (contract revision 1.1, ``flags`` bits 2-5): by preset,
by name or by mask, and back to names.

The bits themselves are :mod:`eol_cal.firmware.contract`'s (``ESTIMATOR_OPTIONS``); what the
estimator does with them is :meth:`eol_cal.firmware.estimator_config.EstimatorConfig.from_flags`.
A choice is written as a preset (``paper``: none, the seed paper's estimator; ``best``: all four),
as option names joined by ``+`` (the contract's names, with or without their ``EST_`` prefix, any
case: ``learn_grid_offset+learn_pitch_errors``), or as a hex mask of bits 2-5 (``0x28``).
"""

from __future__ import annotations

from eol_cal.errors import InputError
from eol_cal.firmware.contract import EST_PREFIX, ESTIMATOR_OPTIONS, FLAG_INTERP_ENABLE, FLAGS_ESTIMATOR

#: the named choices: option bits by preset name
PRESETS: dict[str, int] = {"paper": 0, "best": FLAGS_ESTIMATOR}
#: the choice used when none is given
DEFAULT_PRESET = "best"


def parse_options(text: str, source: str | None = None, field: str = "estimator") -> int:
    """The option bits (``flags`` bits 2-5) of a written choice.

    Parameters
    ----------
    text : str
        ``paper``, ``best``, option names joined by ``+``, or a hex mask (``0x..``) of bits 2-5.
    source, field : str, optional
        File and key the text came from, named in the error.

    Raises
    ------
    InputError
        An unknown name, or a mask with bits outside 2-5.
    """
    if not isinstance(text, str):
        raise InputError(source, field, f"{text!r} is not a string: {_expected()}")
    word = text.strip()
    if word.lower() in PRESETS:
        return PRESETS[word.lower()]
    if word.lower().startswith("0x"):
        try:
            mask = int(word, 16)
        except ValueError:
            raise InputError(source, field, f"{text!r} is not a hex mask: {_expected()}") from None
        if mask & ~FLAGS_ESTIMATOR:
            raise InputError(source, field, f"mask {text} has bits outside the estimator options "
                                            f"(0x{FLAGS_ESTIMATOR:02x}, bits 2-5)")
        return mask
    bits = 0
    for part in word.split("+"):
        name = part.strip().upper()
        name = name if name.startswith(EST_PREFIX) else EST_PREFIX + name
        if name not in ESTIMATOR_OPTIONS:
            raise InputError(source, field, f"unknown estimator option {part.strip()!r} in {text!r}: {_expected()}")
        bits |= ESTIMATOR_OPTIONS[name]
    return bits


def _expected() -> str:
    names = ", ".join(n[len(EST_PREFIX):].lower() for n in ESTIMATOR_OPTIONS)
    return f"expected {' or '.join(PRESETS)}, names joined by '+' ({names}) or a hex mask of bits 2-5"


def option_names(bits: int) -> list[str]:
    """The contract names of the option bits set in ``bits`` (other bits ignored)."""
    return [name for name, mask in ESTIMATOR_OPTIONS.items() if bits & mask]


def options_label(bits: int) -> str:
    """A choice written back: the preset's name when it is one, else the names joined by ``+``."""
    bits &= FLAGS_ESTIMATOR
    for name, mask in PRESETS.items():
        if bits == mask:
            return name
    return "+".join(option_names(bits))


def honoured_options(flags: int) -> int:
    """The option bits a firmware runs with a block's ``flags``: bits 2-5 when ``INTERP_ENABLE``
    is set, none without it (the raw encoder angle needs no estimator)."""
    return flags & FLAGS_ESTIMATOR if flags & FLAG_INTERP_ENABLE else 0


def ignored_options(flags: int) -> int:
    """Option bits a block sets that its firmware will not honour (no ``INTERP_ENABLE``)."""
    return flags & FLAGS_ESTIMATOR & ~honoured_options(flags)
