"""The driver thread's supervision: a device that fails is restarted, and a restarted device gets time
to deliver its first sample (a gyro after a soft reset starts in tens of ms: restarting it on every
empty poll kept it from ever starting, and the daemon without gyro for good)."""

import threading
import time

from thermod.runtime.driver_thread import DeviceState, DriverThread


class ResetDevice:
    """Fails `failures` polls (unplugged), then works; after every start it needs `startup_s` before
    its first sample (a chip's start-up after reset), then delivers one item per poll. Starts number
    2 … `silent_starts` + 1 (the restarts after the failures) leave it silent (a reset that did not
    take)."""

    name = "slow-start device"
    clock = None

    def __init__(self, failures: int, startup_s: float, silent_starts: int = 0):
        self.failures, self.startup_s, self.silent_starts = failures, startup_s, silent_starts
        self.starts = 0
        self.ready_at = 0.0

    def start(self):
        self.starts += 1
        silent = 2 <= self.starts <= self.silent_starts + 1
        self.ready_at = float("inf") if silent else time.monotonic() + self.startup_s

    def stop(self):
        pass

    def poll(self, timeout):
        if self.failures > 0:
            self.failures -= 1
            raise OSError(121, "Remote I/O error (not responding)")
        time.sleep(timeout)
        return ("sample", time.monotonic()) if time.monotonic() >= self.ready_at else None


def supervise(device, seconds, *, stall_s=0.5, want=20):
    items, stop = [], threading.Event()
    st = DeviceState(device.name)
    th = DriverThread("gyro", device, items.append, st, stop, poll_timeout=0.002, priority=0,
                      retry_max_s=0.05, stall_s=stall_s)
    th.start()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and len(items) < want:
        time.sleep(0.01)
    state = st.state
    stop.set()
    th.join(5)
    return items, st, state


def test_a_restarted_device_gets_its_start_up_time():
    """Three failures → one restart; the device then needs 40 ms (20 polls) before its first sample."""
    dev = ResetDevice(failures=3, startup_s=0.04)
    items, st, state = supervise(dev, 5.0)
    assert len(items) >= 20, (dev.starts, st)
    assert st.restarts == 1 and dev.starts == 2, (st.restarts, dev.starts)
    assert state == "running" and st.errors == 3


def test_a_restarted_device_that_stays_silent_is_restarted_again():
    """Silent after its restart for longer than stall_s: restarted again (not left in `error` for good)."""
    dev = ResetDevice(failures=3, startup_s=0.04, silent_starts=1)
    items, st, state = supervise(dev, 5.0, stall_s=0.1)
    assert len(items) >= 20, (dev.starts, st)
    assert st.restarts == 2 and dev.starts == 3 and state == "running", (st.restarts, dev.starts, state)


class StarvedDevice(ResetDevice):
    """Delivers, then its poll is starved once for `starved_s` (the thread did not run) and that read
    finds nothing usable (an overflowed FIFO, flushed), then delivers again."""

    def __init__(self, starved_s: float):
        super().__init__(failures=0, startup_s=0.0)
        self.starved_s, self.polls = starved_s, 0

    def poll(self, timeout):
        self.polls += 1
        if self.polls == 50:
            time.sleep(self.starved_s)
            return None
        return super().poll(timeout)


def test_a_starved_poll_is_no_stall():
    """0.3 s without the CPU inside one poll (stall_s 0.1): the device is not declared stalled nor
    restarted; only polls the device had the chance to answer count towards a stall."""
    dev = StarvedDevice(0.3)
    items, st, state = supervise(dev, 5.0, stall_s=0.1, want=80)
    assert len(items) >= 80 and dev.polls > 50
    assert st.restarts == 0 and st.errors == 0 and state == "running", st
