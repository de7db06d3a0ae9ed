"""The gyro driver in a process of its own, so that its FIFO deadline never waits on the daemon's GIL.

A FIFO gyro must be read before its FIFO fills (an ICM-42688-P's 2 KB hold 256 ms at 1 kHz). In the
daemon's process its reader shares one GIL with the scheduler, the publisher and the monitor, and a
stretch of GIL-bound work, or a loaded host, makes it miss that deadline: samples are lost.

`GyroProcess` spawns a child (a fresh interpreter, a GIL of its own) that builds the source with a
picklable constructor and runs the same `DriverThread` on it as the daemon would: real-time priority,
retries, back-off, stall detection and restarts. Every batch, and the device's state every
`STATE_EVERY_S` and at each change, goes through a `multiprocessing.Queue`, whose feeder thread
buffers while the parent is slow: a starved parent delays samples, it does not lose them (up to
`QUEUE_BATCHES`, after which the child counts them lost and marks the gap). The parent's pump thread
(`start_pump`, named ``thermod-gyro``) hands the batches to the daemon's sink and mirrors the child's
`DeviceState`; a child that dies is respawned with back-off and the samples it held count as a gap.
"""

from __future__ import annotations

import atexit
import logging
import math
import multiprocessing
import os
import queue
import signal
import threading
import time

from thermod.drivers.gyro_base import GyroBatch
from thermod.runtime.driver_thread import DeviceState

log = logging.getLogger("thermod.runtime.daemon")

STATE_EVERY_S = 0.25          # the child reports the device's state this often (and at each change)
QUEUE_BATCHES = 20_000        # batches the child holds for a parent that does not read (≥ 20 s at 1 kHz)
SPAWN_TIMEOUT_S = 60.0        # a child that does not say "ready" by then (a hung import) is restarted
_exiting = threading.Event()  # the interpreter is exiting: multiprocessing ends the child, none respawns
atexit.register(_exiting.set)
_STATE_KEYS = ("state", "last_error", "errors", "restarts", "last_data", "heartbeat", "realtime")


class ClockReport:
    """The child's device-clock fit, as health reads it (`thermod.runtime.health.source_clock`)."""

    def __init__(self, d: dict):
        self.residual_std_s, self.drift_ppm, self.resets = d["residual_std_s"], d["drift_ppm"], d["resets"]


class GyroProcess:
    """A gyro source run in a child process; the daemon reads it with `start_pump`.

    ``build`` is a picklable zero-argument constructor of the source (e.g.
    ``functools.partial(sources.build_gyro, cfg)``, `thermod.sim.payload.EmulatedGyro`); ``preload``
    names modules the child imports while the daemon prepares, so that `start` is quick.
    """

    def __init__(self, name: str, *, poll_timeout: float, priority: int, retry_max_s: float,
                 stall_s: float, preload: tuple[str, ...] = ()):
        self.name = name
        self.opts = dict(poll_timeout=poll_timeout, priority=priority, retry_max_s=retry_max_s,
                         stall_s=stall_s, log_level=logging.getLogger().getEffectiveLevel())
        self.preload = preload
        self.clock: ClockReport | None = None
        self.sim_cpu_s = 0.0            # the emulated device's CPU in the child (a real one costs none)
        self.spawns = 0
        self.child_error = ""           # the current child's last error
        self._ctx = multiprocessing.get_context("spawn")
        self._want = self._ctx.Event()
        self._proc = self._queue = self._stop = self._conn = None
        self._stats: dict = {}
        self._build = None
        self._sim_base = 0.0            # emulation CPU of children before the current one

    # ------------------------------------------------------------------ the child's life
    def spawn(self) -> None:
        """Start the child's interpreter (imports take a while); `start` hands it the constructor."""
        if self._proc is not None and self._proc.is_alive():
            return
        self._queue = self._ctx.Queue()
        self._stop = self._ctx.Event()
        parent_conn, child_conn = self._ctx.Pipe()
        self._proc = self._ctx.Process(target=_child_main, name="thermod-gyro-process", daemon=True,
                                       args=(child_conn, self._queue, self._want, self._stop, self.opts,
                                             self.preload))
        self._proc.start()
        self.child_error = ""
        child_conn.close()
        self._conn = parent_conn
        self.spawns += 1

    def start(self, build=None) -> None:
        """Hand the child its constructor (spawning it if needed); its driver thread starts at once."""
        self._build = build if build is not None else self._build
        self.spawn()
        self._conn.send(self._build)

    def stop(self, timeout: float = 1.0) -> None:
        if self._proc is None:
            return
        self._stop.set()
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)
        self._drop_child()

    def _drop_child(self) -> None:
        self._sim_base = self.sim_cpu_s
        if self._queue is not None:
            self._queue.cancel_join_thread()
            self._queue.close()
        if self._conn is not None:
            self._conn.close()
        self._proc = self._queue = self._conn = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    # ------------------------------------------------------------------ what the daemon asks of a source
    def request_read(self) -> None:
        """A frame waits for its newest samples: the child reads the FIFO now."""
        self._want.set()

    def stats(self) -> dict:
        return {**self._stats, "process_pid": self.pid, "process_spawns": self.spawns}

    def get(self, timeout: float):
        """The child's next message, or None."""
        try:
            return self._queue.get(timeout=timeout)
        except (queue.Empty, EOFError, OSError, ValueError):   # closed or dead queue: the pump restarts it
            return None

    def take_report(self, msg: tuple) -> dict:
        """A "state" message: keep the stats, clock and emulation CPU; return the device's state."""
        _, state, stats, clock, sim_cpu = msg
        self.child_error = state["last_error"]
        self._stats = stats
        self.clock = None if clock is None else ClockReport(clock)
        self.sim_cpu_s = self._sim_base + float(sim_cpu)
        return state

    def start_pump(self, sink, state: DeviceState, stop: threading.Event, *, on_down=None, on_up=None):
        """The parent's ``thermod-gyro`` thread (started): batches → `sink`, the child's state → `state`."""
        th = GyroPump(self, sink, state, stop, on_down=on_down, on_up=on_up)
        th.start()
        return th


