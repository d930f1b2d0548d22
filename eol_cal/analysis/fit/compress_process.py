"""A second process that compresses blocks of motors for :func:`~eol_cal.analysis.fit.batch.fit_many`.

The compression's threads share one GIL: each holds it between its numpy kernels, so two of them
(and the thread that dispatches the solve and unpacks its results) take turns at it. A process of
its own has its own GIL: ``fit_many``'s worker threads hand it blocks of segments and wait (the GIL
released), while the calling thread compresses the other blocks and runs the solve.

The child imports numpy and the compression only (no JAX). It is started on first use, from a
batch of :data:`PROCESS_START_MOTORS` motors on, kept for the process' life (closed at exit) and
used from :data:`PROCESS_MIN_MOTORS` on once it runs.
The segments' arrays reach it through shared buffers, one a request in flight (an anonymous
``memfd``, its descriptor passed over a socket pair: no name that a crash could leave behind), the
summaries (a few kB a motor) come back pickled. What a user sees: a second ``python`` process
(``-c ... serve()``, 35-55 MB) from the first large batch until this process ends; it ignores
Ctrl-C (it ends when this process closes it or is gone). Linux only; where it cannot start (or
dies), the worker threads compress in this process, as without it. An error in the child is
raised here as it was raised there (``fit_many`` names the capture).
"""

from __future__ import annotations

import atexit
import contextlib
import mmap
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence
from typing import Any
from multiprocessing.connection import Connection

import numpy as np

from eol_cal.analysis.fit.compression import SegmentArrays, Summaries, summarise_segments
from eol_cal.analysis.fit.model import FitSpec

#: ``fit_many`` starts the child for a batch of this many motors or more: its start (a Python, numpy
#: and the compression imported: 0.10 s CPU, 0.12 s wall; its buffers' first pages) made a fresh
#: process's first batch of 512 bench captures 3-11 % slower (0.39-0.42 s against 0.38), one of 1000
#: 7-16 % faster (0.66-0.67 s against 0.72-0.79; quiet, docs/benchmarks.md)
PROCESS_START_MOTORS = 1000
#: once the child runs, ``fit_many`` hands it blocks from this many motors on (a batch of 64 bench
#: captures: 57 ms against 64 ms without it; of 32: 35 against 33 ms; median of 5, quiet)
PROCESS_MIN_MOTORS = 64
#: requests in flight at most (a shared buffer each): fit_many's worker threads that feed the child
SLOTS = 2
#: one array's place in the shared buffer: (first double, length)
_Span = tuple[int, int]


