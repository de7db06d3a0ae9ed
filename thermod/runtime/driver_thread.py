"""One driver thread per device: ``source.poll(timeout)`` in a loop → a sink (the ring buffers), with
real-time priority when permitted, retries with exponential back-off, stall detection and source
restarts. `DeviceState` is what the health message says about the device.

These are the only threads with real-time priority (SCHED_FIFO, when ``realtime_priority`` > 0 and
permitted by LimitRTPRIO). They never block on anything but their device.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field

from thermod.errors import DeviceError
from thermod.runtime.sources import Source

log = logging.getLogger("thermod.runtime.daemon")

@dataclass
class DeviceState:
    """What the health message says about one device."""

    name: str
    state: str = "starting"           # starting | running | error | stalled | stopped
    last_error: str = ""
    errors: int = 0
    restarts: int = 0
    last_data: float = math.nan       # host monotonic of the newest item
    items: int = 0
    heartbeat: float = field(default_factory=time.monotonic)
    realtime: bool = False

    def as_dict(self, now: float) -> dict:
        return {"state": self.state, "last_error": self.last_error, "errors": self.errors,
                "restarts": self.restarts, "items": self.items, "realtime": self.realtime,
                "age_s": None if math.isnan(self.last_data) else round(now - self.last_data, 4)}


def set_realtime(prio: int, what: str) -> bool:
    if prio <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))   # 0 = this thread (Linux)
        log.info("%s thread: SCHED_FIFO priority %d", what, prio)
        return True
    except (PermissionError, OSError, AttributeError) as e:
        log.info("%s thread: real-time priority %d not permitted (%s); running SCHED_OTHER "
                 "(grant LimitRTPRIO in the unit)", what, prio, getattr(e, "strerror", None) or e)
        return False


class DriverThread(threading.Thread):
    """Calls ``source.poll`` in a loop, hands results to ``sink``, retries failures with back-off."""

    def __init__(self, kind: str, source: Source, sink, state: DeviceState, stop: threading.Event, *,
                 poll_timeout: float, priority: int, retry_max_s: float, stall_s: float | None = None,
                 on_down=None, on_up=None):
        super().__init__(name=f"thermod-{kind}", daemon=True)
        self.kind, self.source, self.sink, self.st, self.stop_ev = kind, source, sink, state, stop
        self.poll_timeout, self.priority = poll_timeout, priority
        self.retry_max_s, self.stall_s = retry_max_s, stall_s
        self.on_down, self.on_up = on_down, on_up
        self.started_source = False
        self._sink_errors: set[str] = set()
        self.sink_drops = 0

    def _down(self, why: str, state: str = "error") -> None:
        self.st.errors += 1
        self.st.last_error = why
        if self.st.state not in ("error", "stalled"):
            log.warning("%s %s: %s", self.kind, state, why)
            if self.on_down:
                self.on_down()
        self.st.state = state

    def _up(self) -> None:
        if self.st.state != "running":
            if self.st.state in ("error", "stalled"):
                log.warning("%s %s recovered", self.kind, self.st.name)
            self.st.state = "running"
            if self.on_up:
                self.on_up()

    def _sleep(self, s: float) -> None:
        end = time.monotonic() + s
        while not self.stop_ev.is_set() and time.monotonic() < end:
            self.st.heartbeat = time.monotonic()
            self.stop_ev.wait(min(0.1, end - time.monotonic()))

    def _restart_source(self) -> None:
        self.st.restarts += 1
        try:
            self.source.stop()
        except Exception as e:   # noqa: BLE001 - a dead device may fail to stop; we reopen anyway
            log.debug("%s stop during restart failed: %s", self.kind, e)
        self.source.start()

    def run(self) -> None:
        self.st.realtime = set_realtime(self.priority, self.kind)
        backoff = 0.05
        consecutive, restarted, starved = 0, -math.inf, -math.inf
        while not self.stop_ev.is_set():
            self.st.heartbeat = time.monotonic()
            try:
                if not self.started_source:
                    self.source.start()
                    self.started_source = True
                elif consecutive >= 3:
                    self._restart_source()
                    # the restart worked: a device may need a while after a reset before its first sample
                    # (an ICM-42688's gyro starts in ~30 ms), so it is not restarted again before `stall_s`
                    consecutive, restarted = 0, time.monotonic()
                t_poll = time.monotonic()
                item = self.source.poll(self.poll_timeout)
            except (DeviceError, OSError) as e:
                consecutive += 1
                self._down(str(e))
                self._sleep(backoff)
                backoff = min(self.retry_max_s, backoff * 2)
                continue
            except Exception as e:          # a driver bug: log with traceback, keep supervising
                consecutive += 1
                log.exception("%s source raised unexpectedly", self.kind)
                self._down(f"{type(e).__name__}: {e}")
                self._sleep(backoff)
                backoff = min(self.retry_max_s, backoff * 2)
                continue
            now = time.monotonic()
            if self.stall_s and now - t_poll > self.stall_s:
                # this thread was starved inside the poll (the device had no chance to deliver): the
                # silence is counted from here, so a starved read of an overflowed FIFO is no stall
                starved = now
            if item is None:
                last = self.st.last_data if math.isfinite(self.st.last_data) else -math.inf
                quiet_s = now - max(last, starved)
                if self.stall_s and self.st.state == "running" and quiet_s > self.stall_s:
                    self._down(f"no data for {quiet_s:.2f} s", "stalled")
                    consecutive = 3          # reconnect on the next turn
                elif self.stall_s and self.st.state in ("error", "stalled") and \
                        min(quiet_s, now - restarted) > self.stall_s:
                    consecutive = 3          # silent since the last restart or data: restart after back-off
                    self._sleep(backoff)
                    backoff = min(self.retry_max_s, backoff * 2)
                elif self.stall_s and self.st.state == "stalled":
                    self._sleep(backoff)
                    backoff = min(self.retry_max_s, backoff * 2)
                continue
            consecutive, backoff = 0, 0.05
            self.st.last_data = now
            self._up()
            try:
                self.sink(item)
            except Exception as e:      # e.g. a frame of the wrong size: counted, logged once per kind
                self.st.errors += 1
                self.st.last_error = msg = f"{type(e).__name__}: {e}"
                if msg not in self._sink_errors:
                    self._sink_errors.add(msg)
                    log.error("%s: item dropped: %s", self.kind, msg)
                self.sink_drops += 1
        if self.started_source:
            try:
                self.source.stop()
            except Exception as e:  # noqa: BLE001
                log.debug("%s stop failed: %s", self.kind, e)
        self.st.state = "stopped"
