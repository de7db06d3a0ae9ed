"""systemd notification protocol (sd_notify(3)) without libsystemd.

A service with ``Type=notify`` gets ``$NOTIFY_SOCKET``: an AF_UNIX datagram socket, a path or an
abstract name written with a leading ``@``. Each datagram is newline-separated ``KEY=VALUE`` lines:
``READY=1`` once the first frames and samples arrived, ``STATUS=…`` free text for ``systemctl
status``, ``WATCHDOG=1`` at least every ``$WATCHDOG_USEC``/2 while every critical thread is alive,
``STOPPING=1`` on shutdown. Outside systemd every call is a cheap no-op.

Example::

    n = Notifier()
    n.ready(status="50.0 fps, gyro 1000 Hz")
    interval = n.watchdog_interval()       # None when the unit has no WatchdogSec=
    ...
    if all_threads_alive:
        n.watchdog()
"""

from __future__ import annotations

import logging
import os
import socket
import threading

log = logging.getLogger(__name__)


def _address(name: str) -> str | bytes:
    # "@foo" is the abstract socket "\0foo" (Linux); anything else is a filesystem path.
    return b"\0" + name[1:].encode() if name.startswith("@") else name


class Notifier:
    """Sends sd_notify messages to ``$NOTIFY_SOCKET`` (or ``socket_path``).

    Parameters
    ----------
    socket_path : str, optional
        Defaults to ``$NOTIFY_SOCKET``; when neither is set, `enabled` is False and nothing is sent.
    env : mapping, optional
        Where to read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` (default ``os.environ``).

    Send failures are counted in `errors` and logged once: a missing notification must never take
    the daemon down (systemd will act on the missing watchdog ping by itself).
    """

    def __init__(self, socket_path: str | None = None, *, env=None):
        env = os.environ if env is None else env
        self._env = env
        self.socket_path = socket_path if socket_path is not None else env.get("NOTIFY_SOCKET") or None
        self.errors = 0
        self.sent = 0
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        return self.socket_path is not None

    def notify(self, *lines: str, **fields) -> bool:
        """Send one datagram of ``lines`` plus ``KEY=value`` fields; True if it went out."""
        if not self.enabled:
            return False
        parts = list(lines) + [f"{k}={v}" for k, v in fields.items()]
        msg = "\n".join(parts).encode("utf-8")
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                    # never block the caller (the daemon's main loop) on a full receive queue
                    self._sock.setblocking(False)
                self._sock.sendto(msg, _address(self.socket_path))
            except OSError as e:
                self.errors += 1
                if self.errors == 1:
                    log.warning("sd_notify to %s failed: %s (further failures are only counted)",
                                self.socket_path, e)
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        """READY=1 (and optionally STATUS): systemd then considers the unit started."""
        extra = {"STATUS": _one_line(status)} if status is not None else {}
        return self.notify("READY=1", **extra)

    def status(self, text: str) -> bool:
        """STATUS=… shown by ``systemctl status`` (one line)."""
        return self.notify(STATUS=_one_line(text))

    def watchdog(self) -> bool:
        """WATCHDOG=1: call only while every critical thread is alive."""
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        extra = {"STATUS": _one_line(status)} if status is not None else {}
        return self.notify("STOPPING=1", **extra)

    def reloading(self) -> bool:
        return self.notify("RELOADING=1")

    def extend_timeout(self, seconds: float) -> bool:
        """EXTEND_TIMEOUT_USEC: e.g. while the simulated payload pre-renders its loop at first start."""
        return self.notify(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def watchdog_usec(self) -> int | None:
        """$WATCHDOG_USEC if the watchdog is meant for this process (sd_watchdog_enabled(3)), else None."""
        usec = self._env.get("WATCHDOG_USEC")
        if not usec:
            return None
        pid = self._env.get("WATCHDOG_PID")
        try:
            if pid and int(pid) != os.getpid():
                return None
            value = int(usec)
        except ValueError:
            log.warning("ignoring malformed WATCHDOG_USEC=%r / WATCHDOG_PID=%r", usec, pid)
            return None
        return value if value > 0 else None

    def watchdog_interval(self) -> float | None:
        """Seconds between pings: half the watchdog timeout, as sd_watchdog_enabled(3) recommends."""
        usec = self.watchdog_usec()
        return None if usec is None else usec / 2e6

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def _one_line(text) -> str:
    return " ".join(str(text).split())
