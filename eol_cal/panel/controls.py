"""The operator's actions from the panel, checked as the terminal loop checks them, handed to the
station's main thread.

The cycle runs in the main thread, as in the terminal loop, so a signal does there what it does in
the terminal (:mod:`eol_cal.infra.interrupts`). The page's scan puts a serial on a queue that the main
thread waits on; its stop button sends the main thread SIGINT, the terminal's Ctrl-C: the cycle
unwinds through the dyno's safe state and records the run (an error), and the panel's session then
goes on with the next motor (the button is not a signal to end the session).
"""

from __future__ import annotations

import queue
import signal
import threading
from dataclasses import dataclass

from eol_cal.errors import InputError
from eol_cal.panel.state import PanelState
from eol_cal.station.operator_session import operator_name, scanned_serial

#: seconds the main thread waits on the queue at a time (a signal is answered between waits)
POLL_S = 0.2


class Refused(Exception):
    """An action the panel refuses, with the reason for the operator and its HTTP status."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass(frozen=True)
class Scan:
    """A motor to run: its serial and the operator signed in when it was scanned."""

    serial: str
    operator: str


class Controls:
    """Sign-in, scan, stop and end, from the web server's threads; :meth:`next_scan` in the main thread."""

    def __init__(self, state: PanelState) -> None:
        self.state = state
        self._queue: queue.Queue[Scan | None] = queue.Queue(maxsize=1)
        self._lock = threading.Lock()
        self._stop_pressed = False
        self._main = threading.main_thread().ident

    def _operator(self) -> str:
        name = self.state.get("operator")
        if name is None:
            raise Refused(403, "sign in first: no action without an operator")
        return str(name)

    def sign_in(self, text: str) -> str:
        """The operator, checked as the terminal loop checks a typed name; refused while a motor runs."""
        try:
            name = operator_name(text)
        except InputError as exc:
            # one text for the page's state and the request's answer: the page shows whichever of
            # the two comes last (its event stream and its request race)
            text = f"not an operator name: {exc.reason}"
            self.state.message("error", text)
            raise Refused(400, text) from None
        with self._lock:
            if self.state.get("phase") != "idle":
                raise Refused(409, "a motor is running: sign in once it is done")
            self.state.update(operator=name, message={"level": "info", "text": f"operator {name} signed in"})
        return name

    def sign_out(self) -> None:
        with self._lock:
            if self.state.get("phase") != "idle":
                raise Refused(409, "a motor is running: sign out once it is done")
            self.state.update(operator=None, message={"level": "info", "text": "signed out"})

    def scan(self, line: str) -> str:
        """A scanned line: the serial (the terminal loop's check), queued for the main thread."""
        operator = self._operator()
        try:
            serial = scanned_serial(line)
        except InputError as exc:
            text = f"not a serial: {exc.reason}; scan again"  # the state's and the answer's (sign_in says why)
            self.state.message("error", text)
            raise Refused(400, text) from None
        with self._lock:
            if self.state.get("ended"):
                raise Refused(409, "the session has ended")
            if self.state.get("phase") != "idle":
                raise Refused(409, "a motor is running: scan the next one when it is done")
            try:
                self._queue.put_nowait(Scan(serial, operator))
            except queue.Full:
                raise Refused(409, "a motor is already waiting to start") from None
            self.state.update(phase="starting", serial=serial, message=None)
        return serial

    def stop(self) -> None:
        """The stop button: SIGINT to the main thread while a motor runs (its dyno to the safe state)."""
        self._operator()
        with self._lock:
            if self.state.get("phase") != "running":
                raise Refused(409, "no motor is running")
            self._stop_pressed = True
            self.state.message("info", "stop: the dyno is being brought to its safe state")
            signal.pthread_kill(self._main, signal.SIGINT)  # type: ignore[arg-type]

    def end(self) -> None:
        """End the session (as an empty line at the terminal's prompt)."""
        self._operator()
        with self._lock:
            if self.state.get("phase") != "idle":
                raise Refused(409, "a motor is running: end the session once it is done")
            self.state.update(ended=True, message={"level": "info", "text": "the session ends"})
            self._queue.put(None)

    # ------------------------------------------------------------------ the main thread
    def next_scan(self) -> Scan | None:
        """The next motor (None: the session ends); waits in short turns so a signal is answered."""
        while True:
            try:
                return self._queue.get(timeout=POLL_S)
            except queue.Empty:
                continue

    def started(self, scan: Scan) -> None:
        """The main thread starts a motor's cycle: the stop button works until the panel shows it done."""
        with self._lock:
            self._stop_pressed = False
            self.state.begin(scan.serial)

    def took_stop(self) -> bool:
        """Whether the interruption being handled was the stop button's (it is taken: once)."""
        with self._lock:
            pressed, self._stop_pressed = self._stop_pressed, False
            return pressed
