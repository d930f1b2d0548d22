"""The child process an OEM's seed-to-key function runs in (:mod:`eol_cal.ecu.keyalgo`).

Foreign code decides nothing about the tool's process here: whatever it does on import or on a
seed (``sys.exit``, ``os._exit``, raising ``BaseException``, a hang, printing, returning text or
200 MB) ends in this child, which answers on its own pipe or not at all; the parent bounds the
time and the size of every answer and kills the child otherwise.

Protocol (lines of JSON): the parent sends ``{"module", "func", "secret" (hex or null),
"max_key_bytes"}`` and then one seed (hex) per line; the child answers ``["ready", WHERE]`` or
``["error", WHY]`` to the first, ``["key", HEX]`` or ``["error", WHY]`` to each seed.
"""

from __future__ import annotations

import importlib
import json
import os
import sys
from typing import Any, BinaryIO


def _reply(proto: BinaryIO, kind: str, text: str) -> None:
    proto.write(json.dumps([kind, text]).encode() + b"\n")
    proto.flush()


def _why(exc: BaseException) -> str:
    if isinstance(exc, MemoryError):  # its own allocation failed: said in words, it is not the tool's
        return "ran out of memory"
    return f"{exc.__class__.__name__}: {exc}"[:500]


def _find(module: Any, func_name: str) -> Any:
    algo: object = module
    for part in func_name.split("."):  # an entry point may name an attribute path
        algo = getattr(algo, part, None)
    return algo if callable(algo) else None


def main() -> None:
    """Serve seeds until the parent closes the pipe; every answer on the saved stdout only."""
    proto = os.fdopen(os.dup(1), "wb")
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)  # what the algorithm prints must not read as an answer
    spec = json.loads(sys.stdin.readline())
    secret = bytes.fromhex(spec["secret"]) if spec["secret"] is not None else None
    try:
        module = importlib.import_module(spec["module"])
        algo = _find(module, spec["func"])
    except BaseException as exc:  # noqa: BLE001 - SystemExit, KeyboardInterrupt: all the module's doing
        _reply(proto, "error", f"cannot load: {_why(exc)}")
        return
    where = str(getattr(module, "__file__", None) or spec["module"])
    if algo is None:
        _reply(proto, "missing", where)
        return
    _reply(proto, "ready", where)
    for line in sys.stdin:
        try:
            key = algo(bytes.fromhex(line.strip()), secret)
        except BaseException as exc:  # noqa: BLE001 - whatever the foreign function raises, exits included
            _reply(proto, "error", f"failed on the seed: {_why(exc)}")
            continue
        if not isinstance(key, (bytes, bytearray, memoryview)):
            _reply(proto, "error", f"returned {type(key).__name__}, not the key bytes")
        elif not 0 < len(key) <= spec["max_key_bytes"]:
            _reply(proto, "error", f"returned a key of {len(key)} bytes (1 to {spec['max_key_bytes']} expected)")
        else:
            _reply(proto, "key", bytes(key).hex())


if __name__ == "__main__":
    try:
        main()
    finally:
        os._exit(0)  # threads the algorithm started do not keep the child alive
