"""The gyro driver in a process of its own, so that its FIFO deadline never waits on the daemon's GIL.

A FIFO gyro must be read before its FIFO fills (an ICM-42688-P's 2 KB hold 256 ms at 1 kHz). In the
daemon's process its reader shares one GIL with the scheduler, the publisher and the monitor, and a
stretch of GIL-bound work, or a loaded host, makes it miss that deadline: samples are lost.

`GyroProcess` spawns a child (a fresh interpreter, a GIL of its own) that builds the source with a
picklable constructor and runs the same `DriverThread` on it as the daemon would: real-time priority,
retries, back-off, stall detection and restarts. Every batch (raw bytes, no pickling), and the
device's state every `STATE_EVERY_S` and at each change, goes through a pipe of `PIPE_BYTES` (about
40 s of samples): a starved parent delays samples, it does not lose them; one that does not read
for longer blocks the reader, and the FIFO's overflow is counted as usual. The parent's pump thread
(`GyroPump`, named ``thermod-gyro``) hands the batches to the daemon's sink and mirrors the child's
`DeviceState`; a child that dies is respawned with back-off and the samples it held count as a gap.
"""

from __future__ import annotations

import atexit
import logging
import math
import multiprocessing
import os
import pickle
import select
import signal
import struct
import threading
import time
from types import SimpleNamespace

import numpy as np

from thermod.drivers.gyro_base import GyroBatch
from thermod.runtime.driver_thread import DeviceState, set_realtime
from thermod.runtime.health import source_clock

log = logging.getLogger("thermod.runtime.daemon")

STATE_EVERY_S = 0.25          # the child reports the device's state this often (and at each change)
FIFO_POLL_S = 0.05            # a FIFO driver's poll timeout in the child, at least (fewer empty wake-ups)
PIPE_BYTES = 1 << 20          # the data pipe's buffer (Linux's default limit for a user): ~40 s at 1 kHz
_BATCH = struct.Struct("<qBqI")   # seq, gap_before, n_lost, n; then t float64[n], rate float32[n, 3]
SPAWN_TIMEOUT_S = 60.0        # a child that does not say "ready" by then (a hung import) is restarted
_exiting = threading.Event()  # the interpreter is exiting: multiprocessing ends the child, none respawns
atexit.register(_exiting.set)
_STATE_KEYS = ("state", "last_error", "errors", "restarts", "last_data", "heartbeat", "realtime")


