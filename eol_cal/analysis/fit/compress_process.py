"""A second process that compresses blocks of motors for :func:`~eol_cal.analysis.fit.batch.fit_many`.

The compression's threads share one GIL: each holds it between its numpy kernels, so two of them
(and the thread that dispatches the solve and unpacks its results) take turns at it. A process of
its own has its own GIL: ``fit_many``'s worker thread hands it a block's segments and waits (the GIL
released), while the calling thread compresses the other blocks and runs the solve.

The child imports numpy and the compression only (no JAX). It is started on first use, from a
batch of :data:`PROCESS_MIN_MOTORS` motors on, and kept for the process' life (closed at exit).
The segments' arrays reach it through one shared buffer (an anonymous ``memfd``, its descriptor
passed over the socket: no name that a crash could leave behind), the summaries (a few kB a
motor) come back pickled. Linux only; where it cannot start (or dies), the worker thread
compresses in this process, as without it. An error in the child is raised here as it was
raised there (``fit_many`` names the capture).
"""

from __future__ import annotations

import atexit
import contextlib
import mmap
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection

import numpy as np

from eol_cal.analysis.fit.compression import SegmentArrays, _Summaries, summarise_segments
from eol_cal.analysis.fit.model import FitSpec

#: ``fit_many`` compresses in the child from this many motors on: below, the child's start
#: (a Python and numpy, ~0.2 s CPU, once a process) costs more than it saves
PROCESS_MIN_MOTORS = 256
#: one array's place in the shared buffer: (first double, length)
_Span = tuple[int, int]


class CompressProcess:
    """The child process and its shared buffer; :meth:`summarise` is
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
        self._lock = threading.Lock()
        self._buf: np.ndarray | None = None
        self.pid = os.getpid()
        self.broken = False

    def summarise(self, todo: Sequence[SegmentArrays], spec: FitSpec) -> _Summaries:
        """The segments' summaries computed in the child (here, if it is gone: :attr:`broken`)."""
        with self._lock:
            if not self.broken:
                try:
                    layout = self._copy_in(todo)
                    self._conn.send(("work", layout, spec))
                    kind, got = self._conn.recv()
                except (OSError, EOFError):  # the child is gone: this and every later block here
                    self.broken = True
                else:
                    if kind == "error":
                        raise got
                    return got
        return summarise_segments(todo, spec)

    def _copy_in(self, todo: Sequence[SegmentArrays]) -> list[tuple[int, list[_Span | None]]]:
        """The segments' arrays copied into the shared buffer (grown first if they do not fit):
        per segment, its pole pairs and each array's span (None for a missing ``kt * i_q``)."""
        need = sum(len(a) for arrays in todo for a in arrays[:4] if a is not None)
        if self._buf is None or self._buf.size < need:
            self._grow(need)
        assert self._buf is not None
        layout, o = [], 0
        for *arrays, pole_pairs in todo:
            spans: list[_Span | None] = []
            for a in arrays:
                if a is None:
                    spans.append(None)
                    continue
                n = len(a)
                self._buf[o : o + n] = a  # float64, as the compression's np.asarray(a, dtype=float)
                spans.append((o, n))
                o += n
            layout.append((pole_pairs, spans))
        return layout

    def _grow(self, doubles: int) -> None:
        """A new shared buffer of ``doubles`` (with a quarter to spare), handed to the child."""
        size = 8 * (doubles + doubles // 4)
        fd = os.memfd_create("eol-cal-compress")
        try:
            os.ftruncate(fd, size)
            self._conn.send(("buffer", size))
            socket.send_fds(self._sock, [b"b"], [fd])
            self._buf = np.frombuffer(mmap.mmap(fd, size), dtype=np.float64)
        finally:
            os.close(fd)  # the mapping (and the child's) keeps the memory

    def close(self) -> None:
        """Stop the child and wait for it (killed after 5 s)."""
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
        if _CHILD is None or _CHILD.pid != os.getpid():
            if not hasattr(os, "memfd_create") or not hasattr(socket, "send_fds"):
                return None
            try:
                _CHILD = CompressProcess()
            except OSError:
                return None
            atexit.register(_CHILD.close)
        return None if _CHILD.broken else _CHILD


def serve() -> None:
    """The child's loop: a shared buffer, then blocks of segments to summarise, until told to stop
    (or the parent is gone)."""
    sock = socket.socket(fileno=int(sys.argv[1]))
    conn = Connection(os.dup(sock.fileno()))
    buf = np.empty(0)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        if msg[0] == "buffer":
            _, fds, _, _ = socket.recv_fds(sock, 1, 1)
            buf = np.frombuffer(mmap.mmap(fds[0], msg[1]), dtype=np.float64)
            os.close(fds[0])
            continue
        _, layout, spec = msg
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
