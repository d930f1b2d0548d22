"""SIGINT, SIGTERM and SIGHUP as an exception, and holding them off while a record is written.

The CLI's handler (``cli.common.signals_interrupt``) calls :func:`deliver`, which raises
:class:`~eol_cal.errors.Interrupted` in the main thread at once, so every ``finally`` runs (the
dyno's safe state, the ECU's clean-up). Code that must not be cut short once it started (writing
a run's record and report) runs inside :func:`shielded`: a signal arriving there is raised when
the block ends.

A signal must stop the command whatever the main thread is doing when it comes:

- inside a finalizer or a garbage-collector callback (JAX's ``_xla_gc_callback``), an exception
  is not raised but printed ("Exception ignored in ...") and lost; the run went on, flashed and
  exited 0; inside importlib's own code an exception can leave the import lock held (every later
  import hangs); inside a ``__set_name__`` (a class being made) Python 3.11 wraps it in a
  ``RuntimeError``. There :func:`deliver` raises nothing and sends the signal again a moment later,
  and every signal is remembered (:func:`received`): a command checks it before each step that
  writes (:func:`raise_if_received`), and the CLI ends a command that received one with exit 2
  whatever it returned;
- inside a system call that C code repeats after the signal (SQLite opening a FIFO), Python's
  handler never runs. :func:`watchdog` reads the signal from the interpreter's wake-up file
  descriptor on a thread of its own; when the handler has not run within its grace period, it
  runs the emergency actions registered with :func:`emergency` (the dyno's safe state) and ends
  the process with exit 2.
"""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType

from eol_cal.errors import Interrupted

#: seconds the main thread has to run the signal handler before the watchdog ends the process
WATCHDOG_GRACE_S = 10.0
#: seconds after which a signal that came inside a finalizer is sent again
REDELIVER_S = 0.05

_depth = 0
#: the shields' count is kept by every thread that runs a cycle (a what-if lot's motors in threads):
#: ``+= 1`` is no atomic operation, and a lost update would hold signals off for good. The signal
#: handler only reads the count (it must not wait on a lock its own thread may hold)
_depth_lock = threading.Lock()
_pending: str | None = None
_received: str | None = None
_handled: dict[int, int] = {}
_emergency: list[Callable[[], None]] = []
#: whether a signal sent again (:func:`_redeliver`) may still go out: off once the command's
#: handlers are put back, under the lock so that a timer cannot pass the check and then kill
_redeliver_lock = threading.Lock()
_redeliver_on = True


def reset() -> None:
    """A new command: no signal received yet."""
    global _pending, _received, _redeliver_on
    _pending = _received = None
    with _redeliver_lock:
        _redeliver_on = True


def stop_redelivery() -> None:
    """No signal is sent again from now on: call it before the command's handlers are put back.
    The signal was received already (:func:`received`); sent again under the default handler, it
    killed a process that was ending with exit 2 (a slow exit after a signal in a gc callback)."""
    global _redeliver_on
    with _redeliver_lock:
        _redeliver_on = False


def received() -> str | None:
    """The first signal this command received (``SIGTERM``), None when none came."""
    return _received


def handled() -> None:
    """The command has answered the signal as it means to (``station`` ends its session between
    motors with exit 0): it no longer counts as received."""
    global _received
    _received = None


def raise_if_received(during: str | None = None) -> None:
    """Raise :class:`Interrupted` if a signal came and was not raised where it came (a finalizer
    swallowed it); outside :func:`shielded` only. Call it before a step that writes."""
    if _received is not None and _depth == 0:
        raise Interrupted(_received, during)


#: the functions inside which an exception raised now does not reach the command as itself: a
#: ``__del__`` prints and drops it; a ``__set_name__`` (a class being made: a dataclass's fields
#: while a module is imported) Python 3.11 wraps in ``RuntimeError("Error calling __set_name__ ...")``,
#: which no handler takes for an interruption (a SIGHUP while ``run`` started ended it with exit 1)
_NOT_RAISED_IN = ("__del__", "__set_name__")


def _unraisable(frame: FrameType | None) -> bool:
    """Whether the interrupted code runs where an exception does not reach the command as itself:
    a ``__del__``, a garbage-collector callback (JAX registers one: printed and dropped) or a
    ``__set_name__`` (:data:`_NOT_RAISED_IN`)."""
    callbacks = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    for _ in range(64):
        if frame is None:
            return False
        if frame.f_code.co_name in _NOT_RAISED_IN or frame.f_code in callbacks:
            return True
        frame = frame.f_back
    return False


