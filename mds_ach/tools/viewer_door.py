"""The viewer's door: who may open the 3-D page and its websocket (issue 28).

The viewer's sliders write ``mds-ref-filter``, so its page is a way to move the robot: it must not be open to every
local user (loopback is shared by all of them) nor to a web page in a local browser. The credential is a random
token in the URL path (``http://127.0.0.1:8080/<token>/``), as Jupyter does with its query token: the viser client
loads its assets relative to the page and opens its websocket on the page's path, so every request it makes
carries the token and no cookie is needed (a cookie for 127.0.0.1 would be sent to every local port). The token is
made by the viewer process itself (never on a command line, which every user can read in /proc), printed to the
terminal of whoever started it and written to a 0600 file in that user's runtime directory.

Refused with HTTP 403 and no page, no websocket: a request whose path does not start with the token, and a request
whose ``Origin`` is not the page's own (a foreign web page that learnt the token still cannot open the websocket;
a ``Host`` that is not one of the server's names is refused too, against DNS rebinding).

How it is hooked in: viser has no public hook for its HTTP/websocket handshake. It serves through
``websockets.asyncio.server.serve(..., process_request=<its file server>)``; :func:`guarded` replaces that
function of the websockets package only while the ViserServer is constructed (viser starts serving inside its
constructor), so that viser's own ``process_request`` runs behind :meth:`Door.check`, and reports whether the door
was installed: a viser that no longer serves this way makes the viewer refuse to start, never serve unguarded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hmac
import http
import ipaddress
import secrets
import threading
from collections.abc import Awaitable, Callable, Iterator
from typing import Any
from urllib.parse import urlsplit

TOKEN_BYTES = 24  # 192 bits, URL-safe base64: 32 characters
SECURITY_HEADERS = {"Referrer-Policy": "no-referrer", "X-Frame-Options": "DENY", "Cache-Control": "no-store"}

ProcessRequest = Callable[[Any, Any], "Awaitable[Any] | Any"]

_install_lock = threading.Lock()


def new_token() -> str:
    return secrets.token_urlsafe(TOKEN_BYTES)


def _wildcard(host: str) -> bool:
    return host in ("0.0.0.0", "::", "")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class Door:
    """Checks each HTTP request and websocket handshake of the viewer: the token first, then Host and Origin."""

    def __init__(self, token: str, host: str) -> None:
        self.token = token
        self.host = host
        self.installed = False  # set when viser's server was built behind this door
        self.refused = 0

    def _host_ok(self, name: str) -> bool:
        """A name the browser may use for this server (the Host header's name, without the port)."""
        if _wildcard(self.host):
            return True
        name = name.strip("[]").lower()
        bound = self.host.strip("[]").lower()
        return name == bound or (_is_loopback(bound) and _is_loopback(name))

    def _origin_problem(self, headers: Any) -> str | None:
        host = headers.get("Host")
        if host is None or not self._host_ok(urlsplit(f"http://{host}").hostname or ""):
            return f"unknown Host {host!r}"
        origin = headers.get("Origin")
        if origin is not None and origin.lower() != f"http://{host}".lower():
            return f"foreign Origin {origin!r}"
        return None

    def strip(self, path: str) -> str | None:
        """The path behind the token (``/<token>/x`` -> ``/x``, ``/<token>`` -> ``/``), None without the token."""
        head, _, query = path.partition("?")
        parts = head.split("/", 2)  # "", token, rest
        if len(parts) < 2 or not hmac.compare_digest(parts[1].encode(), self.token.encode()):
            return None
        rest = "/" + (parts[2] if len(parts) > 2 else "")
        return rest + (f"?{query}" if query else "")

    def check(self, connection: Any, request: Any, inner: ProcessRequest | None) -> Any:
        """websockets' ``process_request``: a 403 response, a redirect, or ``inner``'s answer for the path behind
        the token (None lets the websocket handshake go on)."""
        behind = self.strip(request.path)
        problem = "no valid token in the URL" if behind is None else self._origin_problem(request.headers)
        if problem is not None:
            self.refused += 1
            response = connection.respond(http.HTTPStatus.FORBIDDEN,
                                          "403 Forbidden: open the URL that `mds-ach sim` printed (it carries the "
                                          "viewer's token).\n")
            response.headers.update(SECURITY_HEADERS)
            return response
        assert behind is not None  # a path without the token is refused above
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return None
        if request.path.partition("?")[0] == f"/{self.token}":  # the page must end in "/": its assets are relative
            query = request.path.partition("?")[2]
            response = connection.respond(http.HTTPStatus.FOUND, "")
            response.headers["Location"] = f"/{self.token}/" + (f"?{query}" if query else "")
            response.headers.update(SECURITY_HEADERS)
            return response
        if inner is None or ".." in behind.partition("?")[0].split("/"):
            # viser 1.0 maps the path onto its client directory without refusing "..": a raw client could read any
            # file of the viewer's user (a browser normalises such paths away, so no page ever asks for one)
            return connection.respond(http.HTTPStatus.NOT_FOUND, "not found\n")
        response = inner(connection, dataclasses.replace(request, path=behind))
        if response is not None and hasattr(response, "headers"):
            response.headers.update(SECURITY_HEADERS)
        return response


@contextlib.contextmanager
def guarded(door: Door) -> Iterator[Door]:
    """While active, every ``websockets.asyncio.server.serve`` call serves behind ``door``; see the module docstring.
    Construct the ViserServer inside it, then require ``door.installed``."""
    import websockets.asyncio.server as ws_server

    original = ws_server.serve

    def serve(*args: Any, process_request: ProcessRequest | None = None, **kwargs: Any) -> Any:
        def process(connection: Any, request: Any) -> Any:
            return door.check(connection, request, process_request)

        door.installed = True
        return original(*args, process_request=process, **kwargs)

    with _install_lock:
        ws_server.serve = serve  # type: ignore[misc,assignment]
        try:
            yield door
        finally:
            ws_server.serve = original  # type: ignore[misc]
