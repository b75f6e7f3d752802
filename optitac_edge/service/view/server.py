"""The view's HTTP server: its own assets and the live data, nothing else (standard library only).

Routes (anything else is 404; other methods 405):

``GET  /``, ``/app.js``, ``/style.css``  the page (shipped in the package: works with no internet)
``GET  /api/layout``                     the fiber map (JSON)
``GET  /api/state``                      the latest update (JSON; ``?after=SEQ`` waits up to 1 s for a newer one)
``GET  /api/frame.jpg``                  the latest camera frame (JPEG)
``POST /api/tare``                       take the baseline again
``POST /api/snapshot``                   the view as a PNG
``POST /api/orient`` ``start``/``cancel`` the guided orientation (press near +x, then +y)

Requests are checked before anything else: the request target at most
``MAX_TARGET`` characters, a body at most ``MAX_BODY`` bytes, a ``Host`` that
names this server (no DNS rebinding: on a loopback address, ``localhost`` or a
loopback IP), POSTs with the ``X-OptiTac`` header (no cross-site requests)
and, when bound to anything but localhost, the token printed at start.

A connection has ``TIMEOUT_S`` in all to send each request (a client that
sends a header line every 2 s is cut off after 5 s, not kept for ever by a
timeout per read); at most ``MAX_CONNECTIONS`` connections are open at once
and at most ``MAX_CLIENTS`` requests answered at once, so slow clients that
hold connections do not keep requests from being answered. A client that
goes away (a closed tab) is counted, never a traceback. All of it runs in the
server's threads: the frame loop never waits for a viewer.
"""

from __future__ import annotations

import hmac
import io
import ipaddress
import json
import logging
import secrets
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit

from optitac_edge.errors import OptiTacError
from optitac_edge.service.view.live import LiveView, lower_priority
from optitac_edge.service.view.render import encode_png, render_published

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

MAX_TARGET = 256
MAX_BODY = 1024
#: Requests answered at once, and connections open at once (most of them may still be sending a request).
MAX_CLIENTS = 16
MAX_CONNECTIONS = 64
#: The time a connection has to send a whole request (request line, headers, body), s.
TIMEOUT_S = 5.0
ASSETS = {"/": ("index.html", "text/html; charset=utf-8"), "/index.html": ("index.html", "text/html; charset=utf-8"),
          "/app.js": ("app.js", "text/javascript; charset=utf-8"), "/style.css": ("style.css", "text/css; charset=utf-8"),
          "/favicon.svg": ("favicon.svg", "image/svg+xml"), "/favicon.ico": ("favicon.svg", "image/svg+xml")}


