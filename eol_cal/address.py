"""``HOST:PORT`` addresses of the line's machines (dyno, CAN-over-websocket server)."""

from __future__ import annotations

from eol_cal.errors import InputError

#: Modbus TCP's registered port: a dyno address without one uses it
MODBUS_PORT = 502


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
    bare = ":" not in text or (text.startswith("[") and text.endswith("]"))
    if default_port is not None and bare and text:
        return text, default_port
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        example = ("HOST or HOST:PORT, e.g. 192.0.2.10 or 127.0.0.1:5020" if default_port is not None
                   else "HOST:PORT, e.g. 127.0.0.1:5020")
        raise InputError(None, field, f"expected {example}, got {text!r}")
    if not port.isdigit():
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
