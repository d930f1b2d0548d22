"""A simulated ECU and a tester on one python-can ``virtual`` channel, for the tests and the
benchmarks (``from eol_cal.sim.virtual_rig import virtual_rig``).
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterator

import can

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import ClientTiming, hmac_seed_to_key
from eol_cal.ecu.flash import NorFlash
from eol_cal.ecu.sim_ecu import EcuSimulator, Faults, SimConfig
from eol_cal.ecu.transport import IsoTpTiming, private_channel_name
from eol_cal.firmware.example import example_block

FAST_ISOTP = IsoTpTiming(n_bs_ms=500, n_cr_ms=500)
__all__ = ["FAST_CLIENT", "FAST_ISOTP", "FAST_SIM", "Rig", "Sniffer", "example_block", "virtual_rig"]

FAST_CLIENT = ClientTiming(p2_s=0.5, p2_star_s=1.0, retries=3, tester_present_s=2.0, isotp=FAST_ISOTP)
"""Short timeouts for in-process tests: a dead ECU is detected in about two seconds. P2 and N_Bs
are the production client's 0.5 s: with 0.15 s a CPU hog (load 8 on 2 cores) starved the
simulator's thread past them and failed flashes that were not about timing."""

FAST_SIM = SimConfig(isotp_timing=FAST_ISOTP, p2_star_s=0.8)
"""The simulator for :data:`FAST_CLIENT`: it announces P2* 0.8 s and repeats NRC 0x78 every
0.4 s, inside the client's P2* of 1 s (a tester waits the server's P2* and a margin). With the
contract's 5 s it repeated 0x78 only every 2.5 s, so an erase held up for more than a second
(the flash file's fsync on a busy CI disk) timed the client out and failed flashes in CI."""



@dataclass
class Sniffer:
    """Every frame seen on the channel, by a third bus object (a bus monitor)."""

    bus: can.BusABC
    frames: list[can.Message] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.02)
            if msg is not None:
                self.frames.append(msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


@dataclass
class Rig:
    """An ECU simulator and a tester bus on one virtual channel."""

    channel: str
    flash_path: Path | None
    sim: EcuSimulator
    tester: can.BusABC
    sniffer: Sniffer | None
    seed_to_key = staticmethod(hmac_seed_to_key(P.DEV_SECRET))

    def restart(self, faults: Faults | None = None, config: SimConfig | None = None) -> EcuSimulator:
        """Power the ECU off and on again: a new simulator on the same flash file."""
        self.sim.stop()
        self.sim.bus.shutdown()
        bus = can.Bus(interface="virtual", channel=self.channel)
        self.sim = EcuSimulator(bus, NorFlash(self.flash_path), config or self.sim.config, faults).start()
        return self.sim


@contextlib.contextmanager
def virtual_rig(flash_path: str | Path | None = None, *, config: SimConfig | None = None,
                faults: Faults | None = None, sniff: bool = False) -> Iterator[Rig]:
    """Start an ECU simulator on a fresh virtual channel; yield the rig; stop everything."""
    channel = private_channel_name()
    sniffer = Sniffer(can.Bus(interface="virtual", channel=channel)) if sniff else None
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    tester = can.Bus(interface="virtual", channel=channel)
    path = Path(flash_path) if flash_path is not None else None
    sim = EcuSimulator(ecu_bus, NorFlash(path), config or FAST_SIM, faults).start()
    rig = Rig(channel, path, sim, tester, sniffer)
    try:
        yield rig
    finally:
        rig.sim.stop()
        rig.sim.bus.shutdown()
        tester.shutdown()
        if sniffer is not None:
            sniffer.close()
