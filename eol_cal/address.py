"""``HOST:PORT`` addresses of the line's machines (dyno, CAN-over-websocket server)."""

from __future__ import annotations

from eol_cal.errors import InputError


def parse_host_port(text: str, field: str = "address", any_port: bool = False) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); a bad address is an :class:`InputError` naming ``field``.

    Parameters
    ----------
    text : str
        The address as the user typed it (IPv6 hosts in brackets keep their colons).
    field : str
        Option name for the error message.
    any_port : bool
        Accept port 0 (a server that binds any free port).
    """
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise InputError(None, field, f"expected HOST:PORT, e.g. 127.0.0.1:5020, got {text!r}")
    if not port.isdigit():
        raise InputError(None, field, f"port {port!r} is not a number")
    lowest = 0 if any_port else 1
    if not lowest <= int(port) <= 65535:
        raise InputError(None, field, f"port {port} out of range {lowest}..65535")
    return host, int(port)
