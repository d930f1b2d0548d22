"""How the client reaches the dyno (:class:`DynoConfig`) and the chunked read of its capture buffer.

The buffer is read page by page through the register map's window (:mod:`.regmap`): select a
channel and a first sample, then read the window in blocks of at most the map's
``max_read_registers``. pymodbus serves one request per connection at a time, so the blocks of a page are
read over ``connections`` parallel connections; a lost connection or a timeout restarts the page
on fresh connections through :func:`eol_cal.infra.retry.retry_async` (the same back-off rule as every
single request, :meth:`eol_cal.dyno.client.DynoClient._call`).

The read is streamed (:class:`BufferReader`): it runs on an event loop in a thread of its own,
its connections kept open from one capture to the next, while the capture records, and reads the
samples the client's status polls report recorded (:class:`BufferFill`, ``capture_count`` while
running), in chunks of :data:`STREAM_CHUNK_S`, so that when the capture is ready only its last
chunk is left to read. A dyno that reports no count before the capture is ready is read whole
then, as before.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.infra import interrupts
from eol_cal.dyno.mapfile import default_register_map
from eol_cal.dyno.regmap import READ_FC, RegisterMap
from eol_cal.infra.exchange_log import log_modbus
from eol_cal.infra.retry import RetriesExhausted, retry_async

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


#: a streamed read waits for at least this much capture (s) before it reads a chunk ...
STREAM_CHUNK_S = 0.05
#: ... and, in the capture's last chunk, this much: what is left to read once it is ready
STREAM_TAIL_S = 0.01
#: how often a streamed read looks for newly recorded samples (s)
STREAM_POLL_S = 0.003


class BufferFill:
    """How many samples of the capture the dyno holds, as the client's status polls see it.

    The polling thread :meth:`update` s it; the :class:`BufferReader` reads :attr:`count`.
    :meth:`stop` ends a read that waits for samples (the capture failed, the client gave up).
    """

    def __init__(self, n_samples: int, count: int = 0) -> None:
        self.n_samples = n_samples
        self.count = min(count, n_samples)
        self.stopped: str | None = None
        self._lock = threading.Lock()

    def update(self, count: int) -> None:
        with self._lock:
            self.count = max(self.count, min(int(count), self.n_samples))

    def stop(self, why: str) -> None:
        self.stopped = why


def channel_plan(regmap: RegisterMap, names: Sequence[str]) -> list[tuple[str, int]]:
    """Channels to read: ``names`` plus the digital channel, as ``(name, channel id)``."""
    return [(n, regmap.channels[n]) for n in names] + [("digital", regmap.window.digital_id)]


def page_plan(regmap: RegisterMap, names: Sequence[str], n_samples: int, first: int = 0
              ) -> tuple[list[tuple[str, int]], list[tuple[int, int, int]]]:
    """Channels to read (:func:`channel_plan`) and the pages of samples ``first:n_samples`` as
    ``(channel id, first sample, registers)``."""
    plan = channel_plan(regmap, names)
    return plan, [page for _name, cid in plan for page in _pages(regmap, cid, first, n_samples)]


def _pages(regmap: RegisterMap, cid: int, first: int, stop: int) -> list[tuple[int, int, int]]:
    per = regmap.regs_per_sample(cid)
    page_samples = regmap.samples_per_page(cid)
    return [(cid, f, min(page_samples, stop - f) * per) for f in range(first, stop, page_samples)]


def _decode(regmap: RegisterMap, plan: list[tuple[str, int]], words: dict[int, list[np.ndarray]]) -> dict[str, np.ndarray]:
    result: dict[str, np.ndarray] = {}
    for name, cid in plan:
        w = np.concatenate(words[cid]) if words[cid] else np.zeros(0, dtype=np.uint16)
        if name == "digital":
            result["enc_a"], result["enc_b"], result["hall"] = regmap.unpack_digital(w)
        else:
            result[name] = regmap.words_to_analog(w)
    return result


def read_capture_buffer(cfg: DynoConfig, names: Sequence[str], n_samples: int,
                        progress: ProgressFn | None = None) -> tuple[dict[str, np.ndarray], int]:
    """Read channels ``names`` (canonical names) and the digital channel from the dyno's buffer
    (a capture that is ready: every sample at once).

    Returns the analog channels (float64 from the f32 on the wire) and ``enc_a``, ``enc_b``,
    ``hall``, and the number of reconnects it took. Raises :class:`TransferError`.
    """
    plan = channel_plan(cfg.regmap, names)

    async def once() -> tuple[dict[int, list[np.ndarray]], int]:
        conns = _Connections(cfg)
        try:
            return await _transfer(cfg, conns, plan, BufferFill(n_samples, n_samples), (n_samples, n_samples),
                                   progress), conns.reconnects
        finally:
            conns.close()

    with asyncio.Runner(loop_factory=_new_loop) as runner:
        words, reconnects = runner.run(once())
    return _decode(cfg.regmap, plan, words), reconnects


def _new_loop() -> asyncio.AbstractEventLoop:
    """A new event loop, built whole before a signal (:mod:`eol_cal.infra.interrupts`) can stop it: a
    loop cut off inside its constructor has no self-pipe, and collecting it later prints
    "Exception ignored ... Traceback" over the command's one-line interruption."""
    loop = None
    try:
        with interrupts.shielded():
            loop = asyncio.new_event_loop()
    except BaseException:
        if loop is not None:
            loop.close()
        raise
    return loop


