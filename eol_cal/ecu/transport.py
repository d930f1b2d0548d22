"""CAN bus and ISO-TP plumbing shared by the flashing client and the ECU simulator.

python-can opens the bus (any interface, or python-can's own config file), can-isotp carries
UDS messages with the contract's addressing and 0xCC padding, and :class:`FaultyBus` injects
dropped and delayed frames for the reliability tests.
"""

from __future__ import annotations

import itertools
import os
import random
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

import can
import isotp

from eol_cal.ecu import protocol as P
from eol_cal.errors import InputError


@dataclass(frozen=True)
class IsoTpTiming:
    """ISO 15765-2 network-layer timeouts.

    Attributes
    ----------
    n_bs_ms : int
        Sender's wait for a flow-control frame, ms (ISO default 1000).
    n_cr_ms : int
        Receiver's wait for the next consecutive frame, ms (ISO default 1000).
    blocksize : int
        BS this side announces in its flow-control frames (contract: 0, no further FC).
    stmin_ms : int
        STmin this side announces, ms (contract: 0).
    """

    n_bs_ms: int = 1000
    n_cr_ms: int = 1000
    blocksize: int = P.FC_BLOCK_SIZE
    stmin_ms: int = P.FC_STMIN


def isotp_params(*, blocking_send: bool, timing: IsoTpTiming = IsoTpTiming()) -> dict[str, Any]:
    """can-isotp parameters for contract section 3: 8-byte frames padded with 0xCC, BS = STmin = 0 by default.

    Parameters
    ----------
    blocking_send : bool
        True for the tester: ``send`` returns only when the last consecutive frame is out, so
        udsoncan's P2 timer starts after the request, not while it is still being sent.
    timing : IsoTpTiming
        N_Bs / N_Cr timeouts.
    """
    return {
        "stmin": int(timing.stmin_ms),
        "blocksize": int(timing.blocksize),
        "tx_padding": P.PADDING,
        "tx_data_length": P.FRAME_BYTES,
        "tx_data_min_length": P.FRAME_BYTES,
        "max_frame_size": 4095,
        "can_fd": False,
        "blocking_send": blocking_send,
        "rx_flowcontrol_timeout": int(timing.n_bs_ms),
        "rx_consecutive_frame_timeout": int(timing.n_cr_ms),
    }


def make_stack(bus: can.BusABC, *, tx_id: int, rx_id: int, blocking_send: bool,
               timing: IsoTpTiming = IsoTpTiming()) -> isotp.CanStack:
    """An unstarted can-isotp stack on ``bus`` with normal 11-bit addressing.

    The stack reads the bus directly (``bus.recv``), so the bus must not be shared with another
    reader in the same process; use a second ``can.Bus`` on the channel to sniff.
    """
    address = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=tx_id, rxid=rx_id)
    return isotp.CanStack(bus, address=address, params=isotp_params(blocking_send=blocking_send, timing=timing),
                          read_timeout=0.02)


def open_bus(interface: str | None, channel: str | None, bitrate: int | None = None,
             can_config: str | None = None) -> can.BusABC:
    """Open a python-can bus from command-line style options.

    Parameters
    ----------
    interface, channel : str or None
        python-can interface name (``socketcan``, ``pcan``, ``vector``, ``virtual``, ``remote``...)
        and channel. Either may come from ``can_config`` instead.
    bitrate : int or None
        bit/s; left to the interface or config file when None.
    can_config : str or None
        python-can configuration file (``[default]`` section); command-line values win.

    Raises
    ------
    InputError
        The interface is unknown, the config file unreadable, or the bus cannot be opened.
    """
    overrides = {k: v for k, v in (("interface", interface), ("channel", channel), ("bitrate", bitrate))
                 if v is not None}
    if can_config is not None and not os.path.isfile(can_config):
        raise InputError(can_config, "can-config", "file not found")
    try:
        config = can.util.load_config(path=can_config, config=overrides) if can_config else overrides
    except (OSError, ValueError, can.CanInterfaceNotImplementedError) as exc:
        raise InputError(can_config, "can-config", str(exc)) from exc
    if not config.get("interface"):
        raise InputError(can_config, "interface", "no CAN interface given (--interface or --can-config)")
    if config.get("interface") == "udp_multicast":
        # Its frames leave through the network card; the project never uses it.
        raise InputError(can_config, "interface", "udp_multicast is not allowed; use virtual or remote")
    try:
        return can.Bus(ignore_config=True, **config)
    except (can.CanError, ValueError, OSError, ImportError, TypeError) as exc:
        raise InputError(can_config, "interface",
                         f"cannot open {config.get('interface')} channel {config.get('channel')!r}: {exc}") from exc


class FaultyBus(can.BusABC):
    """A bus wrapper that drops and delays frames with a seeded RNG (both directions).

    Delays hold the sender (frames keep their order, as on a real CAN controller's queue).

    Parameters
    ----------
    inner : can.BusABC
        The real bus.
    drop_rate : float
        Probability that a frame, sent or received, is lost.
    delay_rate : float
        Probability that a sent frame waits ``delay_s`` first.
    delay_s : float
        Delay, s.
    seed : int
        RNG seed.
    """

    def __init__(self, inner: can.BusABC, *, drop_rate: float = 0.0, delay_rate: float = 0.0,
                 delay_s: float = 0.0, seed: int = 0) -> None:
        self.inner = inner
        self.drop_rate = drop_rate
        self.delay_rate = delay_rate
        self.delay_s = delay_s
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self.dropped = 0
        self.delayed = 0
        super().__init__(channel=getattr(inner, "channel_info", "faulty"))
        self.channel_info = f"faulty({inner.channel_info})"

    def _draw(self) -> float:
        with self._lock:
            return self._rng.random()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._draw() < self.drop_rate:
            self.dropped += 1
            return
        if self.delay_rate and self._draw() < self.delay_rate:
            self.delayed += 1
            time.sleep(self.delay_s)
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        if msg is not None and self._draw() < self.drop_rate:
            self.dropped += 1
            return None, False
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


def private_channel_name(prefix: str = "ecu") -> str:
    """A python-can ``virtual`` channel name no other bus in this process uses by accident."""
    return f"{prefix}-{os.getpid()}-{next(_channel_counter)}-{uuid.uuid4().hex[:6]}"


_channel_counter = itertools.count()


def frame_bits(dlc: int = P.FRAME_BYTES, *, stuffing: bool = True) -> int:
    """Bits on the wire for one classic CAN 2.0A data frame, interframe space included.

    ``44 + 8*dlc`` frame bits (SOF, 11-bit ID, RTR, IDE, r0, DLC, CRC, delimiters, ACK, EOF)
    plus 3 bits of interframe space; with ``stuffing`` the worst-case stuff bits
    ``(34 + 8*dlc - 1) // 4`` of the 34 + 8*dlc stuffable bits (Davis et al., 2007), which
    makes 135 bits for an 8-byte frame.
    """
    bits = 44 + 8 * dlc + 3
    if stuffing:
        bits += (34 + 8 * dlc - 1) // 4
    return bits


def isotp_min_frames(payload_bytes: int) -> int:
    """Fewest CAN frames that carry one ISO-TP message of ``payload_bytes`` (classic CAN, normal addressing).

    7 bytes fit a single frame; otherwise a first frame carries 6 and each consecutive frame 7,
    plus the receiver's one flow-control frame (BS = 0).
    """
    if payload_bytes <= 7:
        return 1
    return 1 + -(-(payload_bytes - 6) // 7) + 1
