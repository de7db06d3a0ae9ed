"""The addresses thermod serves on and their security: the ZeroMQ endpoint and RTSP URL grammars, the
transport defaults, the loopback rule, the CURVE rule, ``ipc://`` socket files, and key loading. The
configuration (`thermod.runtime.config`), the publisher (`thermod.runtime.publish`), the RTSP server, the
web view and subscribers (`thermod.client`) check addresses and keys here and nowhere else.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import re
import socket
import stat
import urllib.parse
from pathlib import Path

from thermod.errors import ThermodError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"
DEFAULT_HWM = 100                     # messages ZeroMQ queues per subscriber (SNDHWM)
DEFAULT_MAX_QUEUE_BYTES = 128 << 20   # bytes ZeroMQ may hold for all subscribers together
DEFAULT_RTSP_URL = "rtsp://127.0.0.1:8554/thermal"


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


def is_loopback_host(host: str) -> bool:
    """Only this host can reach a server bound to `host`: a loopback address (``[::1]`` brackets allowed),
    ``localhost``, or the loopback interface ``lo``. Anything else (``*``, ``0.0.0.0``, a name, another
    interface) is taken as reachable from the network."""
    host = host.strip("[]")
    if host in ("localhost", "lo"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_loopback(endpoint: str) -> bool:
    """Only this host can reach it: ``ipc``/``inproc``, or tcp on a loopback host (`is_loopback_host`)."""
    if not endpoint.startswith("tcp://"):
        return True
    m = _TCP.match(endpoint)
    return m is not None and is_loopback_host(m["host"])


def security_problem(endpoint: str, secret_key: bool, authorized_keys: bool,
                     allow_insecure_remote: bool) -> tuple[str, str] | None:
    """The CURVE rule: (publish setting at fault, what it needs), or None when the settings are safe.
    Client authentication runs inside the CURVE handshake, so authorized keys need the secret key; a
    bind beyond loopback without CURVE lets anyone on the network read the stream, so it needs an
    explicit ``allow_insecure_remote``."""
    if authorized_keys and not secret_key:
        return ("curve_secret_key", "missing (curve_authorized_keys needs the server's secret key file: "
                "client authentication runs inside the CURVE handshake)")
    if not secret_key and not is_loopback(endpoint) and not allow_insecure_remote:
        return ("endpoint", "expected a loopback or ipc:// address, or publish.curve_secret_key for CURVE, "
                "or publish.allow_insecure_remote = true (bound beyond loopback without CURVE, anyone on "
                f"the network could read the stream), got {endpoint!r}")
    return None


def rtsp_url_problem(url) -> str | None:
    """What is wrong with `url` as the RTSP address to serve (``rtsp://HOST:PORT/PATH``), or None."""
    try:
        split_rtsp_url(url)
    except ValueError as e:
        return str(e)
    return None


def split_rtsp_url(url: str) -> tuple[str, int, str]:
    """``rtsp://HOST:PORT/PATH`` → (host, port, mount path); anything else is a ValueError."""
    u = urllib.parse.urlsplit(url)
    try:
        port = u.port
    except ValueError:
        port = -1
    if u.scheme != "rtsp" or not u.hostname or port is None or not 0 < port < 65536 \
            or len(u.path) < 2 or u.query or u.fragment:
        raise ValueError("a URL like rtsp://127.0.0.1:8554/thermal (host, port and path)")
    return u.hostname, port, u.path


def ipc_path(endpoint: str) -> str | None:
    """The socket file of a filesystem ``ipc://`` endpoint (not abstract ``@name`` nor wildcard ``*``)."""
    if not endpoint.startswith("ipc://"):
        return None
    path = endpoint[len("ipc://"):]
    return None if path.startswith("@") or path == "*" else path


def listening(endpoint: str, timeout: float = 1.0) -> bool | None:
    """Whether something accepts connections at ``endpoint`` (a bound publisher, even one still
    starting up and silent): False when the connection is refused or the ``ipc://`` file is missing,
    None when it cannot tell (``inproc``, an unresolvable name, a timeout)."""
    if (path := ipc_path(endpoint)) is not None:
        family, address = socket.AF_UNIX, path
    elif (m := _TCP.match(endpoint)) is not None and m["port"].isdigit():
        family, address = socket.AF_INET6 if m["host"].startswith("[") else socket.AF_INET, \
            (m["host"].strip("[]"), int(m["port"]))
    else:
        return None
    probe = socket.socket(family, socket.SOCK_STREAM)
    try:
        probe.settimeout(timeout)
        probe.connect(address)
    except (ConnectionRefusedError, FileNotFoundError):
        return False
    except OSError:
        return None
    finally:
        probe.close()
    return True


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
    import zmq.auth  # the transport only where keys are read: the rest of io stays free of it

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
    import zmq.auth

    try:
        public, _ = zmq.auth.load_certificate(os.fspath(key))
    except (OSError, ValueError) as e:
        raise TransportError(f"CURVE server key {key}: expected a 40-character z85 key or a certificate "
                             f"file ({e})") from None
    return public
