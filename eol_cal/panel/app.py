"""The operator panel and the line view as ASGI applications (Starlette, served by uvicorn).

Both serve fixed pages (``eol_cal/panel/pages``: HTML, one script and one style sheet, nothing
built from strings) and the state as JSON: ``/state`` once, ``/events`` as server-sent events (a
snapshot each time its version moves). The page writes every text into the document as text
(``textContent``), so a serial or a reason is never markup. The panel's actions are POSTs of a JSON
body (a cross-site form cannot send one, and a request from another origin is refused); the
line view has no action at all.

Every response carries a content security policy that lets the page load only its own script and
style (no inline code, nothing from elsewhere). With credentials (:mod:`eol_cal.panel.serve`) every
request needs them (HTTP basic authentication).
"""

from __future__ import annotations

import asyncio
import base64
import hmac
import json
from collections.abc import Callable
from importlib import resources
from typing import Any, Protocol

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from eol_cal.panel.controls import Controls, Refused

#: the largest body of an action (bytes): a serial, a name
MAX_BODY = 4096
#: seconds between two looks at the state's version in a live stream, and between keep-alives
STREAM_POLL_S = 0.1
KEEPALIVE_S = 15.0
HEADERS = {
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
                               "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}


class Live(Protocol):
    """What a page follows: a JSON-ready snapshot and a version that grows with each change."""

    @property
    def version(self) -> int: ...

    def snapshot(self) -> dict[str, Any]: ...


class Credentials(Protocol):
    user: str
    password: str


def page_file(name: str) -> Response:
    """One of the package's page files, as it is."""
    data = resources.files("eol_cal.panel").joinpath("pages", name).read_bytes()
    return Response(data, media_type=TYPES[name[name.rindex("."):]], headers=HEADERS)


def static_routes(page: str, names: tuple[str, ...]) -> list[Route]:
    """``/`` (``page``) and ``/NAME`` for each file the page loads."""
    def serving(name: str) -> Callable[[Request], Response]:
        return lambda request: page_file(name)

    return [Route("/", serving(page)), *(Route(f"/{n}", serving(n)) for n in names),
            Route("/favicon.ico", lambda request: Response(status_code=204, headers=HEADERS))]  # none: no 404 in the log


def live_routes(live: Live, closing: Callable[[], bool]) -> list[Route]:
    """``/state`` (the snapshot) and ``/events`` (server-sent events: a snapshot at each change)."""

    async def state(request: Request) -> Response:
        return JSONResponse(live.snapshot(), headers=HEADERS)

    async def events(request: Request) -> Response:
        async def stream():
            seen, quiet = -1, 0.0
            while not closing():
                version = live.version
                if version != seen:
                    seen, quiet = version, 0.0
                    yield f"data: {json.dumps(live.snapshot(), allow_nan=False)}\n\n"
                elif quiet >= KEEPALIVE_S:
                    quiet = 0.0
                    yield ": keep-alive\n\n"
                await asyncio.sleep(STREAM_POLL_S)
                quiet += STREAM_POLL_S

        return StreamingResponse(stream(), media_type="text/event-stream", headers=HEADERS)

    return [Route("/state", state), Route("/events", events)]


async def json_body(request: Request) -> dict[str, Any]:
    """An action's body: a JSON object of at most :data:`MAX_BODY` bytes, from this page's origin."""
    origin = request.headers.get("origin")
    if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host', '')}":
        raise Refused(403, "a request from another origin")
    if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
        raise Refused(415, "the body must be JSON (application/json)")
    body = await request.body()
    if len(body) > MAX_BODY:
        raise Refused(413, f"body of {len(body)} bytes, at most {MAX_BODY}")
    try:
        doc = json.loads(body)
    except ValueError:
        raise Refused(400, "the body is not JSON") from None
    if not isinstance(doc, dict):
        raise Refused(400, "the body must be a JSON object")
    return doc


def _text(doc: dict[str, Any], key: str) -> str:
    value = doc.get(key)
    if not isinstance(value, str):
        raise Refused(400, f"{key}: a text is needed")
    return value


def action(do: Callable[[dict[str, Any]], Any]) -> Callable[[Request], Any]:
    """A POST route: the checked body to ``do``; a refusal as ``{"error": reason}`` with its status."""

    async def route(request: Request) -> Response:
        try:
            doc = await json_body(request)
            result = await asyncio.to_thread(do, doc)
        except Refused as exc:
            return JSONResponse({"error": exc.reason}, status_code=exc.status, headers=HEADERS)
        return JSONResponse({"ok": True, "result": result}, headers=HEADERS)

    return route


class BasicAuth:
    """Every request needs the credentials (HTTP basic authentication), compared in constant time."""

    def __init__(self, app: ASGIApp, credentials: Credentials) -> None:
        self.app = app
        self.expected = b"Basic " + base64.b64encode(f"{credentials.user}:{credentials.password}".encode())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            given = dict(scope["headers"]).get(b"authorization", b"")
            if not hmac.compare_digest(given, self.expected):
                response = Response("credentials needed\n", status_code=401, media_type="text/plain",
                                    headers={**HEADERS, "WWW-Authenticate": 'Basic realm="eol-cal", charset="UTF-8"'})
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


def panel_app(controls: Controls, closing: Callable[[], bool], credentials: Credentials | None = None) -> ASGIApp:
    """The operator panel of one station: its page, its live state, its actions."""
    routes = [
        *static_routes("panel.html", ("panel.js", "style.css")),
        *live_routes(controls.state, closing),
        Route("/signin", action(lambda doc: controls.sign_in(_text(doc, "name"))), methods=["POST"]),
        Route("/signout", action(lambda doc: controls.sign_out()), methods=["POST"]),
        Route("/scan", action(lambda doc: controls.scan(_text(doc, "line"))), methods=["POST"]),
        Route("/stop", action(lambda doc: controls.stop()), methods=["POST"]),
        Route("/end", action(lambda doc: controls.end()), methods=["POST"]),
    ]
    app = Starlette(routes=routes)
    return app if credentials is None else BasicAuth(app, credentials)


def line_app(live: Live, closing: Callable[[], bool], credentials: Credentials | None = None) -> ASGIApp:
    """The line view: its page and its live state; no action (read only)."""
    app = Starlette(routes=[*static_routes("line.html", ("line.js", "style.css")), *live_routes(live, closing)])
    return app if credentials is None else BasicAuth(app, credentials)
