"""The stand-ins' control channel: one JSON object per line each way, over a Unix socket.

Tests and the other stand-ins use it to inject faults (``drop_next``, ``stall``...) and to
read state (``dump``); it is not part of any device protocol. Server side: ``answer``
turns one request line into one reply line (a bad line gets ``{"ok": false, "error"}``
and never stops the stand-in) and ``serve_stream`` answers a connection until it closes.
Client side: ``Client`` keeps one connection and reconnects once when it broke;
``ask_once`` is a one-shot request.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Callable
from pathlib import Path

Handler = Callable[[dict], dict]


def answer(line: bytes, handle: Handler) -> bytes:
    """The reply line to one request line."""
    try:
        reply = handle(json.loads(line))
    except Exception as exc:  # report, never die on a bad control line
        reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
    return (json.dumps(reply) + "\n").encode()


def serve_stream(conn: socket.socket, handle: Handler) -> None:
    """Answer every line on ``conn`` until the peer closes it."""
    with conn, conn.makefile("rwb") as stream:
        for line in stream:
            stream.write(answer(line, handle))
            stream.flush()


def listen(path: str | Path, backlog: int = 4) -> socket.socket:
    """A listening Unix socket at ``path`` (a stale socket file is replaced)."""
    path = Path(path)
    if path.exists():
        path.unlink()
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(backlog)
    return server


class Client:
    """A persistent client of one control socket."""

    def __init__(self, path: str | None, timeout: float = 1.0) -> None:
        self.path = path
        self.timeout = timeout
        self.sock: socket.socket | None = None
        self.buf = b""

    def ask(self, request: dict) -> dict | None:
        """The reply to ``request``, or None when there is no socket or it does not
        answer (one reconnection is tried)."""
        if not self.path:
            return None
        for _ in range(2):
            try:
                if self.sock is None:
                    self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                    self.sock.settimeout(self.timeout)
                    self.sock.connect(self.path)
                    self.buf = b""
                self.sock.sendall((json.dumps(request) + "\n").encode())
                while b"\n" not in self.buf:
                    chunk = self.sock.recv(65536)
                    if not chunk:
                        raise ConnectionError
                    self.buf += chunk
                line, self.buf = self.buf.split(b"\n", 1)
                return json.loads(line)
            except (OSError, ConnectionError, json.JSONDecodeError):
                self.close()
        return None

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        self.sock = None


def ask_once(path: str, request: dict, timeout: float = 5.0) -> dict:
    """One request on a fresh connection; raises when the stand-in does not answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(path)
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                raise ConnectionError(f"{path}: closed before answering {request}")
            data += chunk
    return json.loads(data)
