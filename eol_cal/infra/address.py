"""``HOST:PORT`` addresses of the line's machines (dyno, CAN-over-websocket server)."""

from __future__ import annotations

import ipaddress
import os
import re
import stat
from pathlib import Path

from eol_cal.errors import InputError

#: Modbus TCP's registered port: a dyno address without one uses it
MODBUS_PORT = 502

#: a host name (RFC 1123): dot-separated labels of letters, digits and inner hyphens
_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def host_problem(host: str) -> str | None:
    """Why ``host`` is not a host name, an IPv4 address or a bracketed IPv6 address (None when it is).

    ``"a b"`` or ``"http://dyno"`` in a station's settings reached the cycle and failed there; a
    host is refused where the address is read, from an option, a variable or a file alike.
    """
    if host.startswith("[") and host.endswith("]"):
        try:
            ipaddress.IPv6Address(host[1:-1])
            return None
        except ValueError:
            return f"{host!r} is not an IPv6 address"
    try:
        ipaddress.IPv4Address(host)
        return None
    except ValueError:
        pass
    name = host[:-1] if host.endswith(".") else host
    if 0 < len(name) <= 253 and all(_LABEL.fullmatch(label) for label in name.split(".")):
        return None
    return f"{host!r} is not a host name or an IP address (IPv6 in brackets)"


def parse_host_port(text: str, field: str = "address", any_port: bool = False,
                    default_port: int | None = None) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); a bad address is an :class:`InputError` naming ``field``.

    Parameters
    ----------
    text : str
        The address as the user typed it (IPv6 hosts in brackets keep their colons).
    field : str
        Option name for the error message.
    any_port : bool
        Accept port 0 (a server that binds any free port).
    default_port : int, optional
        Port of a bare ``HOST`` (or ``[IPv6]``); without one a port is required.
    """
    if "://" in text:
        raise InputError(None, field, f"{text!r} is a URL; give HOST or HOST:PORT")
    bare = ":" not in text or (text.startswith("[") and text.endswith("]"))
    if default_port is not None and bare and text:
        why = host_problem(text)
        if why is not None:
            raise InputError(None, field, why)
        return text, default_port
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        example = ("HOST or HOST:PORT, e.g. 192.0.2.10 or 127.0.0.1:5020" if default_port is not None
                   else "HOST:PORT, e.g. 127.0.0.1:5020")
        raise InputError(None, field, f"expected {example}, got {text!r}")
    why = host_problem(host)
    if why is not None:
        raise InputError(None, field, why)
    if not port.isdigit() or not port.isascii():
        raise InputError(None, field, f"port {port!r} is not a number")
    lowest = 0 if any_port else 1
    if not lowest <= int(port) <= 65535:
        raise InputError(None, field, f"port {port} out of range {lowest}..65535")
    return host, int(port)


def parse_modbus_address(text: str, field: str = "address") -> tuple[str, int]:
    """A dyno's ``HOST`` or ``HOST:PORT`` -> (host, port), port :data:`MODBUS_PORT` when none is given.

    An IPv6 host comes back without its brackets (``[::1]:502`` -> ``::1``), as sockets take it.
    """
    host, port = parse_host_port(text, field, default_port=MODBUS_PORT)
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host, port


#: URL schemes a records database may have: PostgreSQL, through psycopg 3 (``_sa_url`` in
#: ``eol_cal.records.connect`` maps the plain ones to it)
DB_SCHEMES = ("postgresql", "postgres", "postgresql+psycopg")


def records_db(text: str, field: str = "db", *, writing: bool = False) -> str | Path:
    """A records database as given (a SQLite file path or a PostgreSQL URL), checked before any
    cycle runs: the URL kept as text, a path as a :class:`~pathlib.Path`.

    ``sqlite:///x.sqlite``, ``postgresql+psycopg2://...``, ``mysql://...`` or a malformed URL in a
    station's settings used to pass the start; the cycle ran (a real station would have flashed
    the motor) and only the record's write failed. Refused here: a URL of another scheme or
    driver, one that does not parse or names no database; a path that is empty, a directory, a
    FIFO or a device; with ``writing``, a path whose directory does not exist.

    Raises
    ------
    InputError
        Naming ``field`` and the reason (the URL without its password).
    """
    text = str(text)
    if "://" not in text:
        return _db_path(text, field, writing)
    import sqlalchemy as sa

    try:
        url = sa.engine.make_url(text)
    except (sa.exc.ArgumentError, ValueError) as exc:
        raise InputError(None, field, f"not a database URL ({exc})") from None
    shown = url.render_as_string(hide_password=True)
    if url.drivername == "sqlite" or url.drivername.startswith("sqlite+"):
        raise InputError(None, field, f"{shown}: give a SQLite database as its file path, not a sqlite:// URL")
    if url.drivername not in DB_SCHEMES:
        raise InputError(None, field, f"{shown}: not a PostgreSQL URL (postgresql://user@host:port/db; the driver is "
                                      "psycopg 3, implied); SQLite: a file path")
    if not url.database:
        raise InputError(None, field, f"{shown}: names no database (postgresql://user@host:port/DB)")
    if url.host is not None and host_problem(url.host) is not None and host_problem(f"[{url.host}]") is not None:
        raise InputError(None, field, f"{shown}: {host_problem(url.host)}")
    return text


def path_problem(text: str) -> str | None:
    """Why ``text`` cannot name a file on this system (a NUL, a name over NAME_MAX, a path over
    PATH_MAX: ``os.stat`` raised ValueError or OSError deep in a command), or None."""
    if "\x00" in text:
        return "holds a NUL character"
    if len(os.fsencode(text)) >= os.pathconf("/", "PC_PATH_MAX"):
        return f"{len(text)} characters: longer than a path may be"
    longest = max((len(os.fsencode(part)) for part in text.split("/")), default=0)
    if longest > os.pathconf("/", "PC_NAME_MAX"):
        return f"holds a name of {longest} bytes: longer than a file name may be"
    return None


def _shown(text: str, most: int = 80) -> str:
    return text if len(text) <= most else f"{text[:most]}... ({len(text)} characters)"


def _db_path(text: str, field: str, writing: bool) -> Path:
    if not text.strip():
        raise InputError(None, field, "empty: give a SQLite file path or a postgresql:// URL")
    if (why := path_problem(text)) is not None:
        raise InputError(None, field, f"{_shown(text)!r}: {why}")
    path = Path(text)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = None
    if mode is not None and not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file (a FIFO, a device or a socket)"
        raise InputError(str(path), field, f"{kind}; a records database is a SQLite file or a postgresql:// URL")
    if writing and not path.resolve().parent.is_dir():
        raise InputError(str(path), field, f"directory {path.resolve().parent} does not exist")
    return path