class GyroPump(threading.Thread):
    """Moves the child's batches into the daemon and mirrors its device state; respawns a dead child.
    It has `kind` and `st` as a `DriverThread` has, for the daemon's watchdog."""

    def __init__(self, proc: GyroProcess, sink, state: DeviceState, stop: threading.Event, *, on_down=None,
                 on_up=None):
        super().__init__(name="thermod-gyro", daemon=True)
        self.kind, self.p, self.sink, self.st, self.stop_ev = "gyro", proc, sink, state, stop
        self.on_down, self.on_up = on_down, on_up
        self.sink_drops = 0
        self._respawned = False                 # the next batch follows the samples a dead child held
        # what the children before the current one counted, and the pump's own last error (a death)
        self._before = {"errors": 0, "restarts": 0}
        self._died = ""

    def _mirror(self, state: dict) -> None:
        was = self.st.state
        for k in _STATE_KEYS:
            setattr(self.st, k, state[k] + self._before.get(k, 0) if k in self._before else state[k])
        self.st.last_error = state["last_error"] or self._died
        now_up = self.st.state == "running"
        if was == "running" and not now_up and self.on_down:
            self.on_down()
        elif was != "running" and now_up and self.on_up:
            self.on_up()

    def _child_died(self, backoff: float) -> float:
        code = self.p._proc.exitcode if self.p._proc is not None else None
        said = self.p.child_error
        why = f"gyro process exited (code {code}); restarting it" + (f" (it said: {said})" if said else "")
        log.warning("%s: %s", self.p.name, why)
        self._died = why
        self._before = {"errors": self.st.errors + 1, "restarts": self.st.restarts + 1}
        self._mirror({**{k: getattr(self.st, k) for k in _STATE_KEYS}, "state": "error", "last_error": why,
                      "errors": 0, "restarts": 0})
        self.p._drop_child()
        self._respawned = True
        self.stop_ev.wait(backoff)
        if not self.stop_ev.is_set() and not _exiting.is_set():
            self.p.start()
        return min(self.p.opts["retry_max_s"], backoff * 2)

    def run(self) -> None:
        backoff = 0.05
        started = time.monotonic()
        while not self.stop_ev.is_set() and not _exiting.is_set():
            msg = self.p.get(0.1)
            if msg is None:
                proc = self.p._proc
                silent = time.monotonic() - max(started, self.st.heartbeat)
                if proc is None or not proc.is_alive() or silent > SPAWN_TIMEOUT_S:
                    if proc is not None and proc.is_alive():
                        proc.kill()
                        proc.join(1.0)
                    backoff = self._child_died(backoff)
                    started = time.monotonic()
                continue
            if msg[0] == "state":
                self._mirror(self.p.take_report(msg))
                if self.st.state == "running":
                    backoff = 0.05
                continue
            _, t, rate, seq, gap_before, n_lost = msg
            b = GyroBatch(t, rate, seq, gap_before, n_lost)
            if self._respawned:                   # the samples a dead child held: a gap (count unknown)
                b.gap_before, self._respawned = True, False
            try:
                self.sink(b)
            except Exception as e:   # noqa: BLE001 - counted and logged, as DriverThread does
                self.sink_drops += 1
                self.st.errors += 1
                self.st.last_error = f"{type(e).__name__}: {e}"
                log.error("gyro: batch dropped: %s", self.st.last_error)
        self.p.stop()
        self.st.state = "stopped"


