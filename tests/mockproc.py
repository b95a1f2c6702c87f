"""Start a stand-in as its own process, read its JSON ready line, stop it by PID."""

from __future__ import annotations

import json

from rigctl.childproc import ROOT, ChildProcess

__all__ = ["ROOT", "MockProcess", "control"]


class MockProcess(ChildProcess):
    """A stand-in under test: stderr captured for the failure message."""

    def __init__(self, args: list[str], ready_timeout: float = 15.0) -> None:
        super().__init__(args, ready_timeout, capture_stderr=True)


def control(path: str, request: dict, timeout: float = 5.0) -> dict:
    import socket

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(path)
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    return json.loads(data)
