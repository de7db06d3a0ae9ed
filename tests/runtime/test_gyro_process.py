"""The gyro read in a process of its own: the daemon's GIL held past the FIFO's depth loses no sample
there (it does in-process), a child that dies is respawned with the gap marked, and a constructor
that fails is reported and retried."""

import ctypes
import os
import signal
import threading
import time

import numpy as np

from thermod.drivers.gyro_base import GyroBatch
from thermod.errors import DeviceError
from thermod.physics.calibration import Calibration
from thermod.runtime.driver_thread import DeviceState, DriverThread
from thermod.runtime.gyro_process import GyroProcess, GyroPump
from thermod.sim import playback
from thermod.sim.payload import EmulatedGyro

RATE_HZ = 1000.0
FIFO_S = 2048 / 8 / RATE_HZ          # the emulated ICM-42688-P's FIFO: 256 gyro packets


def emulated(t0: float) -> EmulatedGyro:
    motion = playback.LoopMotion(playback.loop_motion("sway:2", 2.0, 0), 2.0, Calibration())
    return EmulatedGyro(motion, t0, None, 0.002, 0, RATE_HZ)


class Collector:
    def __init__(self):
        self.batches, self.lock = [], threading.Lock()

    def __call__(self, b):
        with self.lock:
            self.batches.append(b)

    def seqs(self) -> np.ndarray:
        with self.lock:
            return np.concatenate([b.seq + np.arange(len(b)) for b in self.batches])

    def gaps(self) -> list:
        with self.lock:
            return [(b.seq, b.n_lost) for b in self.batches if b.gap_before]

    def wait_for(self, n: int, timeout: float = 60.0) -> None:
        end = time.monotonic() + timeout
        while sum(len(b) for b in list(self.batches)) < n:
            assert time.monotonic() < end, f"only {sum(len(b) for b in self.batches)} of {n} samples"
            time.sleep(0.02)


def wait_until(ok, state, timeout: float = 60.0) -> None:
    """Until `ok()` holds; the timeout only catches a hang (a loaded host just takes longer)."""
    end = time.monotonic() + timeout
    while not ok():
        assert time.monotonic() < end, state()
        time.sleep(0.05)


