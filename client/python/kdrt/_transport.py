"""Connections, retries and errors: the HTTP part of kdrt.Client, on the standard library's
http.client (no third-party HTTP package: the client needs keep-alive connections it can hand to
worker threads, bodies sent from numpy buffers without copies, and answers read straight into
numpy arrays with readinto(); http.client does all three).

Semantics follow the C++ client (client/src/http_client.cpp): connection errors and 503 answers
are retried with exponential backoff (Retry-After honoured up to a cap); a request that may have
reached the server is resent only when it is idempotent; every other non-2xx answer becomes a
kdrt.Error carrying the problem+json fields.
"""

from __future__ import annotations

import http.client
import os
import select
import socket
import ssl
import sys
import threading
import time
import urllib.parse

from ._errors import Error

#: Largest error body read (a problem+json refusal, a proxy's error page).
MAX_ERROR_BODY = 1 << 20
#: Bytes read from a file and sent at a time when a file is the request body.
FILE_BLOCK = 1 << 20


#: Answers up to this size may be read into a reused buffer (BodyBuffers).
MAX_POOLED_BODY = 64 << 20
#: Buffers BodyBuffers keeps: an answer in use, the next one read, and a spare per connection.
POOLED_BUFFERS = 4


class BodyBuffers:
    """Reused buffers for large binary answers (a scan's 3 MB point cloud). A fresh buffer of
    that size costs the kernel a page fault on every 4 KiB page as the answer is copied in, and
    on some virtual machines a fault costs ~10 us: 9 ms to read a 3 MB answer against 0.7 ms into
    memory already faulted in. take(n) hands out a view of n bytes of a kept buffer that nothing
    views any more (no memoryview of it, so no numpy array made from one, is alive), else of a
    new buffer, kept while fewer than POOLED_BUFFERS are. Thread-safe."""

    def __init__(self, keep=POOLED_BUFFERS):
        self._keep = keep
        self._buffers = []
        self._lock = threading.Lock()

    def take(self, n: int) -> memoryview:
        with self._lock:
            spare = None
            for buf in self._buffers:
                # Unused when referenced by the list, `buf` and getrefcount's argument only: a
                # view (a memoryview holds a reference to the bytearray it exports) is not alive.
                if sys.getrefcount(buf) == 3:
                    if len(buf) >= n:
                        return memoryview(buf)[:n]
                    spare = buf
            if spare is not None:  # too small: give its place to a larger one
                self._buffers.remove(spare)
            # Room for answers up to an eighth larger (a scan's returns vary from frame to
            # frame), in whole MiB.
            fresh = bytearray(-(-(n + n // 8) // (1 << 20)) << 20)
            if len(self._buffers) < self._keep:
                self._buffers.append(fresh)
            return memoryview(fresh)[:n]


def read_pooled(pool: BodyBuffers):
    """A Transport.request `read` for binary answers: (status, headers, body) as the default
    read, the body a memoryview of a buffer from `pool` when the answer states its length (and
    is at most MAX_POOLED_BODY), else bytes."""

    def read(response):
        length = response.getheader("Content-Length")
        if length is None or not length.isdigit() or int(length) > MAX_POOLED_BODY:
            return response.status, response.headers, response.read()
        body = pool.take(int(length))
        got = 0
        while got < len(body):
            step = response.readinto(body[got:])
            if not step:
                raise http.client.IncompleteRead(b"", len(body) - got)
            got += step
        return response.status, response.headers, body

    return read


class FileBody:
    """A file as (part of) a request body: streamed from disk in FILE_BLOCK pieces, from its
    start again on every attempt. Raises kdrt.Error "input" if the file cannot be opened."""

    def __init__(self, path):
        self.path = os.fspath(path)
        try:
            self.size = os.path.getsize(self.path)
            with open(self.path, "rb"):
                pass
        except OSError as exc:
            raise Error(kind="input", title="cannot upload",
                        detail=f'cannot read "{self.path}": {exc.strerror}') from None

    def send(self, connection):
        sent = 0
        with open(self.path, "rb") as f:
            while sent < self.size:
                block = f.read(min(FILE_BLOCK, self.size - sent))
                if not block:
                    break
                connection.send(block)
                sent += len(block)
        if sent != self.size:
            raise Error(kind="input", title="cannot upload",
                        detail=f'reading "{self.path}" failed while it was sent (the file '
                        f"changed size)")


def _part_size(part) -> int:
    return part.size if isinstance(part, FileBody) else memoryview(part).nbytes


class ServerUrl:
    """http://HOST[:PORT][/PREFIX], https://..., or a bare HOST[:PORT] (http)."""

    def __init__(self, text: str):
        original = text
        if "://" not in text:
            text = "http://" + text
        parts = urllib.parse.urlsplit(text)
        scheme = parts.scheme.lower()
        if scheme not in ("http", "https"):
            raise ValueError(f"server URL {original!r}: unknown scheme {parts.scheme!r} "
                             f"(expected http or https)")
        if parts.query or parts.fragment:
            raise ValueError(f"server URL {original!r}: a query or fragment is not allowed")
        if not parts.hostname:
            raise ValueError(f"server URL {original!r}: empty host")
        try:
            port = parts.port
        except ValueError:
            raise ValueError(f"server URL {original!r}: the port is not 1 .. 65535") from None
        if port == 0:
            raise ValueError(f"server URL {original!r}: the port is not 1 .. 65535")
        self.scheme = scheme
        self.host = parts.hostname
        self.port = port or (443 if scheme == "https" else 80)
        self.base_path = parts.path.rstrip("/")

    def __str__(self):
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}{self.base_path}"


class _Connection:
    """One keep-alive connection (http.client's) with TCP_NODELAY and the I/O timeout."""

    def __init__(self, url: ServerUrl, connect_timeout: float, io_timeout: float):
        if url.scheme == "https":
            self.http = http.client.HTTPSConnection(url.host, url.port, timeout=connect_timeout,
                                                    context=ssl.create_default_context())
        else:
            self.http = http.client.HTTPConnection(url.host, url.port, timeout=connect_timeout)
        self.io_timeout = io_timeout
        self.used = False  # True once an exchange completed on the open socket

    def connect(self):
        self.http.connect()
        sock = self.http.sock
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(self.io_timeout)
        self.used = False

    def usable(self) -> bool:
        """False when the kept-alive socket was closed by the server (it reads as EOF) or has
        unexpected bytes: then a new connection is made."""
        sock = self.http.sock
        if sock is None:
            return False
        try:
            readable, _, _ = select.select([sock], [], [], 0)
        except (OSError, ValueError):
            return False
        return not readable

    def close(self):
        self.http.close()
        self.used = False


def _reason(exc: BaseException) -> str:
    if isinstance(exc, socket.timeout):
        return "timed out"
    if isinstance(exc, socket.gaierror):
        return exc.strerror or str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


class Transport:
    def __init__(self, url: str, token, timeout, connect_timeout, max_retries, backoff_initial,
                 backoff_max, max_retry_after, connections):
        self.url = ServerUrl(url)
        self.token = token
        self.timeout = timeout
        self.connect_timeout = connect_timeout
        self.max_retries = max_retries
        self.backoff_initial = backoff_initial
        self.backoff_max = backoff_max
        self.max_retry_after = max_retry_after
        self.connections = connections
        self._idle = []
        self._lock = threading.Lock()
        self.bodies = BodyBuffers()  # for read_pooled

    def api(self, path: str) -> str:
        return self.url.base_path + path

    # ---- The connection pool ----------------------------------------------------------------

    def acquire(self) -> _Connection:
        with self._lock:
            if self._idle:
                return self._idle.pop()
        return _Connection(self.url, self.connect_timeout, self.timeout)

    def release(self, conn: _Connection):
        with self._lock:
            # More idle connections than chunks in flight would only hold server threads.
            if len(self._idle) < max(1, self.connections):
                self._idle.append(conn)
                return
        conn.close()

    def close(self):
        with self._lock:
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()

    def backoff(self, retry: int) -> float:
        return min(self.backoff_initial * (2 ** retry), self.backoff_max)

    # ---- One exchange, with retries ---------------------------------------------------------

    def request(self, method, path, body=(), content_type=None, headers=None, read=None,
                resend=True, retry_unavailable=True, conn=None):
        """Sends `method path` with `body` (a list of bytes-like parts, sent without copying) and
        returns read(response) for a 2xx answer (default: the body as bytes, with the status and
        headers: (status, headers, body)). Retries connection errors (and, when `resend`, errors
        after the request may have been sent) and 503 answers; raises kdrt.Error otherwise. Uses
        `conn` when given (the caller's pooled connection), else one from the pool."""
        own = conn is None
        if own:
            conn = self.acquire()
        try:
            return self._request(conn, method, path, body, content_type, headers or {}, read,
                                 resend, retry_unavailable)
        finally:
            if own:
                self.release(conn)

    def _request(self, conn, method, path, body, content_type, headers, read, resend,
                 retry_unavailable):
        attempts_allowed = self.max_retries + 1
        attempt = 0
        while True:
            attempt += 1
            stage = "connect"
            try:
                if not conn.usable():
                    conn.close()
                    conn.connect()
                try:
                    stage = "send"
                    self._send(conn, method, path, body, content_type, headers)
                    stage = "read"
                    response = conn.http.getresponse()
                except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                    if not conn.used or not resend:
                        raise
                    # The server closed the kept-alive connection as the request went out; it
                    # never saw the request: send it once more on a new connection. (Not for a
                    # request that must not be sent twice: then it is a connection error.)
                    conn.close()
                    stage = "connect"
                    conn.connect()
                    stage = "send"
                    self._send(conn, method, path, body, content_type, headers)
                    stage = "read"
                    response = conn.http.getresponse()
                status = response.status
                if 200 <= status < 300:
                    try:
                        result = read(response) if read else (
                            status, response.headers, response.read())
                    except Error:
                        conn.close()  # the answer was refused half read: never reuse
                        raise
                    conn.used = True
                    if response.will_close:
                        conn.close()
                    return result
                answer = response.read(MAX_ERROR_BODY)
                if not response.isclosed() or response.will_close:
                    conn.close()  # unread rest, or the server closes: do not reuse
                else:
                    conn.used = True
                if status == 503 and retry_unavailable and attempt < attempts_allowed:
                    delay = self.backoff(attempt - 1)
                    after = response.getheader("Retry-After", "")
                    if after.isdigit():
                        delay = min(float(after), self.max_retry_after)
                    time.sleep(delay)
                    continue
                err = Error.from_response(status, response.getheader("Content-Type", ""),
                                          answer, response.getheader("X-Request-Id", ""))
                err.attempts = attempt
                raise err
            except Error:
                if conn.http.sock is not None and stage != "read":
                    conn.close()  # a body left half sent
                raise
            except (OSError, http.client.HTTPException) as exc:
                conn.close()
                before_sending = stage == "connect"
                retriable = before_sending or resend
                if not retriable or attempt >= attempts_allowed:
                    raise self._transport_error(exc, stage, method, path, attempt) from None
                time.sleep(self.backoff(attempt - 1))

    def _send(self, conn, method, path, body, content_type, headers):
        h = conn.http
        h.putrequest(method, path, skip_accept_encoding=True)
        total = sum(_part_size(part) for part in body)
        if method == "POST" or total:
            h.putheader("Content-Length", str(total))
        if content_type:
            h.putheader("Content-Type", content_type)
        h.putheader("Accept", "*/*")
        h.putheader("User-Agent", "kdrt-python")
        if self.token:
            h.putheader("Authorization", "Bearer " + self.token)
        for name, value in headers.items():
            h.putheader(name, value)
        h.endheaders()
        for part in body:
            if isinstance(part, FileBody):
                part.send(h)
            elif _part_size(part):
                h.send(part)

    def _transport_error(self, exc, stage, method, path, attempts) -> Error:
        what = {
            "connect": "could not connect",
            "send": "the connection closed or timed out while sending the request",
            "read": "the connection closed or timed out while reading the answer",
        }[stage]
        if stage == "connect" and isinstance(exc, socket.timeout):
            what = "the connection timed out"
        title = "cannot connect" if stage == "connect" else "connection failed"
        detail = (f"{self.url}: {what}: {_reason(exc)} ({method} {path}, {attempts} "
                  f"{'attempt' if attempts == 1 else 'attempts'})")
        return Error(kind="connection", title=title, detail=detail, attempts=attempts)
