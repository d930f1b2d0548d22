"""CAN bus and ISO-TP plumbing shared by the flashing client and the ECU simulator.

python-can opens the bus (any interface, or python-can's own config file), can-isotp carries
UDS messages with the contract's addressing and 0xCC padding, and :class:`FaultyBus` injects
dropped and delayed frames for the reliability tests (the ECU simulator's bus paced to a CAN bit
rate is :class:`eol_cal.ecu.wire.PacedBus`).
"""

from __future__ import annotations

import configparser
import errno
import itertools
import logging
import os
import random
import socket
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

import can
import isotp
from udsoncan.connections import PythonIsoTpV2Connection
from udsoncan.exceptions import TimeoutException

from eol_cal.ecu import protocol as P
from eol_cal.errors import InputError
from eol_cal.infra.inputs import read_text

log = logging.getLogger(__name__)


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
    # The stack's reading thread waits in bus.recv at most this long: a frame wakes it at once,
    # so it bounds only how long stopping the stack takes, which the tester pays at the end of
    # every session (the station opens several per motor).
    read_timeout = TESTER_READ_TIMEOUT_S if blocking_send else 0.02
    return isotp.CanStack(bus, address=address, params=isotp_params(blocking_send=blocking_send, timing=timing),
                          read_timeout=read_timeout)


TESTER_READ_TIMEOUT_S = 0.004
"""Longest wait of the tester's ISO-TP reading thread in one ``bus.recv``, s (see :func:`make_stack`)."""


