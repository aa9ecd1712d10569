"""The live page: a read-only HTTP server (standard library) showing the calibration as it grows.

``streamcal daemon|serial … --http [HOST:]PORT`` starts it. Routes (GET only):

- ``/``: the page (``static/live.html``: HTML, CSS and JS in one small file, with
  ``static/sphere3d.js``, the rotatable 3-D sphere, and the latest snapshot inlined, so the page
  shows figures before its first event arrives).
- ``/events``: Server-Sent Events (``text/event-stream``), one ``data:`` line of JSON
  (:mod:`.live_state` snapshot) per capture, at most ``1/period_s`` per second; a comment line
  every 10 s keeps proxies from closing an idle stream.
- ``/state.json``: the latest snapshot once.

Nothing is loaded from elsewhere: the page works without any external network. Bound to
127.0.0.1 unless a host is given; with ``token`` every request must carry it (``?token=`` or an
``X-Streamcal-Token`` header), else 403. Limits (memory bounded, ingest never waits):

- at most ``max_clients`` event streams (16): one more gets 503 with a message saying so;
- at most ``max_connections`` connections in progress (64): beyond, 503 before any parsing;
- each stream has a queue of ``queue_len`` events; a client that does not keep up (its queue full)
  is dropped and its socket shut, and every socket has a ``timeout_s`` send/receive timeout;
- a stream whose client has closed its end frees its slot within ``PEER_CHECK_S`` (0.2 s), even
  when no event is due (an SSE client sends nothing after its request, so end-of-file on the
  socket means it left);
- a request line or header that is not HTTP gets 400; an unknown path 404; other methods 501.

The snapshot is built (:meth:`LiveState.build`) and serialised once per capture on the publisher
thread, then the same bytes are queued for every client; the service loop only copies.
"""
from __future__ import annotations

import hmac
import json
import queue
import select
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

MAX_CLIENTS = 16
MAX_CONNECTIONS = 64
QUEUE_LEN = 8
TIMEOUT_S = 5.0
KEEPALIVE_S = 10.0
PEER_CHECK_S = 0.2
_BUSY = (b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
         b"Connection: close\r\n\r\nstreamcal live page: too many connections; try again later\n")


