"""ZeroMQ endpoints and CURVE key files: the address grammar, the loopback rule, ``ipc://`` socket
files, and key loading. The publisher (`thermod.runtime.publish`) and subscribers
(`thermod.client.subscriber`) check addresses and keys here and nowhere else.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import re
import socket
import stat
from pathlib import Path

import zmq
import zmq.auth

from thermod.errors import ThermodError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"


class TransportError(ThermodError):
    """The ZeroMQ endpoint could not be bound/connected, or a key file is unusable."""


_TCP = re.compile(r"^tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[^:\[\]/;]+):(?P<port>[^:/]+)$")


def endpoint_problem(endpoint) -> str | None:
    """What is wrong with ``endpoint`` as a ZeroMQ bind address, or None if it is well formed:
    ``tcp://HOST:PORT`` (HOST an address, ``[IPv6]``, a name or ``*``; PORT 1–65535 or ``*``),
    ``ipc://PATH`` or ``inproc://NAME``."""
    if not isinstance(endpoint, str):
        return "expected a string like 'tcp://127.0.0.1:5555'"
    scheme, sep, rest = endpoint.partition("://")
    if not sep or scheme not in ("tcp", "ipc", "inproc"):
        return "expected tcp://HOST:PORT, ipc://PATH or inproc://NAME"
    if not rest or any(c.isspace() or not c.isprintable() for c in rest):
        return f"the {scheme} address is empty or has blanks/control characters"
    if scheme != "tcp":
        return None
    m = _TCP.match(endpoint)
    if m is None:
        return "expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:5555 (IPv6: tcp://[::1]:5555)"
    port, host = m["port"], m["host"]
    if port != "*" and not (port.isdigit() and 1 <= int(port) <= 65535):
        return f"port {port!r} is not a number in 1–65535 (or * for any free port)"
    if host.startswith("["):
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            return f"{host} is not an IPv6 address"
    return None


def check_endpoint(endpoint: str, what: str = "publish.endpoint") -> str:
    """``endpoint`` unchanged, or `TransportError` naming ``what`` and the problem (`endpoint_problem`)."""
    problem = endpoint_problem(endpoint)
    if problem is not None:
        raise TransportError(f"{what} {endpoint!r}: {problem}")
    return endpoint


def is_loopback(endpoint: str) -> bool:
    """Only this host can reach it: ``ipc``/``inproc``, or tcp on a loopback address/``localhost``."""
    if not endpoint.startswith("tcp://"):
        return True
    m = _TCP.match(endpoint)
    host = m["host"].strip("[]") if m else ""
    if host in ("localhost", "lo"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # "*", an interface name or a host name: assume reachable from outside
        return False


def ipc_path(endpoint: str) -> str | None:
    """The socket file of a filesystem ``ipc://`` endpoint (not abstract ``@name`` nor wildcard ``*``)."""
    if not endpoint.startswith("ipc://"):
        return None
    path = endpoint[len("ipc://"):]
    return None if path.startswith("@") or path == "*" else path


def claim_ipc(path: str, what: str) -> None:
    """ZeroMQ's bind unlinks whatever is at ``path``, stealing a live daemon's socket. Refuse if
    something accepts connections there; remove a stale socket file nobody listens on."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    except OSError as e:
        raise TransportError(f"{what} ipc://{path}: cannot inspect the socket file ({e})") from None
    if not stat.S_ISSOCK(st.st_mode):
        raise TransportError(f"{what} ipc://{path}: exists and is not a socket; not replacing it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(1.0)
        probe.connect(path)
    except (ConnectionRefusedError, FileNotFoundError):
        live = False
    except OSError as e:  # e.g. permission denied: cannot tell, so do not touch it
        raise TransportError(f"{what} ipc://{path}: cannot probe the existing socket ({e})") from None
    else:
        live = True
    finally:
        probe.close()
    if live:
        raise TransportError(f"{what} ipc://{path}: another process is already publishing there "
                             "(is a second thermod running?); stop it or choose another endpoint")
    log.warning("removing stale socket file %s (nothing listening)", path)
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as e:
        raise TransportError(f"{what} ipc://{path}: cannot remove the stale socket file ({e})") from None


def load_keypair(path, what: str) -> tuple[bytes, bytes]:
    """(public, secret) of a CURVE certificate (``*.key_secret``, mode 0600); `what` names the setting."""
    try:
        public, secret = zmq.auth.load_certificate(os.fspath(path))
        mode = os.stat(path).st_mode
    except (OSError, ValueError) as e:
        raise TransportError(f"{what} {path}: cannot read CURVE certificate ({e}); make one with "
                             "zmq.auth.create_certificates(dir, name)") from None
    if secret is None:
        raise TransportError(f"{what} {path}: has no secret key; pass the '.key_secret' file")
    if mode & 0o077:
        raise TransportError(f"{what} {path}: the secret key is readable by group or others "
                             f"(mode {stat.S_IMODE(mode):04o}); chmod 600 it")
    return public, secret


def load_public_key(key) -> bytes:
    """A z85 public key given as bytes/str (40 chars) or as a path to a certificate file."""
    if isinstance(key, bytes) and len(key) == 40:
        return key
    if isinstance(key, str) and len(key) == 40 and not Path(key).exists():
        return key.encode("ascii")
    try:
        public, _ = zmq.auth.load_certificate(os.fspath(key))
    except (OSError, ValueError) as e:
        raise TransportError(f"CURVE server key {key}: expected a 40-character z85 key or a certificate "
                             f"file ({e})") from None
    return public