class CompressProcess:
    """The child process and its shared buffers; :meth:`summarise` is
    :func:`~eol_cal.analysis.fit.compression.summarise_segments` run there."""

    def __init__(self) -> None:
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        # BLAS's own threads would only spin beside this process's: the child's products are small
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        # the child imports this checkout's eol_cal, whatever the caller's working directory
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", "from eol_cal.analysis.fit.compress_process import serve; serve()",
                 str(theirs.fileno())], pass_fds=[theirs.fileno()], env=env, stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self._sock = ours
        self._conn = Connection(os.dup(ours.fileno()))
        # requests go out one at a time (a buffer's descriptor right behind its message) and the child
        # answers them in order: a request's number says which answer is its
        self._send = threading.Lock()
        self._answers = threading.Condition()
        self._sent = self._received = 0
        self._receiving = False
        self._got: dict[int, tuple[str, Any]] = {}
        self._bufs: list[np.ndarray | None] = [None] * SLOTS
        self._free: queue.SimpleQueue[int] = queue.SimpleQueue()
        for slot in range(SLOTS):
            self._free.put(slot)
        self._ready = False
        self._ready_lock = threading.Lock()
        self._parent = os.getpid()
        self.broken = False

    def summarise(self, todo: Sequence[SegmentArrays], spec: FitSpec) -> Summaries:
        """The segments' summaries computed in the child (here, if it is gone: :attr:`broken`). Up
        to :data:`SLOTS` callers at once: one block is copied in and sent while the child
        compresses another, so the child does not wait for this process's GIL between blocks."""
        if not self.ready():  # still starting: this block here, the caller does not wait for it
            return summarise_segments(todo, spec)
        slot = self._free.get()
        try:
            if not self.broken:
                try:
                    layout = self._copy_in(slot, todo)
                    with self._send:
                        self._conn.send(("work", slot, layout, spec))
                        ticket = self._sent
                        self._sent += 1
                    answer = self._answer(ticket)
                except (OSError, EOFError):  # the child is gone: this and every later block here
                    self.broken = True
                    with self._answers:
                        self._answers.notify_all()
                else:
                    kind, got = answer
                    if kind == "error":
                        got.add_note(f"(raised in the compression process, pid {self._proc.pid})")
                        raise got
                    return got
        finally:
            self._free.put(slot)
        return summarise_segments(todo, spec)

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._proc.pid

    def ready(self) -> bool:
        """Whether the child has started (its imports done: it said so); False while it starts."""
        with self._ready_lock:
            if not self._ready and not self.broken:
                try:
                    if self._conn.poll(0):
                        self._ready = self._conn.recv() == "ready"
                        self.broken = not self._ready
                except (OSError, EOFError):
                    self.broken = True
            return self._ready

    def _answer(self, ticket: int) -> tuple[str, Any]:
        """The child's answer to request ``ticket``: whichever caller is free reads the next answer
        off the socket (the GIL released while it waits) and hands it to its caller."""
        with self._answers:
            while ticket not in self._got:
                if self.broken:
                    raise EOFError("the compression process is gone")
                if self._receiving:
                    self._answers.wait()
                    continue
                self._receiving = True
                self._answers.release()
                try:
                    answer = self._conn.recv()
                finally:
                    self._answers.acquire()
                    self._receiving = False
                    self._answers.notify_all()
                self._got[self._received] = answer
                self._received += 1
            return self._got.pop(ticket)

    def _copy_in(self, slot: int, todo: Sequence[SegmentArrays]) -> list[tuple[int, list[_Span | None]]]:
        """The segments' arrays copied into buffer ``slot`` (grown first if they do not fit): per
        segment, its pole pairs and each array's span (None for a missing ``kt * i_q``)."""
        need = sum(len(a) for arrays in todo for a in arrays[:4] if a is not None)
        buf = self._bufs[slot]
        if buf is None or buf.size < need:
            buf = self._bufs[slot] = self._grow(slot, need)
        layout, o = [], 0
        for *arrays, pole_pairs in todo:
            spans: list[_Span | None] = []
            for a in arrays:
                if a is None:
                    spans.append(None)
                    continue
                n = len(a)
                buf[o : o + n] = a  # float64, as the compression's np.asarray(a, dtype=float)
                spans.append((o, n))
                o += n
            layout.append((pole_pairs, spans))
        return layout

    def _grow(self, slot: int, doubles: int) -> np.ndarray:
        """A new shared buffer of ``doubles`` (with a quarter to spare) for ``slot``, handed to the child."""
        size = 8 * (doubles + doubles // 4)
        fd = os.memfd_create("eol-cal-compress")
        try:
            os.ftruncate(fd, size)
            with self._send:
                self._conn.send(("buffer", slot, size))
                socket.send_fds(self._sock, [b"b"], [fd])
            return np.frombuffer(mmap.mmap(fd, size), dtype=np.float64)
        finally:
            os.close(fd)  # the mapping (and the child's) keeps the memory

    def close(self) -> None:
        """Stop the child and wait for it (killed after 5 s). Nothing in a forked copy of this
        process: the child is its parent's."""
        if os.getpid() != self._parent:
            return
        with contextlib.suppress(OSError):  # the child gone already
            self._conn.send(None)
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._conn.close()
        self._sock.close()
        self.broken = True


_CHILD: CompressProcess | None = None
_START = threading.Lock()


def compress_process() -> CompressProcess | None:
    """This process's compression child, started on the first call; None where it cannot start
    (not Linux, no ``memfd_create``, the executable cannot be run) or it has died."""
    global _CHILD
    with _START:
        # a forked copy of this process does not share its parent's child (the socket is the parent's)
        if _CHILD is None or _CHILD._parent != os.getpid():
            if not hasattr(os, "memfd_create") or not hasattr(socket, "send_fds"):
                return None
            try:
                _CHILD = CompressProcess()
            except OSError:
                return None
            atexit.register(_CHILD.close)
        return None if _CHILD.broken else _CHILD


def running() -> CompressProcess | None:
    """This process's compression child if one was started (and is this process's), else None."""
    child = _CHILD
    return child if child is not None and child._parent == os.getpid() else None


def serve() -> None:
    """The child's loop: a shared buffer, then blocks of segments to summarise, until told to stop
    (or the parent is gone)."""
    # Ctrl-C reaches the terminal's whole process group: the parent decides, and closes this
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sock = socket.socket(fileno=int(sys.argv[1]))
    conn = Connection(os.dup(sock.fileno()))
    bufs = [np.empty(0)] * SLOTS
    conn.send("ready")
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        if msg[0] == "buffer":
            _, fds, _, _ = socket.recv_fds(sock, 1, 1)
            bufs[msg[1]] = np.frombuffer(mmap.mmap(fds[0], msg[2]), dtype=np.float64)
            os.close(fds[0])
            continue
        _, slot, layout, spec = msg
        buf = bufs[slot]
        try:
            todo = [(*(None if s is None else buf[s[0] : s[0] + s[1]] for s in spans), pole_pairs)
                    for pole_pairs, spans in layout]
            reply: tuple[str, object] = ("ok", summarise_segments(todo, spec))
        except Exception as e:  # noqa: BLE001 - raised in the parent
            reply = ("error", e)
        try:
            conn.send(reply)
        except Exception as e:  # noqa: BLE001 - an error that does not pickle: its text
            conn.send(("error", RuntimeError(f"{type(reply[1]).__name__} in the compression process: {reply[1]} ({e})")))
