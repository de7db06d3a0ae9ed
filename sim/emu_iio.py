"""A Linux IIO gyro in a temp directory: the sysfs tree the kernel would show plus a FIFO standing in
for /dev/iio:deviceN, fed in real time while ``buffer/enable`` reads 1.

The tree (``<root>/iio:device0/...``) has ``name``, ``scan_elements/*_{en,index,type}`` for the
gyro, accelerometer, temperature and timestamp channels, ``buffer/{length,enable}``,
``current_timestamp_clock``, the scale files and the sampling frequency. A second device
(``iio:device1``, another name) makes the lookup by name meaningful.

The writer thread reads the configuration the way the kernel freezes it when the buffer is
enabled: which elements are on, their types and indices. It packs records with its own
implementation of the ABI rules (each element aligned to its storage size, records padded to the
largest), stamps the timestamp channel with the CLOCK_MONOTONIC ns of the data-ready interrupt
(true sample time + ``irq_latency_s`` jitter), and writes them to the FIFO. A full FIFO drops new
records like the kernel's kfifo (counted in ``dropped``); ``pipe_size`` shrinks it to make that easy.
Time stamp faults: ``corrupt_timestamps(values)`` (the next records carry these stamps instead) and
``shift_timestamps(seconds)`` (every later stamp is off by that much: a changed time base).

Layouts (``layout=``): "s16" (le:s16/16>>0 gyro, 16-byte records with the timestamp), "be20"
(be:s20/32>>4 gyro with per-axis scales, 24-byte records: 12 bytes of gyro padded to the 8-byte
timestamp), "s16-nots" (no timestamp channel: 6-byte records).
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from thermod.sim.emu_thread import ThreadedEmulator

F_SETPIPE_SZ = 1031

# element → (index, type) per layout; the gyro is what matters, the rest fills the record when enabled
LAYOUTS = {
    "s16": {"in_accel_x": (0, "le:s16/16>>0"), "in_accel_y": (1, "le:s16/16>>0"),
            "in_accel_z": (2, "le:s16/16>>0"), "in_anglvel_x": (3, "le:s16/16>>0"),
            "in_anglvel_y": (4, "le:s16/16>>0"), "in_anglvel_z": (5, "le:s16/16>>0"),
            "in_temp": (6, "le:s16/16>>0"), "in_timestamp": (7, "le:s64/64>>0")},
    "be20": {"in_temp": (0, "be:u12/16>>4"), "in_anglvel_x": (1, "be:s20/32>>4"),
             "in_anglvel_y": (2, "be:s20/32>>4"), "in_anglvel_z": (3, "be:s20/32>>4"),
             "in_timestamp": (4, "le:s64/64>>0")},
    "s16-nots": {"in_anglvel_x": (0, "le:s16/16>>0"), "in_anglvel_y": (1, "le:s16/16>>0"),
                 "in_anglvel_z": (2, "le:s16/16>>0"), "in_temp": (3, "le:s16/16>>0")},
}


def _parse(t: str) -> tuple[str, bool, int, int, int]:
    end, rest = t.split(":")
    sign, rest = rest[0], rest[1:]
    bits, rest = rest.split("/")
    storage, shift = rest.split(">>")
    return end, sign == "s", int(bits), int(storage.split("X")[0]), int(shift)


class IIOEmulator(ThreadedEmulator):
    """Fake IIO gyro device tree + FIFO; ``start()`` the writer, point the driver at ``sysfs_root``
    and ``dev_path``."""

    thread_name = "emu-iio"

    def __init__(self, root: str | os.PathLike | None = None, *, name: str = "icm42688", layout: str = "s16",
                 rate_hz: float = 1000.0, scale: float = 0.001065264, batch_s: float = 0.004,
                 rate_fn: Callable[[np.ndarray], np.ndarray] | None = None, drift_ppm: float = 0.0,
                 irq_latency_s: tuple[float, float] = (20e-6, 80e-6), pipe_size: int | None = None,
                 seed: int = 0):
        super().__init__(root, "thermod-emu-iio-")
        self.root = Path(root or self._dir)
        self.sysfs_root = self.root / "sys/bus/iio/devices"
        self.dir = self.sysfs_root / "iio:device0"
        self.dev_path = str(self.root / "dev/iio:device0")
        self.name, self.layout = name, LAYOUTS[layout]
        self.rate_hz, self.scale, self.batch_s = float(rate_hz), float(scale), float(batch_s)
        self.rate_fn, self.drift_ppm, self.irq_latency_s = rate_fn, drift_ppm, irq_latency_s
        self.pipe_size = pipe_size
        self._fd = -1                                  # the writer's end of the FIFO, once started
        self._rng = np.random.default_rng(seed)
        self.counters = {"records": 0, "dropped": 0, "enables": 0}
        self.truth: list[tuple[float, np.ndarray]] = []   # (true time, rate) of every record written
        self._ts_lock = threading.Lock()
        self._ts_override: list[int] = []
        self._ts_shift_ns = 0
        self._build(layout)

    # -- the tree ----------------------------------------------------------------------------------
    def _put(self, rel: str, value) -> None:
        p = self.dir / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(f"{value}\n")

    def _get(self, rel: str) -> str:
        return (self.dir / rel).read_text().strip()

    def _build(self, layout: str) -> None:
        other = self.sysfs_root / "iio:device1"
        other.mkdir(parents=True)
        (other / "name").write_text("ads1015\n")
        self._put("name", self.name)
        for el, (idx, typ) in self.layout.items():
            self._put(f"scan_elements/{el}_en", 0)
            self._put(f"scan_elements/{el}_index", idx)
            self._put(f"scan_elements/{el}_type", typ)
        self._put("buffer/length", 1)
        self._put("buffer/enable", 0)
        self._put("current_timestamp_clock", "realtime")
        self._put("in_anglvel_sampling_frequency", f"{self.rate_hz:g}")
        self._put("in_anglvel_sampling_frequency_available", "12.5 25 50 100 200 500 1000 2000 4000")
        if layout == "be20":                          # per-axis calibration scales
            self.axis_scale = self.scale * np.array([1.0, 1.01, 0.99])
            for a, s in zip("xyz", self.axis_scale, strict=True):
                self._put(f"in_anglvel_{a}_scale", f"{s:.9f}")
        else:
            self.axis_scale = np.full(3, self.scale)
            self._put("in_anglvel_scale", f"{self.scale:.9f}")
        self._put("in_accel_scale", "0.000598")
        Path(self.dev_path).parent.mkdir(parents=True, exist_ok=True)
        os.mkfifo(self.dev_path)

    # -- control -----------------------------------------------------------------------------------
    def _open(self) -> None:
        # O_RDWR: never blocks on a FIFO without reader; O_NONBLOCK: a full FIFO drops, as kfifo does
        self._fd = os.open(self.dev_path, os.O_RDWR | os.O_NONBLOCK)
        if self.pipe_size:
            fcntl.fcntl(self._fd, F_SETPIPE_SZ, self.pipe_size)

    def _close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self._fd)

    def corrupt_timestamps(self, values) -> None:
        """The next ``len(values)`` records carry these time stamps (ns) instead of their own."""
        with self._ts_lock:
            self._ts_override.extend(int(v) for v in values)

    def shift_timestamps(self, seconds: float) -> None:
        """Every record from now on is stamped ``seconds`` off its true interrupt time."""
        with self._ts_lock:
            self._ts_shift_ns += int(round(seconds * 1e9))

    # -- writer ------------------------------------------------------------------------------------
    def _freeze(self):
        """Scan configuration at buffer enable: [(element, offset, endian, signed, bits, storage, shift)]."""
        en = [(int(self._get(f"scan_elements/{el}_index")), el) for el in self.layout
              if self._get(f"scan_elements/{el}_en") == "1"]
        off, biggest, out = 0, 1, []
        for _, el in sorted(en):
            end, signed, bits, storage, shift = _parse(self._get(f"scan_elements/{el}_type"))
            size = storage // 8
            off = (off + size - 1) // size * size
            out.append((el, off, end, signed, bits, storage, shift))
            off += size
            biggest = max(biggest, size)
        return out, (off + biggest - 1) // biggest * biggest

    def _run(self) -> None:
        active = False
        period = 1.0 / (self.rate_hz * (1.0 + self.drift_ppm * 1e-6))
        while not self._stop.wait(self.batch_s):
            on = self._get("buffer/enable") == "1"
            if on and not active:
                fields, size = self._freeze()
                self.record_size = size
                self.rate_hz = float(self._get("in_anglvel_sampling_frequency"))
                period = 1.0 / (self.rate_hz * (1.0 + self.drift_ppm * 1e-6))
                epoch, k_done = time.monotonic(), 0
                self.counters["enables"] += 1
                active = True
            elif not on:
                active = False
                continue
            k_now = int(math.floor((time.monotonic() - epoch) / period))
            if k_now <= k_done:
                continue
            t = epoch + (np.arange(k_done, k_now) + 1.0) * period
            k_done = k_now
            self._write(self._records(fields, size, t))

    def _records(self, fields, size: int, t: np.ndarray) -> list[bytes]:
        n = len(t)
        rate = np.zeros((n, 3)) if self.rate_fn is None else np.asarray(self.rate_fn(t), float).reshape(n, 3)
        raw = np.rint(rate / self.axis_scale).astype(np.int64)
        irq = t + self._rng.uniform(*self.irq_latency_s, n)
        out = []
        for i in range(n):
            rec = bytearray(size)
            for el, off, end, signed, bits, storage, shift in fields:
                if el.startswith("in_anglvel_"):
                    v = int(raw[i, "xyz".index(el[-1])])
                    lim = (1 << (bits - 1)) if signed else (1 << bits)
                    v = max(-lim, min(lim - 1, v)) if signed else max(0, min(lim - 1, v))
                elif el == "in_timestamp":
                    with self._ts_lock:
                        bad = self._ts_override.pop(0) if self._ts_override else None
                        v = int(round(irq[i] * 1e9)) + self._ts_shift_ns if bad is None else bad
                elif el == "in_temp":
                    v = 1234
                else:
                    v = 100
                word = (v & ((1 << bits) - 1)) << shift
                rec[off:off + storage // 8] = word.to_bytes(storage // 8, "big" if end == "be" else "little")
            out.append(bytes(rec))
            self.truth.append((float(t[i]), rate[i]))
        return out

    def _write(self, records: list[bytes]) -> None:
        # ≤ PIPE_BUF per write is atomic: whole records land or the chunk is dropped (kfifo full)
        per = max(1, 4096 // len(records[0]))
        for i in range(0, len(records), per):
            chunk = b"".join(records[i:i + per])
            try:
                os.write(self._fd, chunk)
                self.counters["records"] += len(chunk) // len(records[0])
            except BlockingIOError:
                self.counters["dropped"] += len(chunk) // len(records[0])