class BufferReader:
    """Streamed reads of the dyno's capture buffer (module doc): an event loop in a thread of its
    own and the parallel connections, kept for every capture of a profile; :meth:`close` ends both.
    """

    def __init__(self, cfg: DynoConfig) -> None:
        self._cfg = cfg
        self._loop = _new_loop()
        self._conns = _Connections(cfg)
        self._thread = threading.Thread(target=self._loop.run_forever, name="dyno-stream", daemon=True)
        try:
            with interrupts.shielded():  # a signal between the two leaves no loop without its thread
                self._thread.start()
        except BaseException:
            self.close()
            raise

    @property
    def reconnects(self) -> int:
        """Connections opened again after a loss, over every read so far."""
        return self._conns.reconnects

    def stream(self, names: Sequence[str], fill: BufferFill, rate_hz: float,
               progress: ProgressFn | None = None, first: int = 0) -> Stream:
        """Start reading channels ``names`` (and the digital channel) of the capture ``fill``
        follows, from sample ``first`` on (the samples before it are never read)."""
        plan = channel_plan(self._cfg.regmap, names)
        chunk = (max(1, int(rate_hz * STREAM_CHUNK_S)), max(1, int(rate_hz * STREAM_TAIL_S)))
        job = asyncio.run_coroutine_threadsafe(_transfer(self._cfg, self._conns, plan, fill, chunk, progress, first),
                                               self._loop)
        return Stream(self._cfg, plan, fill, job)

    def close(self) -> None:
        if self._loop.is_closed():
            return
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._conns.close)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(2.0)
        if not self._thread.is_alive():
            self._loop.close()


class Stream:
    """One capture's streamed read (:meth:`BufferReader.stream`)."""

    def __init__(self, cfg: DynoConfig, plan: list[tuple[str, int]], fill: BufferFill, job: Future) -> None:
        self.plan, self._cfg, self._fill, self._job = plan, cfg, fill, job

    def result(self, timeout: float | None = None) -> dict[str, np.ndarray]:
        """The channels read (as :func:`read_capture_buffer`) once every sample is in; raises
        :class:`TransferError`. Call after the fill reached the capture's length (or was stopped)."""
        try:
            words = self._job.result(timeout)
        except FutureTimeout:
            self._fill.stop("no answer in time")
            raise TransferError(f"the buffer read did not finish within {timeout} s") from None
        except TransferError:
            raise
        except Exception as exc:  # any failure of the read is the transfer's
            raise TransferError(f"{type(exc).__name__}: {exc}") from exc
        return _decode(self._cfg.regmap, self.plan, words)

    def abandon(self, why: str) -> None:
        """Stop reading (the capture failed): the read ends within a request timeout."""
        self._fill.stop(why)
        with contextlib.suppress(Exception):  # the capture's own failure is what is reported
            self._job.result(self._cfg.timeout * (self._cfg.retries + 1) + 1.0)


class _Connections:
    """``cfg.connections`` parallel pymodbus connections to the dyno, opened when first needed
    and again after a loss (counted in :attr:`reconnects`); used on one event loop."""

    def __init__(self, cfg: DynoConfig) -> None:
        self.cfg = cfg
        self.clients: list = []
        self.reconnects = 0
        self._opened = False

    @property
    def up(self) -> bool:
        return len(self.clients) == max(1, self.cfg.connections) and all(cl.connected for cl in self.clients)

    async def open(self) -> None:
        from pymodbus.client import AsyncModbusTcpClient

        from eol_cal.dyno.pdu import fast_reads

        cfg = self.cfg
        self.close()
        if self._opened:
            self.reconnects += 1
        self._opened = True
        for _ in range(max(1, cfg.connections)):
            cl = AsyncModbusTcpClient(cfg.host, port=cfg.port, timeout=cfg.timeout, retries=0, reconnect_delay=0)
            fast_reads(cl)
            self.clients.append(cl)
            if not await cl.connect():
                raise ConnectionError("cannot connect")

    def close(self) -> None:
        for cl in self.clients:
            cl.close()
        self.clients.clear()


