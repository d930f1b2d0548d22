"""A timestamped log of what is said to the line's machines: UDS with the ECU, Modbus with the dyno.

The UDS side comes from the libraries' own loggers: udsoncan's ``UdsClient`` (one line per
service request and its positive or negative response) and ``Connection`` (the payload bytes
sent and received, service id first); can-isotp's and python-can's warnings come along. The
Modbus side is this project's own hook in the dyno client (:func:`log_modbus`): function code,
first address, register count, the values written or read back, or the exception code.

Outside :func:`exchange_logging` those loggers stay quiet (:func:`quiet`): the commands report
failures themselves, in one line.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from typing import TextIO
from collections.abc import Iterator, Sequence

from eol_cal.errors import InputError
from eol_cal.infra.inputs import refuse_overwriting_input

#: logger of the dyno client's Modbus exchanges
MODBUS_LOGGER = "eol_cal.modbus"
#: loggers written while logging is on, and the level each is opened to
EXCHANGE_LOGGERS: dict[str, int] = {
    "UdsClient": logging.INFO,  # udsoncan: service requests and responses
    "Connection": logging.DEBUG,  # udsoncan: payload bytes, service id first
    "isotp": logging.WARNING,
    "can": logging.WARNING,
    MODBUS_LOGGER: logging.DEBUG,
}
#: Modbus values shown per line (a capture window block has up to 125 registers)
MAX_LOGGED_VALUES = 16

_FORMAT = "%(asctime)s.%(msecs)03dZ %(name)s %(levelname)s %(message)s"
_DATEFMT = "%Y-%m-%dT%H:%M:%S"
_active: set[str] = set()
_modbus = logging.getLogger(MODBUS_LOGGER)
_modbus.propagate = False
_modbus.addHandler(logging.NullHandler())


def quiet(names: Sequence[str]) -> None:
    """Silence loggers ``names`` (only CRITICAL passes) unless :func:`exchange_logging` writes them."""
    for name in names:
        if name not in _active:
            logging.getLogger(name).setLevel(logging.CRITICAL)


@contextlib.contextmanager
def exchange_logging(stream: TextIO | None = None, path: str | None = None) -> Iterator[None]:
    """Write the UDS and Modbus exchanges, with UTC timestamps (ms), to ``stream`` and/or ``path``.

    Parameters
    ----------
    stream : text stream, optional
        E.g. ``sys.stderr``.
    path : str, optional
        Log file, appended to (a station's log grows over a shift).

    Raises
    ------
    InputError
        The log file cannot be opened.
    """
    if stream is None and path is None:
        yield
        return
    formatter = logging.Formatter(_FORMAT, _DATEFMT)
    formatter.converter = time.gmtime
    handlers: list[logging.Handler] = []
    if stream is not None:
        handlers.append(logging.StreamHandler(stream))
    if path is not None:
        # opened at the first exchange, after the command's checks of its outputs (the log file
        # named the block being flashed or the limits file, and was appended to); a file that
        # cannot be written is refused now
        refuse_overwriting_input(path)
        parent = os.path.dirname(os.path.abspath(path))
        if not (os.access(path, os.W_OK) if os.path.exists(path) else os.access(parent, os.W_OK)):
            raise InputError(path, None, "cannot open the log file: not writable (or its directory does not exist)")
        handlers.append(logging.FileHandler(path, mode="a", encoding="utf-8", delay=True))
    saved = {}
    for handler in handlers:
        handler.setFormatter(formatter)
    for name, level in EXCHANGE_LOGGERS.items():
        logger = logging.getLogger(name)
        saved[name] = (logger.level, logger.propagate)
        logger.setLevel(level)
        logger.propagate = False
        for handler in handlers:
            logger.addHandler(handler)
        _active.add(name)
    try:
        yield
    finally:
        for name, (level, propagate) in saved.items():
            logger = logging.getLogger(name)
            for handler in handlers:
                logger.removeHandler(handler)
            logger.setLevel(level)
            logger.propagate = propagate
            _active.discard(name)
        for handler in handlers:
            handler.close()


def _values(words: Sequence[int] | None) -> str:
    if words is None:
        return ""
    shown = " ".join(f"{int(w):04x}" for w in list(words)[:MAX_LOGGED_VALUES])
    more = f" ...(+{len(words) - MAX_LOGGED_VALUES})" if len(words) > MAX_LOGGED_VALUES else ""
    return f" [{shown}{more}]"


def log_modbus(where: str, function_code: int, address: int, count: int, words: Sequence[int] | None = None,
               exception: int | str | None = None) -> None:
    """One Modbus exchange of the dyno client (nothing is formatted while nobody listens).

    Parameters
    ----------
    where : str
        The dyno (``host:port``).
    function_code : int
        3 read holding, 4 read input, 6/16 write.
    address, count : int
        First register (0-based PDU address) and how many.
    words : sequence of int, optional
        Register values written (writes) or read back (reads).
    exception : int or str, optional
        The Modbus exception code of a refusal, or why no answer came.
    """
    if not _modbus.isEnabledFor(logging.DEBUG):
        return
    outcome = f" -> exception {exception}" if exception is not None else _values(words)
    _modbus.debug("%s FC%02d addr %d (0x%04x) count %d%s", where, function_code, address, address, count, outcome)