def bus_config(interface: str | None, channel: str | None, bitrate: int | None = None,
               can_config: str | None = None) -> dict:
    """The python-can settings :func:`open_bus` opens: the options over the configuration file's
    ``[default]`` section, checked without opening anything (a station checks them at its start).

    Raises
    ------
    InputError
        The file is not a readable regular file or not a python-can configuration (a garbage
        file was a ``MissingSectionHeaderError`` traceback), no interface, or one this tool
        does not drive.
    """
    overrides = {k: v for k, v in (("interface", interface), ("channel", channel), ("bitrate", bitrate))
                 if v is not None}
    if can_config is not None:
        parser = configparser.ConfigParser()
        try:  # read as python-can will, but through the one reader of input files (a FIFO is refused)
            parser.read_string(read_text(can_config, "can-config", max_bytes=1 << 20), source=can_config)
        except configparser.Error as exc:
            raise InputError(can_config, "can-config", f"not a python-can configuration file: "
                                                       f"{str(exc).splitlines()[0]}") from None
    try:
        config = can.util.load_config(path=can_config, config=overrides) if can_config else overrides
    except (OSError, ValueError, configparser.Error, can.CanInterfaceNotImplementedError) as exc:
        raise InputError(can_config, "can-config", str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    if not config.get("interface"):
        raise InputError(can_config, "interface",
                         "no CAN interface given (neither directly nor in a python-can configuration file)")
    if config.get("interface") == "udp_multicast":
        # Its frames leave through the network card; the project never uses it.
        raise InputError(can_config, "interface", "udp_multicast is not allowed; use virtual or remote")
    if config["interface"] not in can.interfaces.VALID_INTERFACES:
        raise InputError(can_config, "interface", f"{config['interface']!r} is not a python-can interface")
    for key in ("bitrate", "data_bitrate"):
        if key in config:
            try:
                rate = int(config[key])
            except (TypeError, ValueError):
                raise InputError(can_config, key, f"{config[key]!r} is not a bit rate (bit/s)") from None
            if not 10_000 <= rate <= 8_000_000:
                raise InputError(can_config, key, f"{rate} bit/s outside 10000..8000000")
            config[key] = rate
    return config


def open_bus(interface: str | None, channel: str | None, bitrate: int | None = None,
             can_config: str | None = None) -> GuardedBus:
    """Open a python-can bus from command-line style options, wrapped in a :class:`GuardedBus`.

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
    config = bus_config(interface, channel, bitrate, can_config)
    previous_timeout = socket.getdefaulttimeout()
    try:
        # python-can-remote's WebSocket handshake has no timeout of its own: a server that accepts
        # the connection and never answers would hold the command forever.
        socket.setdefaulttimeout(CONNECT_TIMEOUT_S)
        bus = can.Bus(ignore_config=True, **config)
    except (can.CanError, ValueError, OSError, TypeError) as exc:
        raise InputError(can_config, "interface",
                         f"cannot open {config.get('interface')} channel {config.get('channel')!r}: {exc}") from exc
    except Exception as exc:
        raise InputError(can_config, "interface",
                         f"cannot open {config.get('interface')} channel {config.get('channel')!r}: its driver is "
                         f"missing or failed ({type(exc).__name__}: {exc})") from exc
    finally:
        socket.setdefaulttimeout(previous_timeout)
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket):
        sock.settimeout(None)  # reads are select()ed with their own timeouts from here on
    return GuardedBus(bus)


CONNECT_TIMEOUT_S = 5.0
"""Longest wait for a network CAN server (python-can-remote) to accept the bus, s."""


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


class LinkLost(Exception):
    """The tester's CAN link is gone (remote server closed, adapter unplugged): no frame can pass."""


# Send errors that mean "queue full, try later" on a healthy link (socketcan, pcan).
_TRANSIENT_ERRNOS = {errno.ENOBUFS, errno.EAGAIN}


class GuardedBus(can.BusABC):
    """The tester's bus with every transport failure caught and remembered.

    can-isotp calls ``recv``/``send`` from its own threads; an exception there (python-can-remote's
    ``WebsocketClosed``, ``BrokenPipeError``, a socketcan ``ENETDOWN``) kills those threads and
    leaves a blocking send waiting for ever. Here the first such failure sets :attr:`lost`,
    later frames go nowhere, and :class:`TesterConnection` raises :class:`LinkLost` at once.

    Parameters
    ----------
    inner : can.BusABC
        The bus opened by :func:`open_bus` (or any python-can bus).
    owns : bool
        Shut ``inner`` down with this bus (False: the caller keeps using it).
    """

    def __init__(self, inner: can.BusABC, *, owns: bool = True) -> None:
        self.inner = inner
        self.owns = owns
        self.lost: str | None = None
        self.watch_id: int | None = None
        self.foreign_frames = 0
        """Frames received with :attr:`watch_id` (the tester's own request ID: another tester)."""
        super().__init__(channel=getattr(inner, "channel_info", "guarded"))
        self.channel_info = getattr(inner, "channel_info", "guarded")

    def _lose(self, exc: BaseException) -> None:
        if self.lost is None:
            self.lost = f"{type(exc).__name__}: {exc}".rstrip(": ")
            log.info("CAN link lost: %s", self.lost)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.lost is not None:
            return
        try:
            self.inner.send(msg, timeout)
        except can.CanOperationError as exc:
            if exc.error_code not in _TRANSIENT_ERRNOS:
                self._lose(exc)
        except Exception as exc:  # noqa: BLE001 - any other failure of the link ends it
            self._lose(exc)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.lost is not None:
            time.sleep(timeout or 0.0)
            return None, False
        try:
            msg = self.inner.recv(timeout)
        except Exception as exc:  # noqa: BLE001
            self._lose(exc)
            return None, False
        if msg is not None and msg.arbitration_id == self.watch_id:
            self.foreign_frames += 1  # a bus does not echo our own frames: someone else sent it
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        if not self.owns:
            return
        # python-can-remote's shutdown waits for the server's close frame with no time limit
        # (a frozen server never sends it): close from a helper thread and wait a bounded time.
        done = threading.Event()

        def close() -> None:
            try:
                self.inner.shutdown()
            except Exception as exc:  # noqa: BLE001 - closing a dead link fails; nothing is left to close
                log.debug("closing the CAN bus: %s", exc)
                can.BusABC.shutdown(self.inner)  # marks it closed, so its __del__ does not try again
            done.set()

        threading.Thread(target=close, name="can-close", daemon=True).start()
        if not done.wait(SHUTDOWN_S):
            log.info("the CAN bus did not close within %.1f s; left to the process exit", SHUTDOWN_S)
            sock = getattr(self.inner, "socket", None)
            if isinstance(sock, socket.socket):
                sock.close()  # ends the close's wait on a frozen server


SHUTDOWN_S = 0.5
"""Longest wait for the CAN interface to close, s."""


POLL_S = 0.05
"""How often a waiting request looks at the link, s (also bounds the reaction to Ctrl-C)."""


class TesterConnection(PythonIsoTpV2Connection):
    """udsoncan's can-isotp connection with every wait bounded and a dead link reported at once.

    Parameters
    ----------
    stack : isotp.CanStack
        On a :class:`GuardedBus`.
    link : GuardedBus
    send_timeout_s : float
        Longest a request may take to leave (all consecutive frames), s.
    """

    def __init__(self, stack: isotp.CanStack, link: GuardedBus, send_timeout_s: float) -> None:
        super().__init__(stack)
        self.link = link
        self.send_timeout_s = send_timeout_s

    def check_link(self) -> None:
        """Raise :class:`LinkLost` when the bus failed or the ISO-TP threads are gone."""
        if self.link.lost is not None:
            raise LinkLost(self.link.lost)
        layer = self.isotp_layer
        if self.opened and not all(t is not None and t.is_alive() for t in (layer.main_thread, layer.relay_thread)):
            raise LinkLost("the ISO-TP stack stopped")

    def specific_send(self, payload: bytes, timeout: float | None = None) -> None:
        self.check_link()
        self.isotp_layer.send(payload, send_timeout=self.send_timeout_s)
        self.check_link()

    def specific_wait_frame(self, timeout: float | None = None) -> bytes | None:
        self.check_connection_opened()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self.check_link()
            left = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
            frame = self.isotp_layer.recv(block=True, timeout=max(left, 0.0))
            if frame is not None:
                return bytes(frame)
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutException(f"Did not receive IsoTP frame from the Transport layer in time "
                                       f"(timeout={timeout} sec)")