def deliver(signal_name: str, frame: FrameType | None = None) -> None:
    """Raise :class:`Interrupted` now, or at the end of the enclosing :func:`shielded` block, or
    (inside a finalizer, where it would be lost) once the signal comes again a moment later."""
    global _pending, _received
    signum = signal.Signals[signal_name]
    _handled[signum] = _handled.get(signum, 0) + 1
    _received = _received or signal_name
    if _depth:
        _pending = _pending or signal_name
        return
    if _unraisable(frame) or _in_import_machinery(frame):
        _redeliver(signum)
        return
    raise Interrupted(signal_name)


def _in_import_machinery(frame: FrameType | None) -> bool:
    """Whether the interrupted code is importlib's own (a lazy import in progress): an exception
    raised between its ``_imp.acquire_lock()`` and the ``try`` that releases it left the import
    lock held, and the next import in any thread waited for ever (a SIGTERM while ``run`` started:
    its spool flush thread and the cycle both stuck). Raised a moment later, in the module's own
    code or after the import, it unwinds through importlib's ``finally`` blocks."""
    return frame is not None and frame.f_code.co_filename.startswith("<frozen importlib")


def _redeliver(signum: int) -> None:
    def send() -> None:
        with _redeliver_lock:
            if _redeliver_on:
                os.kill(os.getpid(), signum)

    timer = threading.Timer(REDELIVER_S, send)
    timer.daemon = True
    timer.start()


@contextlib.contextmanager
def dropped_redelivered() -> Iterator[None]:
    """While the block runs, an :class:`Interrupted` that Python drops (raised where
    :func:`_unraisable` did not see a finalizer: a weakref callback, a generator closed by the
    collector) is not printed as "Exception ignored ... Traceback", and its signal comes again a
    moment later, where it can stop the command."""
    previous = sys.unraisablehook

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if isinstance(unraisable.exc_value, Interrupted):
            _redeliver(signal.Signals[unraisable.exc_value.signal_name])
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """Hold signals off for the block; one that arrived meanwhile is raised after it."""
    global _depth, _pending
    with _depth_lock:
        _depth += 1
    try:
        yield
    finally:
        with _depth_lock:
            _depth -= 1
    if _depth == 0 and _pending is not None:
        name, _pending = _pending, None
        raise Interrupted(name)


@contextlib.contextmanager
def emergency(action: Callable[[], None]) -> Iterator[None]:
    """Register ``action`` (bounded, best effort: the dyno's safe state) for the block: the
    watchdog runs it before it ends a process whose main thread does not answer a signal."""
    _emergency.append(action)
    try:
        yield
    finally:
        _emergency.remove(action)


def _end_now(signum: int, grace_s: float) -> None:
    for action in list(reversed(_emergency)):
        with contextlib.suppress(BaseException):  # the process ends anyway; each action is best effort
            action()
    name = signal.Signals(signum).name
    try:
        sys.stderr.write(f"error: interrupted by {name}; the command did not answer it within {grace_s:g} s (blocked "
                         "in a system call) and was ended\n")
        sys.stderr.flush()
    except Exception:  # noqa: BLE001 - a closed stderr
        pass
    os._exit(Interrupted.exit_code)


@contextlib.contextmanager
def watchdog(grace_s: float | None = None) -> Iterator[None]:
    """End the process (exit 2, after the emergency actions) when a signal's handler has not run
    ``grace_s`` (default :data:`WATCHDOG_GRACE_S`) after the signal came: the main thread is stuck
    in C code that repeats its system call. Main thread only (the wake-up descriptor is the main
    thread's)."""
    grace_s = WATCHDOG_GRACE_S if grace_s is None else grace_s
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    stop = threading.Event()

    def watch() -> None:
        seen: dict[int, int] = {}
        while not stop.is_set():
            try:
                data = os.read(read_fd, 64)
            except OSError:
                return
            if not data or stop.is_set():
                return
            for signum in data:
                seen[signum] = seen.get(signum, 0) + 1
            deadline = time.monotonic() + grace_s
            while any(_handled.get(s, 0) < n for s, n in seen.items()):
                if stop.wait(0.05):
                    return
                if time.monotonic() >= deadline:
                    _end_now(next(s for s, n in seen.items() if _handled.get(s, 0) < n), grace_s)

    thread = threading.Thread(target=watch, name="signal-watchdog", daemon=True)
    baseline = dict(_handled)
    _handled.clear()
    thread.start()
    try:
        yield
    finally:
        stop.set()
        signal.set_wakeup_fd(previous)
        os.close(write_fd)  # the reader sees end of file
        thread.join(1.0)
        os.close(read_fd)
        _handled.clear()
        _handled.update(baseline)
