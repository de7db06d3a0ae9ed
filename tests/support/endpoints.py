"""Endpoints for the daemons tests start.

`private_endpoint` is an ``ipc://`` socket no other process can hold: a free TCP port found by binding
and closing it can be taken by another test's daemon (pytest-xdist) before ours binds it, and a
subscriber may then read that daemon (seen: a recording with another daemon's calibration). Use
`free_port` only where TCP is the point (RTSP, HTTP)."""

import socket
import tempfile
import uuid


def private_endpoint() -> str:
    """A publish endpoint of its own (the daemon removes the socket file when it closes)."""
    return f"ipc://{tempfile.gettempdir()}/thermod-test-{uuid.uuid4().hex[:16]}.sock"


def free_port() -> int:
    """A loopback TCP port free at the time of asking."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
