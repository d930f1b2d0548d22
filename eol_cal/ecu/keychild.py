"""An OEM's seed-to-key function in a child process (:mod:`eol_cal.ecu.keyworker`), bounded in
time and in the size of its answer.

Foreign code in the tool's own process could end it (``sys.exit(1)`` read as "verification
failed"; a ``BaseException`` was a traceback), hang a flash for ever or hand a 200 MB key to the
ECU session. Here every call is a line to the child and a line back within
:data:`KEY_TIMEOUT_S`, at most :data:`MAX_KEY_BYTES` of key; anything else kills the child and is
one :class:`~eol_cal.errors.InputError` naming the algorithm's file and the field that chose it
(exit 2, before any erase: security access comes first). The cost is measured in
``bench/bench_faults.py --section oemkey`` (docs/benchmarks.md).
"""

from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
import threading
import time
import weakref

from eol_cal.errors import InputError

#: seconds a key may take: an ECU's security access waits for it within its S3 session timer (5 s)
KEY_TIMEOUT_S = 5.0
#: seconds for the child to start and import the algorithm's module (Python's start on a loaded machine)
LOAD_TIMEOUT_S = 20.0
#: the longest key taken (bytes): UDS keys are a few bytes, the contract's 4
MAX_KEY_BYTES = 64
#: the longest answer line read from the child: a key of MAX_KEY_BYTES in hex, or a message
_MAX_LINE = 2 * MAX_KEY_BYTES + 1024


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    for f in (proc.stdin, proc.stdout):
        if f is not None:
            f.close()


class ContainedKey:
    """``seed -> key bytes`` by the function ``func`` of module ``module`` in a child process.

    Parameters
    ----------
    module, func : str
        Where the function is (``func`` may be an attribute path).
    shown : str
        The algorithm as the user named it (for messages).
    secret : bytes or None
        The key file's secret, passed to the function as its second argument.
    field : str
        The option or settings key that chose it (for messages).
    """

    def __init__(self, module: str, func: str, shown: str, secret: bytes | None, field: str) -> None:
        self.module, self.func, self.shown, self.secret, self.field = module, func, shown, secret, field
        self.where: str | None = None
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()

    def _fail(self, why: str) -> InputError:
        if self._proc is not None:
            _kill(self._proc)
            self._proc = None
        return InputError(self.where, self.field, f"{self.shown} {why}")

    def _answer(self, timeout_s: float) -> list[str]:
        """The child's next answer line, within ``timeout_s`` and :data:`_MAX_LINE` bytes."""
        assert self._proc is not None and self._proc.stdout is not None
        fd = self._proc.stdout.fileno()
        buf = b""
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while b"\n" not in buf:
                left = deadline - time.monotonic()
                if left <= 0 or not sel.select(left):
                    raise self._fail(f"gave no answer within {timeout_s:g} s")
                chunk = os.read(fd, 65536)
                if not chunk:
                    code = self._proc.wait()
                    raise self._fail(f"ended its process (exit code {code}) without an answer")
                buf += chunk
                if len(buf) > _MAX_LINE:
                    raise self._fail(f"answered more than {_MAX_LINE} bytes (keys are at most {MAX_KEY_BYTES} bytes)")
        try:
            kind, text = json.loads(buf.split(b"\n", 1)[0])
            return [str(kind), str(text)]
        except (ValueError, TypeError):
            raise self._fail("answered something that is not a key") from None

    def _start(self) -> None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if isinstance(p, str) and p))
        self._proc = subprocess.Popen([sys.executable, "-m", "eol_cal.ecu.keyworker"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
                                      start_new_session=True)  # a terminal's Ctrl-C is the tool's, not the child's
        weakref.finalize(self, _kill, self._proc)
        spec = {"module": self.module, "func": self.func, "max_key_bytes": MAX_KEY_BYTES,
                "secret": None if self.secret is None else self.secret.hex()}
        self._send(json.dumps(spec))
        kind, text = self._answer(LOAD_TIMEOUT_S)
        if kind == "missing":
            self.where = text
            raise self._fail(f"names no function: {self.module} has no function {self.func!r}")
        if kind != "ready":
            raise self._fail(text)
        self.where = text

    def _send(self, line: str) -> None:
        assert self._proc is not None and self._proc.stdin is not None
        try:
            self._proc.stdin.write(line.encode() + b"\n")
            self._proc.stdin.flush()
        except OSError:
            raise self._fail(f"ended its process (exit code {self._proc.poll()}) before the seed was given") from None

    def __call__(self, seed: bytes) -> bytes:
        with self._lock:
            try:
                if self._proc is None or self._proc.poll() is not None:
                    self._start()
                self._send(bytes(seed).hex())
                kind, text = self._answer(KEY_TIMEOUT_S)
            except BaseException:  # a signal while waiting: the child goes with the call
                if self._proc is not None:
                    _kill(self._proc)
                    self._proc = None
                raise
            if kind != "key":
                raise self._fail(text)
            return bytes.fromhex(text)

    def close(self) -> None:
        """End the child (also done when this object is collected, and at the process's exit)."""
        with self._lock:
            if self._proc is not None:
                _kill(self._proc)
                self._proc = None