class GyroProcess:
    """A gyro source run in a child process; the daemon reads it with a `GyroPump`.

    ``build`` is a picklable zero-argument constructor of the source (e.g.
    ``functools.partial(sources.build_gyro, cfg)``, `thermod.sim.payload.EmulatedGyro`); ``preload``
    names modules the child imports while the daemon prepares, so that `start` is quick.
    """

    def __init__(self, name: str, *, poll_timeout: float, priority: int, retry_max_s: float,
                 stall_s: float, preload: tuple[str, ...] = ()):
        self.name = name
        self.opts = dict(poll_timeout=poll_timeout, priority=priority, retry_max_s=retry_max_s,
                         stall_s=stall_s, log_level=log.getEffectiveLevel())
        self.preload = preload
        self.clock: SimpleNamespace | None = None   # the child's clock fit, as health reads a source's
        self.sim_cpu_s = 0.0            # the emulated device's CPU in the child (a real one costs none)
        self.spawns = 0
        self.child_error = ""           # the current child's last error
        self._ctx = multiprocessing.get_context("spawn")
        self._proc = self._stop = self._conn = self._data = self._wake = None
        self._stats: dict = {}
        self._build = None
        self._sim_base = 0.0            # emulation CPU of children before the current one
        self._stopping = threading.Lock()

    # ------------------------------------------------------------------ the child's life
    def spawn(self) -> None:
        """Start the child's interpreter (imports take a while); `start` hands it the constructor."""
        if self._proc is not None and self._proc.is_alive():
            return
        self._stop = self._ctx.Event()
        parent_conn, child_conn = self._ctx.Pipe()
        data_r, data_w = self._ctx.Pipe(duplex=False)
        _enlarge(data_w.fileno())
        wake_r, wake_w = self._ctx.Pipe(duplex=False)
        os.set_blocking(wake_w.fileno(), False)
        self._proc = self._ctx.Process(target=_child_main, name="thermod-gyro-process", daemon=True,
                                       args=(child_conn, data_w, wake_r, self._stop, self.opts,
                                             self.preload))
        self._proc.start()
        self.child_error = ""
        for c in (child_conn, data_w, wake_r):
            c.close()
        self._conn, self._data, self._wake = parent_conn, data_r, wake_w
        self.spawns += 1

    def start(self, build=None) -> None:
        """Hand the child its constructor (spawning it if needed); its driver thread starts at once."""
        self._build = build if build is not None else self._build
        self.spawn()
        self._conn.send(self._build)

    def stop(self, timeout: float = 1.0) -> None:
        """End the child (the pump's end, or the daemon's when its start failed before the pump ran)."""
        with self._stopping:
            proc = self._proc
            if proc is None:
                return
            if proc.is_alive():     # a dead child's event can wait forever for its acknowledgement
                self._stop.set()
            proc.join(timeout)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
            self._drop_child()

    def _drop_child(self) -> None:
        self._sim_base = self.sim_cpu_s
        for c in (self._conn, self._data, self._wake):
            if c is not None:
                c.close()
        self._proc = self._conn = self._data = self._wake = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    # ------------------------------------------------------------------ what the daemon asks of a source
    def request_read(self) -> None:
        """A frame waits for its newest samples: the child reads the FIFO now."""
        wake = self._wake
        if wake is not None:
            WakeUp.poke(wake.fileno())

    def stats(self) -> dict:
        return {**self._stats, "process_pid": self.pid, "process_spawns": self.spawns}

    def get(self, timeout: float):
        """The child's next message (a `GyroBatch` or a state tuple), or None."""
        try:
            if self._data is None or not self._data.poll(timeout):
                return None
            buf = self._data.recv_bytes()
        except (EOFError, OSError, ValueError):     # a dead child's pipe: the pump restarts it
            return None
        if buf[:1] == b"S":
            return pickle.loads(buf[1:])
        seq, gap, n_lost, n = _BATCH.unpack_from(buf, 1)
        at = 1 + _BATCH.size
        t = np.frombuffer(buf, "<f8", n, at)
        rate = np.frombuffer(buf, "<f4", 3 * n, at + 8 * n).reshape(n, 3)
        return GyroBatch(t, rate, seq, bool(gap), n_lost)

    def take_report(self, msg: tuple) -> dict:
        """A "state" message: keep the stats, clock and emulation CPU; return the device's state."""
        state, stats, clock, sim_cpu = msg
        self.child_error = state["last_error"]
        self._stats = stats
        self.clock = None if clock is None else SimpleNamespace(**clock)
        self.sim_cpu_s = self._sim_base + float(sim_cpu)
        return state


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
            setattr(self.st, k, state[k] + self._before[k] if k in self._before else state[k])
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
        # the parent's end of the gyro path: the frames wait on it, as on a driver thread in-process
        set_realtime(self.p.opts["priority"], "gyro pump")
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
            if isinstance(msg, tuple):
                self._mirror(self.p.take_report(msg))
                if self.st.state == "running":
                    backoff = 0.05
                continue
            b = msg
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
class WakeUp:
    """A read request across processes that never blocks the one asking (a `multiprocessing.Event`'s
    `set` waits for the woken side to acknowledge): a byte written to a non-blocking pipe, dropped
    when one is pending. It has an `Event`'s ``wait``, ``clear`` and ``set`` for `FifoGyro.wake_on`."""

    def __init__(self, conn):
        self._conn, self._fd = conn, conn.fileno()      # the Connection keeps the descriptor open
        os.set_blocking(self._fd, False)

    @staticmethod
    def poke(fd: int) -> None:
        try:
            os.write(fd, b"\0")
        except (BlockingIOError, OSError):   # one pending already, or the child is gone
            pass

    def set(self) -> None:                  # `Event` API; only the parent asks, through `poke`
        pass

    def wait(self, timeout: float | None = None) -> bool:
        return bool(select.select([self._fd], [], [], timeout)[0])

    def clear(self) -> None:
        try:
            while os.read(self._fd, 4096):
                pass
        except BlockingIOError:
            pass


def _enlarge(fd: int) -> None:
    """Give the data pipe `PIPE_BYTES` of buffer where the system allows (F_SETPIPE_SZ, Linux)."""
    import fcntl

    for size in (PIPE_BYTES, PIPE_BYTES // 4):
        try:
            fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, size)
            return
        except (OSError, AttributeError):
            continue


