"""A serial IMU on a real pseudo-terminal, speaking thermod's serial IMU protocol v1
(see :mod:`thermod.drivers.serial_imu`).

A writer thread produces samples at ``rate_hz`` on the device's own oscillator (``drift_ppm``,
positive = fast) and writes them every ``batch_s`` to the pty master, as a USB-serial adapter
delivers them in bursts. The driver opens the slave path, or better the stable symlink
``link`` (``<link_dir>/usb-thermod_emu_IMU_<serial>-if00-port0``, like /dev/serial/by-id) that is
re-pointed at the new pty after a reconnect.

Faults (probabilities per frame, seeded): ``garbage_prob`` (1–16 junk bytes, never 0xA5, before a
frame), ``drop_prob`` (the frame is not sent; its seq is skipped), ``corrupt_prob`` (one bit flipped
after the header: a CRC error), and ``disconnect(seconds)`` (both pty ends closed, like pulling the
cable; frames produced meanwhile are lost; ``reset_counters=True`` restarts seq and time at 0 as a
rebooted device would). ``bad_rate_prob``: the frame carries a NaN, ±inf or out-of-range rate (type
2: a NaN, infinite, zero or negative scale) under a valid CRC. ``glitch_times(values)``: the next
frames carry these device times (µs) instead of their own. Every produced frame is logged in ``log``
(``good``, ``dropped``, ``corrupted``, ``bad_rate``, ``offline`` seq lists; ``garbage_bytes``,
``garbage_before`` {seq: bytes}) as the truth a test compares against.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import struct
import threading
import time
import tty
from collections.abc import Callable

import numpy as np

from thermod.drivers.serial_imu import PAYLOAD_LEN, SYNC, TYPE_I16, crc16_ccitt, encode_frame
from thermod.sim.emu_thread import ThreadedEmulator


class SerialIMUEmulator(ThreadedEmulator):
    """Real-time serial IMU on ``os.openpty()``; use as a context manager or start()/stop()."""

    thread_name = "emu-serial-imu"

    def __init__(self, *, rate_hz: float = 1000.0, batch_s: float = 0.005,
                 rate_fn: Callable[[np.ndarray], np.ndarray] | None = None, noise_rad_s: float = 0.0,
                 drift_ppm: float = 0.0, int16_scale: float | None = None, garbage_prob: float = 0.0,
                 drop_prob: float = 0.0, corrupt_prob: float = 0.0, bad_rate_prob: float = 0.0, seed: int = 0,
                 link_dir: str | None = None, serial_number: str = "EMU0001", t_us0: int | None = None,
                 seq0: int = 0, clock: Callable[[], float] = time.monotonic):
        self.rate_hz, self.batch_s = float(rate_hz), float(batch_s)
        self.rate_fn, self.noise_rad_s, self.drift_ppm = rate_fn, noise_rad_s, drift_ppm
        self.int16_scale = int16_scale
        self.garbage_prob, self.drop_prob, self.corrupt_prob = garbage_prob, drop_prob, corrupt_prob
        self.bad_rate_prob = bad_rate_prob
        self._time_glitches: list[int] = []
        self.clock = clock
        self._rng = np.random.default_rng(seed)
        super().__init__(link_dir, "thermod-emu-serial-")
        self.link_dir = link_dir or self._dir
        self.link = os.path.join(self.link_dir, f"usb-thermod_emu_IMU_{serial_number}-if00-port0")
        self._seq0 = seq0
        self._t_us0 = int(self._rng.integers(0, 2**32)) if t_us0 is None else int(t_us0)
        self.log = {"good": [], "dropped": [], "corrupted": [], "bad_rate": [], "offline": [],
                    "garbage_bytes": 0, "garbage_before": {}, "overrun_bytes": 0, "writes": 0}
        self.truth_t: dict[int, float] = {}       # seq → true host time (good frames only)
        self._lock = threading.Lock()
        self._master = self._slave = -1
        self.slave_path = ""
        self._pending = b""
        self._offline_until = -math.inf
        self._reset_on_return = False

    # -- pty ---------------------------------------------------------------------------------------
    def _open_pty(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)                    # no echo, no CR/LF translation: a binary link
        os.set_blocking(self._master, False)
        self.slave_path = os.ttyname(self._slave)
        tmp = self.link + ".new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(self.slave_path, tmp)
        os.replace(tmp, self.link)                 # atomic re-point, as udev does

    def _close_pty(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.link)
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1
        self._pending = b""

    # -- control -----------------------------------------------------------------------------------
    def _open(self) -> None:
        self._open_pty()
        self._epoch = self.clock()
        self._k = 0

    def _close(self) -> None:
        with self._lock:
            self._close_pty()

    def disconnect(self, seconds: float, *, reset_counters: bool = False) -> None:
        """Pull the cable for ``seconds``: both pty ends close, then a new pty appears at ``link``."""
        with self._lock:
            self._close_pty()
            self._offline_until = self.clock() + seconds
            self._reset_on_return = reset_counters

    def reboot(self) -> None:
        """Restart the device's counters (seq and time at 0) without dropping the link."""
        with self._lock:
            self._seq0 = -self._k
            self._t_us0 = -int(round(self._k * 1e6 / self.rate_hz))

    def glitch_times(self, t_us_values) -> None:
        """The next ``len(t_us_values)`` frames carry these device times (µs, mod 2**32)."""
        with self._lock:
            self._time_glitches.extend(int(v) for v in t_us_values)

    # -- writer ------------------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / (self.rate_hz * (1.0 + self.drift_ppm * 1e-6))
        next_write = self.clock()
        while not self._stop.is_set():
            next_write += self.batch_s
            delay = next_write - self.clock()
            if delay > 0:
                time.sleep(delay)
            else:
                next_write = self.clock()          # fell behind (loaded machine): do not burst-catch-up twice
            with self._lock:
                now = self.clock()
                k_now = int(math.floor((now - self._epoch) / period))
                if k_now <= self._k:
                    continue
                k = np.arange(self._k, k_now)
                self._k = k_now
                offline = now < self._offline_until or self._master < 0
                if offline:
                    self.log["offline"].extend((self._seq0 + k).tolist())
                    if now >= self._offline_until:
                        self._come_back(k_now)
                    continue
                self._write(self._frames(k, self._epoch + (k + 1.0) * period))

    def _come_back(self, k_now: int) -> None:
        if self._reset_on_return:
            self._seq0 = -k_now                     # the next sample is seq 0, time 0
            self._t_us0 = -int(round(k_now * 1e6 / self.rate_hz))
        self._open_pty()

    def _frames(self, k: np.ndarray, t: np.ndarray) -> bytes:
        n = len(k)
        if self.rate_fn is None:
            rate = np.zeros((n, 3))
        else:
            rate = np.asarray(self.rate_fn(t), np.float64).reshape(n, 3)
        if self.noise_rad_s:
            rate = rate + self._rng.normal(0, self.noise_rad_s, rate.shape)
        u = self._rng.random((n, 3))
        u_bad = self._rng.random(n) if self.bad_rate_prob else np.ones(n)    # same stream without it
        out = bytearray()
        for i in range(n):
            seq = int(self._seq0 + k[i])
            t_us = self._t_us0 + int(round(int(k[i]) * 1e6 / self.rate_hz))
            if u[i, 0] < self.garbage_prob:
                junk = self._rng.integers(0, 255, int(self._rng.integers(1, 17)))
                junk[junk >= 0xA5] += 1                # never a sync byte: garbage stays garbage
                out += junk.astype(np.uint8).tobytes()
                self.log["garbage_bytes"] += len(junk)
                self.log["garbage_before"][seq] = len(junk)
            if u[i, 1] < self.drop_prob:
                self.log["dropped"].append(seq)
                continue
            if self._time_glitches:
                t_us = self._time_glitches.pop(0)
            if u_bad[i] < self.bad_rate_prob:
                out += self._bad_rate_frame(seq, t_us)
                self.log["bad_rate"].append(seq)
                continue
            frame = bytearray(encode_frame(seq, t_us, rate[i], int16_scale=self.int16_scale))
            if u[i, 2] < self.corrupt_prob:
                pos = int(self._rng.integers(4, len(frame)))
                frame[pos] ^= 1 << int(self._rng.integers(0, 8))
                self.log["corrupted"].append(seq)
            else:
                self.log["good"].append(seq)
                self.truth_t[seq] = float(t[i])
            out += frame
        return bytes(out)

    def _bad_rate_frame(self, seq: int, t_us: int) -> bytes:
        bad = [math.nan, math.inf, -math.inf, 1e4][int(self._rng.integers(0, 4))]
        if self.int16_scale is None:
            rate = [0.1, 0.1, 0.1]
            rate[int(self._rng.integers(0, 3))] = bad
            return encode_frame(seq, t_us, rate)
        scale = [math.nan, math.inf, 0.0, -self.int16_scale][int(self._rng.integers(0, 4))]
        body = struct.pack("<BBII3hf", PAYLOAD_LEN[TYPE_I16], TYPE_I16, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFF,
                           100, -100, 5, scale)
        return SYNC + body + struct.pack("<H", crc16_ccitt(body))

    def _write(self, data: bytes) -> None:
        buf = self._pending + data
        try:
            n = os.write(self._master, buf)
        except BlockingIOError:
            n = 0
        except OSError as e:
            if e.errno not in (errno.EIO, errno.EAGAIN):
                raise
            n = 0
        self._pending = buf[n:]
        self.log["writes"] += 1
        if len(self._pending) > 1 << 16:           # nobody reads: the adapter's buffer overruns
            self.log["overrun_bytes"] += len(self._pending)
            self._pending = b""