def parse_bind(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT``) -> (host, port).

    Raises
    ------
    OptiTacError
        One line when it is not an address and a port in 1..65535 (0: any free port).
    """
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    try:
        number = int(port)
        if not sep or not host or not 0 <= number <= 65535:
            raise ValueError
        ipaddress.ip_address(host) if host != "localhost" else None
    except ValueError:
        raise OptiTacError(f"view address must be HOST:PORT with an IP address (e.g. 127.0.0.1:8080), "
                           f"got {text!r}") from None
    return host, number


def is_loopback(host: str) -> bool:
    """``host`` (an address to bind, or a Host header's host) is ``localhost`` or a loopback IP literal: what
    a page served on a loopback address may be asked for (any other name may be a DNS rebinding)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_of(header: str) -> str:
    """The host of a ``Host`` header: ``[::1]:8080`` -> ``::1``, ``127.0.0.2:8080`` -> ``127.0.0.2``."""
    header = header.strip()
    if header.startswith("["):
        return header[1:header.find("]")] if "]" in header else ""
    return header.rsplit(":", 1)[0] if ":" in header else header


class _DeadlineSocketReader(io.RawIOBase):
    """A socket's reads, each with the time left until :attr:`deadline` (monotonic s) as its timeout."""

    def __init__(self, sock: socket.socket) -> None:
        super().__init__()
        self._sock = sock
        self.deadline = time.monotonic() + TIMEOUT_S

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request took too long")
        self._sock.settimeout(left)
        return self._sock.recv_into(buffer)


def _assets() -> dict[str, bytes]:
    root = resources.files("optitac_edge.service.view") / "assets"
    return {name: (root / name).read_bytes() for name, _ in set(ASSETS.values())}


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 16

    def __init__(self, address: tuple[str, int], view: LiveView, token: str | None) -> None:
        self.view, self.token = view, token
        self.assets = _assets()
        self.connections = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.answering = threading.BoundedSemaphore(MAX_CLIENTS)
        self.refused = 0
        self.bad_requests = 0
        #: Clients that went away while being answered, or took too long to ask (counted, not logged).
        self.client_errors = 0
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        super().__init__(address, _Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.connections.acquire(blocking=False):  # too many connections: close at once, count it
            self.refused += 1
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.connections.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        lower_priority()
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.connections.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that went away or stalled is counted; anything else is one line (never a traceback)."""
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError, OSError)):
            self.client_errors += 1
            log.debug("view %s: %s", client_address[0] if client_address else "?", exc)
        else:
            log.warning("view: a request from %s failed: %s: %s", client_address[0] if client_address else "?",
                        type(exc).__name__, exc)


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = TIMEOUT_S
    protocol_version = "HTTP/1.1"
    server_version = "optitac-view"
    sys_version = ""

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("view %s: %s", self.client_address[0], format % args)

    def setup(self) -> None:
        super().setup()
        self._reader = _DeadlineSocketReader(self.connection)
        self.rfile = io.BufferedReader(self._reader)

    def handle_one_request(self) -> None:
        """One request within ``TIMEOUT_S`` in all, answered while one of ``MAX_CLIENTS`` slots is free."""
        self._reader.deadline = time.monotonic() + TIMEOUT_S
        try:
            super().handle_one_request()
        except TimeoutError:
            self.server.client_errors += 1
            self.close_connection = True
        finally:
            self._release()

    def parse_request(self) -> bool:
        ok = super().parse_request()  # the headers are in
        self.connection.settimeout(TIMEOUT_S)  # for the answer's writes (the reads had what was left)
        ok = ok and self._read_body()  # before a slot: a body that never comes must hold none
        if ok and not self.server.answering.acquire(timeout=TIMEOUT_S):
            self._refuse(HTTPStatus.SERVICE_UNAVAILABLE, "too many requests at once")
            return False
        self._answering = ok
        return ok

    def _read_body(self) -> bool:
        """Read the request's body (at most :data:`MAX_BODY` bytes, within the request's time); False after a
        refusal."""
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_BODY:
            self._refuse(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, "request body too large")
            return False
        if length:
            self.rfile.read(length)
        return True

    def _release(self) -> None:
        if getattr(self, "_answering", False):
            self._answering = False
            self.server.answering.release()

    # -- checks ---------------------------------------------------------------------------------

    def _refuse(self, status: HTTPStatus, why: str) -> None:
        self.server.bad_requests += 1
        self._send(status, why.encode() + b"\n", "text/plain; charset=utf-8", close=True)

    def _send(self, status: HTTPStatus, body: bytes, kind: str, close: bool = False, cache: bool = False) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", "default-src 'self'; img-src 'self' blob:; style-src 'self'")
        if close:
            self.send_header("Connection", "close")
            self.close_connection = True
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _checked(self) -> tuple[str, dict[str, list[str]]] | None:
        if len(self.path) > MAX_TARGET:
            self._refuse(HTTPStatus.REQUEST_URI_TOO_LONG, "request target too long")
            return None
        host = host_of(self.headers.get("Host") or "")
        bound = str(self.server.server_address[0])
        if is_loopback(bound) and not is_loopback(host):
            self._refuse(HTTPStatus.FORBIDDEN, "unexpected Host")
            return None
        parts = urlsplit(self.path)
        try:
            query = parse_qs(parts.query, strict_parsing=False, max_num_fields=4)
        except ValueError:
            self._refuse(HTTPStatus.BAD_REQUEST, "malformed query")
            return None
        return parts.path, query

    def _authorised(self) -> bool:
        if self.headers.get("X-OptiTac") != "1":
            self._refuse(HTTPStatus.FORBIDDEN, "missing X-OptiTac header")
            return False
        token = self.server.token
        given = self.headers.get("X-OptiTac-Token") or ""
        if token is not None and not hmac.compare_digest(given.encode(), token.encode()):
            self._refuse(HTTPStatus.FORBIDDEN, "a token is needed (printed when the view started)")
            return False
        return True

    # -- methods ----------------------------------------------------------------------------------

    def do_GET(self) -> None:
        checked = self._checked()
        if checked is None:
            return
        path, query = checked
        view = self.server.view
        if path in ASSETS:
            name, kind = ASSETS[path]
            self._send(HTTPStatus.OK, self.server.assets[name], kind, cache=False)
        elif path == "/api/layout":
            self._send(HTTPStatus.OK, view.layout_json(), "application/json")
        elif path == "/api/state":
            after = query.get("after", ["0"])[0]
            if not (after.isascii() and after.isdigit()) or len(after) > 12:  # '²' is a digit to isdigit()
                self._refuse(HTTPStatus.BAD_REQUEST, "after must be a number")
                return
            p = view.wait_published(int(after), timeout_s=1.0) or view.published
            self._send(HTTPStatus.OK, p.state if p is not None else b'{"seq":0}', "application/json")
        elif path == "/api/frame.jpg":
            p = view.published
            if p is None or not p.jpeg:
                self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"no frame yet\n", "text/plain; charset=utf-8")
            else:
                self._send(HTTPStatus.OK, p.jpeg, "image/jpeg")
        else:
            self._refuse(HTTPStatus.NOT_FOUND, "not found")

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_POST(self) -> None:
        checked = self._checked()
        if checked is None or not self._authorised():
            return
        path, query = checked
        view = self.server.view
        if path == "/api/tare":
            view.actions.append(("tare", None))
            self._send(HTTPStatus.OK, b'{"ok":true}', "application/json")
        elif path == "/api/snapshot":
            p = view.published
            if p is None:
                self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"no frame yet\n", "text/plain; charset=utf-8")
                return
            self._send(HTTPStatus.OK, encode_png(render_published(p, view.bundle)), "image/png")
        elif path == "/api/orient":
            what = query.get("do", [""])[0]
            if what not in ("start", "cancel"):
                self._refuse(HTTPStatus.BAD_REQUEST, "do must be start or cancel")
                return
            message = view.start_orientation() if what == "start" else view.cancel_orientation()
            self._send(HTTPStatus.OK, json.dumps({"message": message}).encode(), "application/json")
        else:
            self._refuse(HTTPStatus.NOT_FOUND, "not found")

    def _not_allowed(self) -> None:
        self._refuse(HTTPStatus.METHOD_NOT_ALLOWED, "method not allowed")

    do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_TRACE = do_CONNECT = _not_allowed


class ViewServer:
    """Serves a :class:`LiveView` on ``host:port`` from a daemon thread; ``close()`` stops it (idempotent).

    Parameters
    ----------
    view : LiveView
    bind : str
        ``HOST:PORT``; anything but a loopback address requires the token for actions.
    """

    def __init__(self, view: LiveView, bind: str = "127.0.0.1:8080") -> None:
        host, port = parse_bind(bind)
        self.token = None if is_loopback(host) else secrets.token_urlsafe(18)
        try:
            self._server = _Server((host, port), view, self.token)
        except OSError as exc:
            raise OptiTacError(f"view: cannot listen on {bind} ({exc.strerror or exc})") from None
        self.view = view
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="optitac-view-http", daemon=True)
        self._thread.start()
        self._closed = False

    @property
    def url(self) -> str:
        host, port = str(self._server.server_address[0]), int(self._server.server_address[1])
        shown = f"[{host}]" if ":" in host else host
        return f"http://{shown}:{port}/" + (f"?token={self.token}" if self.token else "")

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    @property
    def bad_requests(self) -> int:
        return self._server.bad_requests + self._server.refused

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