def parse_http(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` → (host, port); host 127.0.0.1 when absent (``[::1]:8080`` for IPv6)."""
    from ..errors import InputError

    host, sep, port = text.rpartition(":")
    if not sep:
        host = "127.0.0.1"
    host = host.strip("[]") or "127.0.0.1"
    try:
        value = int(port)
    except ValueError:
        raise InputError(f"--http: expected [HOST:]PORT such as 8080 or 0.0.0.0:8080, got "
                         f"{text!r}") from None
    if not 0 <= value <= 65535:
        raise InputError(f"--http: port must be 0..65535, got {value}")
    return host, value


def is_loopback(host: str) -> bool:
    return host in ("localhost", "::1") or host.startswith("127.")


class _Client:
    def __init__(self, conn, queue_len: int):
        self.conn = conn
        self.queue: queue.Queue = queue.Queue(maxsize=queue_len)
        self.dropped = False

    def drop(self) -> None:
        self.dropped = True
        try:
            self.conn.shutdown(socket.SHUT_RDWR)     # wakes a handler blocked in send
        except OSError:
            pass


class LivePage:
    """Serve ``state`` (a :class:`~streamcal.service.live_state.LiveState`) over HTTP.

    Args:
        state: the observer the service loop feeds.
        host, port: where to listen (port 0: any free port; :attr:`address` tells which).
        token: required on every request when given.
        max_clients, max_connections, queue_len, timeout_s: limits (module docstring).
    """

    def __init__(self, state, host: str = "127.0.0.1", port: int = 0, *, token: str | None = None,
                 max_clients: int = MAX_CLIENTS, max_connections: int = MAX_CONNECTIONS,
                 queue_len: int = QUEUE_LEN, timeout_s: float = TIMEOUT_S):
        self.state, self.token = state, token
        self.max_clients, self.max_connections = int(max_clients), int(max_connections)
        self.queue_len, self.timeout_s = int(queue_len), float(timeout_s)
        self._lock = threading.Lock()
        self._clients: set[_Client] = set()
        self._connections = 0
        self.latest = b""                # the last event's JSON, UTF-8
        self.published = 0               # the state's capture number ``latest`` was built from
        self._published = threading.Condition()
        self.stats = {"streams": 0, "refused_busy": 0, "dropped_slow": 0, "events": 0,
                      "bad_requests": 0, "forbidden": 0, "not_found": 0, "build_errors": 0}
        self._stop = threading.Event()
        server_cls = _Server6 if ":" in host else _Server
        try:
            self.server = server_cls((host, port), _Handler)
        except OSError as exc:
            from ..errors import InputError
            raise InputError(f"--http {host}:{port}: cannot listen ({exc.strerror or exc})") \
                from None
        self.server.page = self
        self._threads = [threading.Thread(target=self.server.serve_forever, kwargs={
                             "poll_interval": 0.2}, name="live-http", daemon=True),
                         threading.Thread(target=self._publish, name="live-publish", daemon=True)]

    @property
    def address(self) -> tuple[str, int]:
        return self.server.server_address[:2]

    @property
    def url(self) -> str:
        host, port = self.address
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{port}/"

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    def start(self) -> "LivePage":
        for t in self._threads:
            t.start()
        return self

    def wait_published(self, seq: int, timeout: float) -> bool:
        """Block until capture ``seq`` (or a later one) is what the page serves; False after
        ``timeout`` s."""
        with self._published:
            return self._published.wait_for(lambda: self.published >= seq, timeout)

    def close(self) -> None:
        self._stop.set()
        self.server.shutdown()
        self.server.server_close()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.drop()

    # -- publisher --------------------------------------------------------------------------------
    def _publish(self) -> None:
        seq = 0
        while not self._stop.is_set():
            new = self.state.wait(seq, timeout=0.5)
            if new == seq:
                continue
            seq = new
            try:
                snap = self.state.build()
                if snap is None:
                    continue
                data = json.dumps(snap, separators=(",", ":"), allow_nan=False).encode()
            except Exception:          # a bad capture must not stop the page
                self.stats["build_errors"] += 1
                continue
            self.latest = data
            with self._published:
                self.published = new
                self._published.notify_all()
            self.stats["events"] += 1
            with self._lock:
                clients = list(self._clients)
            for c in clients:
                try:
                    c.queue.put_nowait(data)
                except queue.Full:
                    self._remove(c, slow=True)

    # -- client registry ----------------------------------------------------------------------------
    def _add(self, conn) -> _Client | None:
        with self._lock:
            if len(self._clients) >= self.max_clients:
                self.stats["refused_busy"] += 1
                return None
            c = _Client(conn, self.queue_len)
            self._clients.add(c)
            self.stats["streams"] += 1
            return c

    def _remove(self, c: _Client, slow: bool = False) -> None:
        with self._lock:
            present = c in self._clients
            self._clients.discard(c)
            if present and slow:
                self.stats["dropped_slow"] += 1
        if slow:
            c.drop()

    def authorised(self, query: dict, headers) -> bool:
        if self.token is None:
            return True
        given = (query.get("token") or [""])[0] or headers.get("X-Streamcal-Token", "")
        return hmac.compare_digest(given.encode(), self.token.encode())


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False
    request_queue_size = 64
    page: LivePage

    def process_request(self, request, client_address):
        page = self.page
        with page._lock:
            busy = page._connections >= page.max_connections
            if not busy:
                page._connections += 1
        if busy:
            page.stats["refused_busy"] += 1
            try:
                request.settimeout(0.5)
                request.sendall(_BUSY)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            with page._lock:
                page._connections -= 1
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self.page._lock:
                self.page._connections -= 1


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server_version = "streamcal-live"
    sys_version = ""
    protocol_version = "HTTP/1.0"

    def setup(self):
        self.timeout = self.server.page.timeout_s
        super().setup()

    def log_message(self, format, *args):      # noqa: A002 — no access log on the journal
        pass

    error_message_format = "streamcal live page: %(code)d %(message)s\n"
    error_content_type = "text/plain; charset=utf-8"

    def send_error(self, code, message=None, explain=None):
        if code == 400:
            self.server.page.stats["bad_requests"] += 1
        # A one-word request line parses as HTTP/0.9, which would get a bare body: answer with
        # a status line and headers whatever came in.
        self.request_version = "HTTP/1.0"
        super().send_error(code, message, explain)

    def _plain(self, status: HTTPStatus, text: str) -> None:
        body = (text + "\n").encode()
        self.send_response(status)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _body(self, ctype: str, body: bytes) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self):
        page = self.server.page
        try:
            url = urlsplit(self.path)
            query = parse_qs(url.query, max_num_fields=8)
        except ValueError:
            self.send_error(HTTPStatus.BAD_REQUEST, "unparseable request target")
            return
        if not page.authorised(query, self.headers):
            page.stats["forbidden"] += 1
            self._plain(HTTPStatus.FORBIDDEN, "streamcal live page: missing or wrong token "
                        "(add ?token=… to the address)")
            return
        if url.path in ("/", "/index.html"):
            self._body("text/html; charset=utf-8", _page_html(page.latest))
        elif url.path == "/events":
            self._events(page)
        elif url.path == "/state.json":
            self._body("application/json", page.latest or b"null")
        else:
            page.stats["not_found"] += 1
            self._plain(HTTPStatus.NOT_FOUND, f"streamcal live page: no such page {url.path!r}; "
                        "try / or /events")

    def _events(self, page: LivePage) -> None:
        client = page._add(self.connection)
        if client is None:
            self._plain(HTTPStatus.SERVICE_UNAVAILABLE,
                        f"streamcal live page: {page.max_clients} live views are open already "
                        "(the most this service serves); close one and reload")
            return
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            first = b"retry: 2000\n\n"
            if page.latest:
                first += b"data: " + page.latest + b"\n\n"
            self.wfile.write(first)
            self.wfile.flush()
            keepalive_at = time.monotonic() + KEEPALIVE_S
            while not client.dropped:
                try:
                    chunk = b"data: " + client.queue.get(timeout=PEER_CHECK_S) + b"\n\n"
                except queue.Empty:
                    chunk = None
                if client.dropped or _peer_closed(self.connection):
                    break
                if chunk is None:
                    if time.monotonic() < keepalive_at:
                        continue
                    chunk = b": keepalive\n\n"
                self.wfile.write(chunk)
                self.wfile.flush()
                keepalive_at = time.monotonic() + KEEPALIVE_S
        except (OSError, ValueError):        # the client left, or its socket was shut
            pass
        finally:
            page._remove(client)
            self.close_connection = True


def _peer_closed(conn) -> bool:
    """True when the peer has closed its end (readable with nothing to read) or the socket failed."""
    try:
        poller = select.poll()                  # not select.select: descriptors may pass 1024
        poller.register(conn, select.POLLIN)
        return bool(poller.poll(0)) and conn.recv(1, socket.MSG_PEEK) == b""
    except (OSError, ValueError):
        return True


_TEMPLATE: str | None = None


def _page_html(latest: bytes) -> bytes:
    global _TEMPLATE
    if _TEMPLATE is None:
        static = resources.files("streamcal.service").joinpath("static")
        sphere = static.joinpath("sphere3d.js").read_text(encoding="utf-8")
        _TEMPLATE = static.joinpath("live.html").read_text(encoding="utf-8").replace(
            "/*SPHERE3D*/", sphere, 1)     # the script holds no "</"
    # JSON inside <script>: "</" cannot close the element once escaped.
    initial = (latest.decode() if latest else "null").replace("</", "<\\/")
    return _TEMPLATE.replace("/*INITIAL*/null", initial, 1).encode("utf-8")
