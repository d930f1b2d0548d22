"""Serve the ECU simulator to other processes over python-can-remote (WebSocket, loopback).

The simulator sits on a private ``virtual`` channel; ``can_remote.RemoteServer`` gives every
connecting client its own bus on that channel, so a tester in another process reaches the
ECU with ``--interface remote --channel ws://127.0.0.1:PORT/``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path

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
