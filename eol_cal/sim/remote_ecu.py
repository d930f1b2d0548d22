"""Serve the ECU simulator to other processes over python-can-remote (WebSocket, loopback).

The simulator sits on a private ``virtual`` channel; ``can_remote.RemoteServer`` gives every
connecting client its own bus on that channel, so a tester in another process reaches the
ECU with ``--interface remote --channel ws://127.0.0.1:PORT/``.

:func:`serve_remote` serves from this process (``eol-cal ecu-sim``); :func:`spawn_remote` from a
child process of its own, as a real ECU answers from a device of its own: a tester working in
this process then cannot starve the server of the interpreter. python-can-remote's client waits a
fixed 5 s for the server's answer to its bus request; beside a CPU hog at load 15-22 on 2 cores
a server thread in the tester's process (the dyno simulator and the cycle busy in it) missed it.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

if __name__ == "__main__":
    # The child (spawn_remote) writes no MDF4: python-can's MF4 logger, which `import can` loads,
    # would import asammdf and pandas (~0.45 CPU s of each child's start); it takes their absence.
    sys.modules.setdefault("asammdf", None)  # type: ignore[arg-type]

import can
from can_remote import RemoteServer

from eol_cal.ecu.flash import NorFlash
from eol_cal.ecu.sim_ecu import EcuSimulator, Faults, SimConfig
from eol_cal.ecu.transport import private_channel_name


@dataclass
class RemoteEcu:
    """A running simulator behind a python-can-remote server; :meth:`close` stops both."""

    sim: EcuSimulator
    server: RemoteServer
    thread: threading.Thread
    channel: str = ""
    """The private virtual channel the simulator and the server share."""

    def replace(self, flash_path: str | Path, config: SimConfig | None = None, faults: Faults | None = None) -> None:
        """Put another ECU on the same server (the next motor on a line): the simulator stops and
        a new one starts on ``flash_path``; testers keep the same URL."""
        self.sim.stop()
        self.sim.bus.shutdown()
        self.sim = _start_sim(self.channel, flash_path, config, faults)

    @property
    def url(self) -> str:
        """The ``--channel`` a tester passes with ``--interface remote``."""
        host, port = self.server.server_address[:2]
        return f"ws://{host}:{port}/"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(2.0)
        self.sim.stop()
        self.sim.bus.shutdown()


def serve_remote(flash_path: str | Path, *, host: str = "127.0.0.1", port: int = 0,
                 config: SimConfig | None = None, faults: Faults | None = None) -> RemoteEcu:
    """Start a simulator on ``flash_path`` and a python-can-remote server on ``host:port``.

    Parameters
    ----------
    port : int
        TCP port; 0 picks a free one (read it back from :attr:`RemoteEcu.url`).
    """
    # can_remote logs every frame at INFO/DEBUG; keep it to warnings.
    logging.getLogger("can_remote").setLevel(logging.WARNING)
    channel = private_channel_name("ecu-sim")
    sim = _start_sim(channel, flash_path, config, faults)
    server = RemoteServer(host, port, interface="virtual", channel=channel)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1},
                              name="can-remote", daemon=True)
    thread.start()
    return RemoteEcu(sim, server, thread, channel)


def _start_sim(channel: str, flash_path: str | Path, config: SimConfig | None, faults: Faults | None) -> EcuSimulator:
    return EcuSimulator(can.Bus(interface="virtual", channel=channel), NorFlash(flash_path), config, faults).start()


@dataclass
class RemoteEcuProcess:
    """A simulator and its python-can-remote server in a child process (:func:`spawn_remote`);
    the same calls as :class:`RemoteEcu`. The child ends with :meth:`close`, or by itself when
    this process goes (its command pipe closes)."""

    process: subprocess.Popen
    _url: str | None = field(default=None, repr=False)

    @property
    def url(self) -> str:
        """The ``--channel`` a tester passes with ``--interface remote`` (waits for the child to listen)."""
        if self._url is None:
            self._url = str(self._reply())
        return self._url

    def replace(self, flash_path: str | Path, config: SimConfig | None = None, faults: Faults | None = None) -> None:
        """As :meth:`RemoteEcu.replace`: the next motor's ECU behind the same URL."""
        self.url  # noqa: B018 - the child's first reply is its URL: read it before the answer to this
        self._send(("replace", (str(flash_path), config, faults)))
        self._reply()

    def close(self) -> None:
        """Stop the server and the simulator and wait for the child (killed after 10 s); twice is once."""
        if self.process.poll() is None:
            try:
                self._send(("close", ()))
                self.process.wait(10.0)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()
                self.process.wait()
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                pipe.close()

    def _send(self, command: tuple[str, tuple]) -> None:
        assert self.process.stdin is not None  # spawn_remote opens both pipes
        pickle.dump(command, self.process.stdin)
        self.process.stdin.flush()

    def _reply(self) -> Any:
        assert self.process.stdout is not None  # spawn_remote opens both pipes
        try:
            status, value = pickle.load(self.process.stdout)
        except EOFError:
            raise RuntimeError(f"the ECU simulator's process ended (exit code {self.process.wait()}); "
                               "its error is on standard error") from None
        if status != "ok":
            raise RuntimeError(f"ECU simulator process: {value}")
        return value


def spawn_remote(flash_path: str | Path, *, host: str = "127.0.0.1", port: int = 0,
                 config: SimConfig | None = None, faults: Faults | None = None) -> RemoteEcuProcess:
    """:func:`serve_remote` in a child process (``python -m eol_cal.sim.remote_ecu``).

    Returns at once: the child imports and binds while the caller goes on; :attr:`RemoteEcuProcess.url`
    waits for it. Commands and answers travel pickled over the child's standard input and output:
    it is this package's own process on pipes no one else holds.
    """
    package_root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")])))
    process = subprocess.Popen([sys.executable, "-m", "eol_cal.sim.remote_ecu"], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, env=env)
    ecu = RemoteEcuProcess(process)
    try:
        ecu._send(("start", (str(flash_path), host, port, config, faults)))
    except OSError:
        ecu.close()
        raise
    return ecu


def _answer(out: IO[bytes], status: str, value: object) -> None:
    pickle.dump((status, value), out)
    out.flush()


def _child(inp: IO[bytes], out: IO[bytes]) -> None:
    """The child of :func:`spawn_remote`: start, then replace or close as the parent says."""
    _, (flash_path, host, port, config, faults) = pickle.load(inp)
    try:
        ecu = serve_remote(flash_path, host=host, port=port, config=config, faults=faults)
    except Exception as exc:  # noqa: BLE001 - the parent raises it with its words
        _answer(out, "error", f"cannot start on {flash_path} ({host}:{port}): {exc}")
        return
    try:
        _answer(out, "ok", ecu.url)
        while True:
            try:
                command, args = pickle.load(inp)
            except EOFError:  # the parent is gone
                return
            if command == "close":
                return
            try:
                ecu.replace(*args)
            except Exception as exc:  # noqa: BLE001 - the parent raises it with its words
                _answer(out, "error", f"cannot replace the ECU with {args[0]}: {exc}")
            else:
                _answer(out, "ok", None)
    finally:
        ecu.close()


if __name__ == "__main__":
    # the answers go on a descriptor of their own: a stray print on standard output lands on standard error
    _out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    _child(sys.stdin.buffer, _out)
