"""How the client reaches the dyno (:class:`DynoConfig`) and the chunked read of its capture buffer.

The buffer is read page by page through the register map's window (:mod:`.regmap`): select a
channel and a first sample, then read the window in blocks of at most the map's
``max_read_registers``. pymodbus serves one request per connection at a time, so the blocks of a page are
read over ``connections`` parallel connections; a lost connection or a timeout restarts the page
on fresh connections through :func:`eol_cal.retry.retry_async` (the same back-off rule as every
single request, :meth:`eol_cal.dyno.client.DynoClient._call`).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.dyno.mapfile import default_register_map
from eol_cal.dyno.regmap import READ_FC, RegisterMap
from eol_cal.exchange_log import log_modbus
from eol_cal.retry import RetriesExhausted, retry_async

ProgressFn = Callable[[str, float, float], None]  # (what, done, total)


class TransferError(Exception):
    """The capture buffer could not be read (the client names the dyno and raises its own error)."""


@dataclass(frozen=True)
class DynoConfig:
    """How to talk to the dyno.

    Attributes
    ----------
    host : str
        Dyno address.
    port : int
        Modbus TCP port.
    device_id : int
        Modbus unit id.
    timeout : float
        Per-request response timeout (s).
    retries : int
        Attempts after the first one for each request before giving up (reconnecting between).
    retry_delay : float
        First delay between attempts (s); doubles each time.
    connections : int
        Parallel TCP connections used to read the capture buffer.
    watchdog_ms : int
        Communication watchdog set on the dyno (ms): it stops the drive by itself when this
        client goes silent (0 = off).
    settle_timeout : float
        Extra time allowed to reach a set point beyond the ramp time (s).
    capture_timeout : float
        Extra time allowed for a capture beyond its duration (s).
    poll_interval : float
        Status polling period (s).
    register_map : RegisterMap or None
        The dyno's register layout; None: the eol-cal reference map (``maps/default.toml``).
    """

    host: str = "127.0.0.1"
    port: int = 5020
    device_id: int = 1
    timeout: float = 1.0
    retries: int = 3
    retry_delay: float = 0.1
    connections: int = 4
    watchdog_ms: int = 2000
    settle_timeout: float = 10.0
    capture_timeout: float = 60.0
    poll_interval: float = 0.01
    register_map: RegisterMap | None = None

    @property
    def regmap(self) -> RegisterMap:
        """The register map in use (the default map when none was given)."""
        return default_register_map() if self.register_map is None else self.register_map


def page_plan(regmap: RegisterMap, names: Sequence[str], n_samples: int) -> tuple[list[tuple[str, int]], list[tuple[int, int, int]]]:
    """Channels to read (``names`` plus the digital channel, as ``(name, channel id)``) and their
    pages as ``(channel id, first sample, registers)``."""
    plan = [(n, regmap.channels[n]) for n in names] + [("digital", regmap.window.digital_id)]
    pages: list[tuple[int, int, int]] = []
    for _name, cid in plan:
        per = regmap.regs_per_sample(cid)
        page_samples = regmap.samples_per_page(cid)
        for first in range(0, n_samples, page_samples):
            pages.append((cid, first, min(page_samples, n_samples - first) * per))
    return plan, pages


def read_capture_buffer(cfg: DynoConfig, names: Sequence[str], n_samples: int,
                        progress: ProgressFn | None = None) -> tuple[dict[str, np.ndarray], int]:
    """Read channels ``names`` (canonical names) and the digital channel from the dyno's buffer.

    Returns the analog channels (float64 from the f32 on the wire) and ``enc_a``, ``enc_b``,
    ``hall``, and the number of reconnects it took. Raises :class:`TransferError`.
    """
    regmap = cfg.regmap
    plan, pages = page_plan(regmap, names, n_samples)
    words = asyncio.run(_transfer(cfg, pages, progress))
    reconnects = int(words.pop())
    result: dict[str, np.ndarray] = {}
    for name, cid in plan:
        w = np.concatenate([wp for (c, _f, _n), wp in zip(pages, words, strict=True) if c == cid])
        if name == "digital":
            result["enc_a"], result["enc_b"], result["hall"] = regmap.unpack_digital(w)
        else:
            result[name] = regmap.words_to_analog(w)
    return result, reconnects


async def _transfer(cfg: DynoConfig, pages: list[tuple[int, int, int]], progress: ProgressFn | None) -> list:
    """Read capture pages over ``cfg.connections`` parallel connections.

    pymodbus serves one request per connection at a time, so parallel connections are how
    requests overlap. The page selection is dyno state shared by all connections: each page is
    selected, then its blocks are read in parallel. A lost connection or timeout restarts the
    page on fresh connections (:func:`eol_cal.retry.retry_async`: ``cfg.retries`` times, doubling delays). Returns the pages' words
    followed by the number of reconnects.
    """
    from pymodbus.client import AsyncModbusTcpClient
    from pymodbus.exceptions import ModbusException

    k = max(1, cfg.connections)
    regmap = cfg.regmap
    where = f"{cfg.host}:{cfg.port}"
    clients: list = []
    reconnects = 0

    async def open_all() -> None:
        for cl in clients:
            cl.close()
        clients.clear()
        for _ in range(k):
            cl = AsyncModbusTcpClient(cfg.host, port=cfg.port, timeout=cfg.timeout, retries=0, reconnect_delay=0)
            clients.append(cl)
            if not await cl.connect():
                raise ConnectionError("cannot connect")

    async def read_page(cid: int, first: int, n_regs: int) -> np.ndarray:
        for address, select, _names in regmap.write_runs({"buf_channel": cid, "buf_offset": first}):
            sel = await clients[0].write_registers(address, select, device_id=cfg.device_id)
            log_modbus(where, 16, address, len(select), select,
                       exception=getattr(sel, "exception_code", None) if sel.isError() else None)
            if sel.isError():
                raise TransferError(f"page select refused (Modbus exception {getattr(sel, 'exception_code', None)})")
        blocks = regmap.page_blocks(n_regs)
        out: list = [None] * len(blocks)
        fc = READ_FC[regmap.window.table]

        async def worker(i: int) -> None:
            for j in range(i, len(blocks), k):
                address, count = blocks[j]
                read = clients[i].read_input_registers if fc == 4 else clients[i].read_holding_registers
                r = await read(address, count=count, device_id=cfg.device_id)
                log_modbus(where, fc, address, count, getattr(r, "registers", None),
                           exception=getattr(r, "exception_code", None) if r.isError() else None)
                if r.isError():
                    raise TransferError(f"read of {count} registers at 0x{address:04x} refused (Modbus exception {getattr(r, 'exception_code', None)})")
                if len(r.registers) != count:
                    raise ConnectionError(f"short read at 0x{address:04x}: {len(r.registers)} of {count} registers")
                out[j] = r.registers

        await asyncio.gather(*(worker(i) for i in range(min(k, len(blocks)))))
        return np.concatenate([np.asarray(b, dtype=np.uint16) for b in out])

    words: list = []
    total = sum(n for _c, _f, n in pages)
    done = 0
    try:
        for cid, first, n_regs in pages:
            async def attempt(n: int, cid: int = cid, first: int = first, n_regs: int = n_regs) -> np.ndarray:
                nonlocal reconnects
                if len(clients) != k or not all(cl.connected for cl in clients):
                    if n or words:
                        reconnects += 1
                    await open_all()
                return await read_page(cid, first, n_regs)

            def drop_all(_n: int, _exc: BaseException) -> None:
                for cl in clients:
                    cl.close()
                clients.clear()

            try:
                words.append(await retry_async(attempt, retries=cfg.retries, delay_s=cfg.retry_delay,
                                               retry_on=(ModbusException, ConnectionError, OSError, asyncio.TimeoutError),
                                               before_retry=drop_all))
            except RetriesExhausted as exc:
                raise TransferError(f"channel {cid} at sample {first}: {exc.last or type(exc.last).__name__} after {exc.attempts} attempts") from None
            done += n_regs
            if progress:
                progress("transfer", done, total)
    finally:
        for cl in clients:
            cl.close()
    return words + [reconnects]
