"""Serving a panel safely: where it listens, who may reach it, one panel per station.

- **Where**: ``--bind HOST:PORT`` (default ``127.0.0.1:8080``; port 0: any free one). A loopback
  address (127.0.0.0/8, ::1, ``localhost``) serves this PC's screen; any other address only with
  a credentials file (:func:`load_credentials`): refused otherwise, before anything starts.
- **Who**: the credentials file is a TOML file with ``user`` and ``password`` (12 characters at
  least) that only its owner may read (mode 600, as ssh wants a key); with it every request needs
  them (HTTP basic authentication, :class:`eol_cal.panel.app.BasicAuth`).
- **One per station**: :func:`station_lock` holds an exclusive lock on a file of the station's
  spool directory while the panel runs; a second panel of the same station is refused, naming
  the first one's process and address. The lock is the kernel's (``flock``): a killed panel
  leaves no stale lock.
- The server runs on a thread of its own (:func:`served`); the cycle stays in the main thread.
"""

from __future__ import annotations

import contextlib
import fcntl
import ipaddress
import os
import socket
import stat
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import uvicorn
from starlette.types import ASGIApp

from eol_cal.infra.address import parse_host_port
from eol_cal.errors import EolCalError, InputError
from eol_cal.infra.inputs import load_toml
from eol_cal.infra.lockfile import open_lock_file, refusal

DEFAULT_BIND = "127.0.0.1:8080"
#: the shortest password a credentials file may hold
MIN_PASSWORD = 12
#: seconds the server has to start listening, and to close its streams at the end (hang guards)
START_S = 30.0
STOP_S = 5.0


class PanelBusy(EolCalError):
    """Another panel of this station runs (exit code 2)."""



@dataclass(frozen=True)
class Credentials:
    user: str
    password: str

    def __repr__(self) -> str:  # never print the password
        return f"Credentials(user={self.user!r})"


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only (127.0.0.0/8, ::1, ``localhost``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_bind(text: str, credentials: Credentials | None) -> tuple[str, int]:
    """``HOST:PORT`` where the panel listens; a non-loopback host only with ``credentials``."""
    host, port = parse_host_port(text, "--bind", any_port=True)
    if not is_loopback(host) and credentials is None:
        raise InputError(None, "--bind", f"{host} is reachable from other machines: give --credentials FILE "
                                         "(user and password) to serve there, or bind 127.0.0.1")
    return host.strip("[]"), port


def load_credentials(path: str | os.PathLike) -> Credentials:
    """``user`` and ``password`` from a TOML file that only its owner can read."""
    file = str(path)
    doc = load_toml(path, max_bytes=4096)
    mode = os.stat(path).st_mode
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise InputError(file, None, f"mode {stat.S_IMODE(mode):o}: others can read it (chmod 600 {file})")
    unknown = sorted(set(doc) - {"user", "password"})
    if unknown:
        raise InputError(file, unknown[0], "unknown key (user and password only)")
    user, password = doc.get("user"), doc.get("password")
    if not isinstance(user, str) or not user or ":" in user or not user.isprintable():
        raise InputError(file, "user", "a printable name without ':' is needed")
    if not isinstance(password, str) or len(password) < MIN_PASSWORD or not password.isprintable():
        raise InputError(file, "password", f"a printable password of {MIN_PASSWORD} characters at least is needed")
    return Credentials(user, password)


@contextlib.contextmanager
def station_lock(lock_dir: Path, station: str | None, what: str) -> Iterator[Path]:
    """Hold the station's panel lock (``lock_dir/panel-STATION.lock``) for the block; :class:`PanelBusy`
    when another process holds it. ``what`` (its address) is written into the file for the refusal."""
    lock_dir.mkdir(parents=True, exist_ok=True)
    path = lock_dir / f"panel-{station or 'station'}.lock"
    try:
        fd = open_lock_file(path)
    except OSError as exc:
        raise InputError(str(path), "lock file", refusal(exc)) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            held = os.pread(fd, 512, 0).decode("utf-8", "replace").strip() or "another process"
            raise PanelBusy(f"a panel of station {station} already runs ({held}; lock {path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, {what}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)  # the lock goes with the descriptor


def listening_socket(host: str, port: int) -> socket.socket:
    """A socket bound to ``host:port``, listening; :class:`InputError` naming ``--bind`` when it cannot be."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(64)
    except OSError as exc:
        sock.close()
        raise InputError(None, "--bind", f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


@contextlib.contextmanager
def served(app: ASGIApp, sock: socket.socket, closing: threading.Event) -> Iterator[str]:
    """Serve ``app`` on ``sock`` from a thread for the block; its URL. At the end ``closing`` is set
    (the live streams end) and the server stops."""
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off",
                            timeout_graceful_shutdown=int(STOP_S))
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="panel-server", daemon=True)
    thread.start()
    end = time.monotonic() + START_S
    while not server.started and thread.is_alive() and time.monotonic() < end:
        time.sleep(0.02)
    try:
        if not server.started:
            raise EolCalError(f"the panel's server did not start on {url_of(sock)}")
        yield url_of(sock)
    finally:
        closing.set()
        server.should_exit = True
        thread.join(STOP_S * 2)
        sock.close()