def _child_main(conn, data, wake, stop, opts: dict, preload: tuple[str, ...]) -> None:
    """The gyro process: wait for the constructor, run a `DriverThread` on the source until told to stop
    or the parent is gone; batches and state reports go into `data`. A parent that goes away, at any
    moment (its pipes at EOF or broken, this process re-parented), ends it with one log line."""
    import importlib

    from thermod.runtime.driver_thread import DriverThread

    # the pid the parent gave at spawn: by now it may have died already and getppid() say another
    parent = getattr(multiprocessing.parent_process(), "pid", None) or os.getppid()
    # the daemon stops us: systemd's stop and Ctrl-C reach the whole group, and a child dead of them
    # inside `stop.wait` would leave the daemon's `stop.set` waiting for its acknowledgement forever
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=opts.get("log_level", logging.INFO),
                        format="%(levelname)s %(name)s [gyro process]: %(message)s")
    gone = threading.Event()        # the parent went away: nothing to read from nor send to any more

    def orphaned() -> bool:
        if not gone.is_set() and os.getppid() != parent:
            gone.set()
        return gone.is_set()

    def left_alone() -> None:
        log.info("the daemon (pid %d) went away; the gyro process ends", parent)

    for name in preload:
        importlib.import_module(name)
    build = None
    try:
        while not conn.poll(0.2) and not orphaned():
            if stop.is_set():
                return
        if not gone.is_set():
            build = conn.recv()
    except (EOFError, OSError):       # the parent's end closed: it died before handing the constructor
        gone.set()
    if gone.is_set():
        left_alone()
        return
    sending = threading.Lock()      # the driver thread and this one both send: one message at a time
    halt = threading.Event()

    def send(msg: bytes) -> None:
        with sending:
            if gone.is_set():
                return
            try:
                data.send_bytes(msg)
            except OSError:           # BrokenPipeError: the parent died; the loop below ends us
                gone.set()
                halt.set()

    def send_state(state: dict, stats: dict, clock, sim_cpu: float) -> None:
        send(b"S" + pickle.dumps((state, stats, clock, sim_cpu)))

    try:
        src = build()
    except Exception as e:   # noqa: BLE001 - said once, in the parent's health, then the parent retries
        send_state({**{k: getattr(DeviceState("gyro"), k) for k in _STATE_KEYS}, "state": "error",
                    "last_error": f"{type(e).__name__}: {e}"}, {}, None, 0.0)
        raise SystemExit(1) from None
    st = DeviceState(src.name)

    def report() -> None:
        book = getattr(src, "emulation_cpu", None)
        try:
            stats = {k: v for k, v in src.stats().items() if isinstance(v, (int, float, str, bool))}
        except Exception as e:  # noqa: BLE001 - the parent reports it
            stats = {"stats_error": f"{type(e).__name__}: {e}"}
        send_state({k: getattr(st, k) for k in _STATE_KEYS}, stats, source_clock(src),
                   0.0 if book is None else book.cpu_s)

    def sink(b: GyroBatch) -> None:
        n = len(b)
        send(b"".join((b"B", _BATCH.pack(int(b.seq), bool(b.gap_before), int(b.n_lost), n),
                       np.ascontiguousarray(b.t, "<f8").tobytes(),
                       np.ascontiguousarray(b.rate, "<f4").tobytes())))

    # a FIFO driver waits on the parent's requests itself: a request wakes the real-time reader
    # directly, not through this thread
    want = WakeUp(wake)
    relay = getattr(src, "request_read", None)
    poll_timeout = opts["poll_timeout"]
    if (wake_on := getattr(src, "wake_on", None)) is not None:
        wake_on(want)
        relay = None
        # its reads come at its interval or on a request; the timeout only bounds how soon it stops
        poll_timeout = max(poll_timeout, FIFO_POLL_S)
    th = DriverThread("gyro", src, sink, st, halt, poll_timeout=poll_timeout,
                      priority=opts["priority"], retry_max_s=opts["retry_max_s"], stall_s=opts["stall_s"],
                      on_down=report, on_up=report)
    th.start()
    last = -math.inf
    try:
        while not stop.is_set() and not orphaned():
            left = max(0.0, STATE_EVERY_S - (time.monotonic() - last))
            if relay is None:
                stop.wait(left)
            elif want.wait(left):
                want.clear()
                relay()
            if time.monotonic() - last >= STATE_EVERY_S:
                last = time.monotonic()
                report()
    finally:
        halt.set()
        th.join(1.0)
    if gone.is_set():
        left_alone()