def hold_the_gil(seconds: float) -> None:
    """Sleep in C with the GIL held (a `PyDLL` call does not release it): no other thread of this
    process runs Python meanwhile, as during a long GIL-bound call in the scheduler."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def process_gyro(stall_s: float = 0.5) -> GyroProcess:
    return GyroProcess("sim gyro", poll_timeout=0.002, priority=0, retry_max_s=0.5, stall_s=stall_s,
                       preload=("thermod.sim.payload",))


def stalled_for_three_fifos(reader, sink: Collector, stop: threading.Event) -> None:
    """Start `reader` (a thread feeding `sink`), hold this process's GIL for three FIFO fills once
    samples flow, go on until 300 more samples came, and stop it."""
    reader.start()
    try:
        sink.wait_for(300)
        hold_the_gil(3 * FIFO_S)
        sink.wait_for(len(sink.seqs()) + 300)
    finally:
        stop.set()
        reader.join(5.0)


def test_a_parent_holding_its_gil_past_the_fifo_loses_no_sample_in_the_gyro_process():
    sink, state, stop = Collector(), DeviceState("sim gyro"), threading.Event()
    gyro = process_gyro()
    gyro.spawn()
    gyro.start(emulated(time.monotonic()))
    stalled_for_three_fifos(GyroPump(gyro, sink, state, stop), sink, stop)
    seq = sink.seqs()
    assert sink.gaps() == [] and np.all(np.diff(seq) == 1), sink.gaps()
    assert gyro.stats()["overflows"] == 0 and state.state == "stopped"
    assert not gyro.alive()


def test_the_same_stall_overflows_the_fifo_of_a_reader_in_the_parent():
    """The counterpart: read in this process, the same GIL hold overflows the FIFO (counted, a gap)."""
    sink, state, stop = Collector(), DeviceState("sim gyro"), threading.Event()
    th = DriverThread("gyro", emulated(time.monotonic())(), sink, state, stop, poll_timeout=0.002,
                      priority=0, retry_max_s=0.5, stall_s=0.5)
    stalled_for_three_fifos(th, sink, stop)
    gaps = sink.gaps()
    assert len(gaps) >= 1 and sum(lost for _, lost in gaps) >= 1.5 * FIFO_S * RATE_HZ, gaps


def test_a_gyro_process_that_dies_is_respawned_and_the_gap_marked():
    sink, state, stop = Collector(), DeviceState("sim gyro"), threading.Event()
    downs, ups = [], []
    gyro = process_gyro()
    gyro.start(emulated(time.monotonic()))
    pump = GyroPump(gyro, sink, state, stop, on_down=lambda: downs.append(1), on_up=lambda: ups.append(1))
    pump.start()
    try:
        sink.wait_for(200)
        first = gyro.pid
        os.kill(first, signal.SIGKILL)
        wait_until(lambda: gyro.stats()["process_spawns"] >= 2 and state.state == "running",
                   lambda: (gyro.stats(), state))
        sink.wait_for(len(sink.seqs()) + 200)
    finally:
        stop.set()
        pump.join(5.0)
    assert gyro.pid is None or gyro.pid != first
    assert state.restarts >= 1 and "gyro process exited" in state.last_error
    assert downs and len(ups) >= 2          # running → error → running
    # the first batch of the new child says samples were lost before it
    assert len(sink.gaps()) >= 1


class Unplugged:
    """A constructor that fails as a missing device does (picklable: the child imports this module)."""

    def __call__(self):
        raise DeviceError("/dev/spidev9.9: no such device")


def test_a_constructor_that_fails_is_reported_and_retried():
    sink, state, stop = Collector(), DeviceState("gyro"), threading.Event()
    gyro = process_gyro()
    gyro.start(Unplugged())
    pump = GyroPump(gyro, sink, state, stop)
    pump.start()
    try:
        wait_until(lambda: gyro.stats()["process_spawns"] >= 3, lambda: (gyro.stats(), state))
    finally:
        stop.set()
        pump.join(5.0)
    assert state.errors >= 2 and "/dev/spidev9.9: no such device" in state.last_error
    assert sink.batches == []


def test_a_read_request_wakes_the_reader_in_the_child():
    """Asked every 5 ms (as a frame waiting for samples asks), the child reads far more often than
    its interval (25 ms for this FIFO) alone would: the request reaches its reader."""
    sink, state, stop = Collector(), DeviceState("sim gyro"), threading.Event()
    gyro = process_gyro()
    gyro.start(emulated(time.monotonic()))
    pump = GyroPump(gyro, sink, state, stop)
    pump.start()

    def batches_in(seconds: float, ask: bool) -> int:
        n0, end = len(sink.batches), time.monotonic() + seconds
        while time.monotonic() < end:
            if ask:
                gyro.request_read()
            time.sleep(0.005)
        return len(sink.batches) - n0

    try:
        sink.wait_for(100)
        alone = batches_in(2.0, ask=False)
        asked = batches_in(2.0, ask=True)
    finally:
        stop.set()
        pump.join(5.0)
    assert asked >= 1.5 * alone and alone >= 40, (alone, asked)


class UnpluggedAfter:
    """The emulated gyro, unplugged for `seconds` after `after` s (every bus access fails, then the chip
    comes back power-cycled): built in the child, as a real chip fails there."""

    def __init__(self, t0: float, after: float, seconds: float):
        self.t0, self.after, self.seconds = t0, after, seconds

    def __call__(self):
        driver = emulated(self.t0)()
        threading.Timer(self.after, driver.emulator.unplug, (self.seconds,)).start()
        return driver


def test_a_device_error_in_the_child_is_mirrored_and_recovered():
    sink, state, stop = Collector(), DeviceState("sim gyro"), threading.Event()
    downs, ups = [], []
    gyro = process_gyro()
    gyro.start(UnpluggedAfter(time.monotonic(), after=1.0, seconds=0.4))
    pump = GyroPump(gyro, sink, state, stop, on_down=lambda: downs.append(state.last_error),
                    on_up=lambda: ups.append(1))
    pump.start()
    try:
        wait_until(lambda: downs and len(ups) >= 2 and state.state == "running",
                   lambda: (state, gyro.stats()))
        sink.wait_for(len(sink.seqs()) + 100)
    finally:
        stop.set()
        pump.join(5.0)
    assert gyro.stats()["process_spawns"] == 1            # the child recovered the device itself
    assert state.errors >= 1 and "failed" in downs[0], downs
    gaps = sink.gaps()
    assert gaps and gaps[0][1] >= 300, gaps                # ≥ 0.3 s of samples lost while unplugged, counted


def test_a_child_spawned_but_never_given_its_source_stops_with_the_daemon():
    """The daemon spawns the child before it prepares; a start that fails after that still ends it."""
    gyro = process_gyro()
    gyro.spawn()
    pid = gyro.pid
    assert gyro.alive()
    gyro.stop(timeout=5.0)
    assert not gyro.alive() and gyro.pid is None
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"



def test_sigterm_to_the_process_group_leaves_the_child_to_the_daemons_stop():
    """systemd's stop sends SIGTERM to every process of the service. The child ignores it, as the
    solver children do, and ends when the daemon stops it. It used to die inside `stop.wait`, and the
    daemon's stop (before its pump noticed the death) then waited forever in `stop.set` for the dead
    child's acknowledgement, until systemd's SIGKILL."""
    gyro = process_gyro()
    gyro.start(emulated(time.monotonic()))
    end = time.monotonic() + 60.0               # a hang bound: samples come within a few seconds
    while not isinstance(gyro.get(0.1), GyroBatch):
        assert time.monotonic() < end and gyro.alive(), "no sample from the gyro process"
    pid, proc = gyro.pid, gyro._proc
    os.kill(pid, signal.SIGTERM)
    proc.join(1.0)                              # a child that dies of it dies now
    stopper = threading.Thread(target=gyro.stop, daemon=True)
    stopper.start()
    stopper.join(30.0)                          # a hang bound: the stop takes a fraction of a second
    assert not stopper.is_alive(), "the gyro process's stop hung"
    assert not gyro.alive() and proc.exitcode == 0, proc.exitcode
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