# ---------------------------------------------------------------------------------------- the child
def _clock_report(clk) -> dict | None:
    if clk is None:
        return None
    return {"residual_std_s": float(clk.residual_std_s), "drift_ppm": float(clk.drift_ppm),
            "resets": int(clk.resets)}


def _child_main(conn, q, want, stop, opts: dict, preload: tuple[str, ...]) -> None:
    """The gyro process: wait for the constructor, run a `DriverThread` on the source until told to stop
    or the parent is gone; batches and state reports go into `q`."""
    import importlib

    from thermod.runtime.driver_thread import DriverThread

    signal.signal(signal.SIGINT, signal.SIG_IGN)     # the daemon stops us (Ctrl-C reaches the group)
    logging.basicConfig(level=opts.get("log_level", logging.INFO),
                        format="%(levelname)s %(name)s [gyro process]: %(message)s")
    for name in preload:
        importlib.import_module(name)
    parent = os.getppid()
    while not conn.poll(0.2):
        if stop.is_set() or os.getppid() != parent:
            return
    build = conn.recv()
    try:
        src = build()
    except Exception as e:   # noqa: BLE001 - said once, in the parent's health, then the parent retries
        q.put(("state", {**{k: getattr(DeviceState("gyro"), k) for k in _STATE_KEYS}, "state": "error",
                         "last_error": f"{type(e).__name__}: {e}"}, {}, None, 0.0))
        q.close()
        q.join_thread()
        raise SystemExit(1) from None
    st = DeviceState(src.name)
    halt = threading.Event()
    held = {"seq": None}           # a batch the queue could not take: the next one carries the gap

    def report() -> None:
        book = getattr(src, "emulation_cpu", None)
        try:
            stats = {k: v for k, v in src.stats().items() if isinstance(v, (int, float, str, bool))}
        except Exception as e:  # noqa: BLE001 - the parent reports it
            stats = {"stats_error": f"{type(e).__name__}: {e}"}
        q.put(("state", {k: getattr(st, k) for k in _STATE_KEYS}, stats, _clock_report(src.clock),
               0.0 if book is None else book.cpu_s))

    def sink(b: GyroBatch) -> None:
        gap, lost = b.gap_before, b.n_lost
        if held["seq"] is not None:
            gap, lost = True, lost + b.seq - held["seq"]
            held["seq"] = None
        if q.qsize() >= QUEUE_BATCHES:       # the parent has not read for that long: count, not grow
            held["seq"] = held["seq"] if held["seq"] is not None else b.seq
            return
        q.put(("batch", b.t, b.rate, int(b.seq), bool(gap), int(lost)))

    th = DriverThread("gyro", src, sink, st, halt, poll_timeout=opts["poll_timeout"],
                      priority=opts["priority"], retry_max_s=opts["retry_max_s"], stall_s=opts["stall_s"],
                      on_down=report, on_up=report)
    th.start()
    last = -math.inf
    try:
        while not stop.is_set() and os.getppid() == parent:
            if want.wait(max(0.0, STATE_EVERY_S - (time.monotonic() - last))):
                want.clear()
                if (ask := getattr(src, "request_read", None)) is not None:
                    ask()
            if time.monotonic() - last >= STATE_EVERY_S:
                last = time.monotonic()
                report()
    finally:
        halt.set()
        th.join(1.0)
        q.cancel_join_thread()      # the parent has stopped reading: buffered batches are not waited for