async def _transfer(cfg: DynoConfig, conns: _Connections, plan: list[tuple[str, int]], fill: BufferFill,
                    chunk: tuple[int, int], progress: ProgressFn | None, first: int = 0) -> dict[int, list[np.ndarray]]:
    """Read the buffer's channels ``plan`` as ``fill`` says samples are recorded, over the parallel
    connections ``conns``.

    pymodbus serves one request per connection at a time, so parallel connections are how
    requests overlap. The page selection is dyno state shared by all connections: each page is
    selected, then its blocks are read in parallel. A read waits until ``chunk[0]`` samples more
    (``chunk[1]`` in the capture's last ``chunk[0]``; or the rest of the capture) are recorded:
    few requests while the capture runs, little left when it is ready. A lost connection or a
    timeout restarts the page on fresh connections (:func:`eol_cal.infra.retry.retry_async`:
    ``cfg.retries`` times, doubling delays). Returns each channel's words of samples ``first`` on,
    page by page.
    """
    from pymodbus.exceptions import ModbusException

    regmap = cfg.regmap
    where = f"{cfg.host}:{cfg.port}"

    async def read_page(cid: int, first: int, n_regs: int) -> np.ndarray:
        clients = conns.clients
        for address, select, _names in regmap.write_runs({"buf_channel": cid, "buf_offset": first}):
            sel = await clients[0].write_registers(address, select, device_id=cfg.device_id)
            log_modbus(where, 16, address, len(select), select,
                       exception=getattr(sel, "exception_code", None) if sel.isError() else None)
            if sel.isError():
                raise TransferError(f"page select refused (Modbus exception {getattr(sel, 'exception_code', None)})")
        blocks = regmap.page_blocks(n_regs)
        out: list = [None] * len(blocks)
        fc = READ_FC[regmap.window.table]
        k = len(clients)

        async def worker(i: int) -> None:
            for j in range(i, len(blocks), k):
                address, count = blocks[j]
                read = clients[i].read_input_registers if fc == 4 else clients[i].read_holding_registers
                r = await read(address, count=count, device_id=cfg.device_id)
                log_modbus(where, fc, address, count, getattr(r, "registers", None),
                           exception=getattr(r, "exception_code", None) if r.isError() else None)
                if r.isError():
                    raise TransferError(f"read of {count} registers at 0x{address:04x} refused "
                                        f"(Modbus exception {getattr(r, 'exception_code', None)})")
                if len(r.registers) != count:
                    raise ConnectionError(f"short read at 0x{address:04x}: {len(r.registers)} of {count} registers")
                out[j] = r.registers

        await asyncio.gather(*(worker(i) for i in range(min(k, len(blocks)))))
        return np.concatenate([np.asarray(b, dtype=np.uint16) for b in out])

    async def read_with_retry(cid: int, first: int, n_regs: int) -> np.ndarray:
        async def attempt(_n: int) -> np.ndarray:
            if not conns.up:
                await conns.open()
            return await read_page(cid, first, n_regs)

        try:
            return await retry_async(attempt, retries=cfg.retries, delay_s=cfg.retry_delay,
                                     retry_on=(ModbusException, ConnectionError, OSError, asyncio.TimeoutError),
                                     before_retry=lambda _n, _exc: conns.close())
        except RetriesExhausted as exc:
            raise TransferError(f"channel {cid} at sample {first}: {exc.last or type(exc.last).__name__} "
                                f"after {exc.attempts} attempts") from None

    n = fill.n_samples
    words: dict[int, list[np.ndarray]] = {cid: [] for _name, cid in plan}
    total = sum(regmap.regs_per_sample(cid) for _name, cid in plan) * (n - first)
    done = first
    while done < n:
        if fill.stopped is not None:
            raise TransferError(f"stopped at sample {done} of {n}: {fill.stopped}")
        count = fill.count
        want = chunk[0] if n - count > chunk[0] else chunk[1]
        if count - done < min(want, n - done):
            await asyncio.sleep(STREAM_POLL_S)
            continue
        for _name, cid in plan:
            for page in _pages(regmap, cid, done, count):
                words[cid].append(await read_with_retry(*page))
        done = count
        if progress:
            progress("transfer", total * (done - first) / (n - first), total)
    return words
