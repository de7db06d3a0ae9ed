"""PX4 ULog gyro through pyulog, for `thermod.io.flightlog`: ``sensor_combined``, else
``vehicle_angular_velocity``, of the lowest instance, in rad/s FRD on the log's µs clock. ULog files
joined end to end (``cat``: pyulog mixes them up, either's samples as one log) are read each from its
own header on."""

from __future__ import annotations

import contextlib
import io
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("thermod.io.flightlog")      # what it says is the flight-log reader's

MAGIC = b"ULog\x01\x12\x35"
TOPICS = (("sensor_combined", ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]")),
          ("vehicle_angular_velocity", ("xyz[0]", "xyz[1]", "xyz[2]")))


def gyro_logs(path: Path, error, max_samples: int) -> tuple[list[tuple[np.ndarray, np.ndarray, str]],
                                                                tuple[int, str] | None]:
    """([(t s, rate [N, 3], topic)] of each ULog in the file, (how many failed, the first's problem)
    or None). `error(path, problem)` is the exception raised: for a lone ULog that cannot be read, or
    when no joined one has a gyro."""
    starts = _starts(path)
    bounds = list(zip(starts, [*starts[1:], path.stat().st_size], strict=True))
    logs, n_failed, first = [], 0, ""
    for a, b in bounds:
        try:
            logs.append(_gyro(path, a, b, error, max_samples))
        except error as e:
            if len(bounds) == 1:
                raise
            n_failed += 1
            first = first or f"the one at byte {a}: {e.problem}"
    if not logs:
        raise error(path, f"{len(bounds)} ULog files joined, none with a gyro ({first})")
    return logs, ((n_failed, first) if n_failed else None)


def _starts(path: Path, chunk: int = 1 << 24) -> list[int]:
    """Byte offsets of the ULog headers in the file (0 first), found a chunk at a time."""
    starts, offset, tail = [0], 0, b""
    with open(path, "rb") as f:
        while block := f.read(chunk):
            data = tail + block
            i = data.find(MAGIC, 1 if offset == 0 else 0)
            while i >= 0:
                starts.append(offset - len(tail) + i)
                i = data.find(MAGIC, i + 1)
            tail = data[-(len(MAGIC) - 1):]
            offset += len(block)
    return sorted(set(starts))


class _Window(io.RawIOBase):
    """Bytes [start, end) of an open file, as a file of their own."""

    def __init__(self, f, start: int, end: int):
        super().__init__()
        self._f, self._start, self._size, self._pos = f, start, end - start, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = 0) -> int:
        pos = (0, self._pos, self._size)[whence] + offset
        if pos < 0:
            raise OSError("seek before the start")
        self._pos = pos
        return pos

    def read(self, n: int | None = -1) -> bytes:
        left = max(0, self._size - self._pos)
        self._f.seek(self._start + self._pos)
        data = self._f.read(left if n is None or n < 0 else min(n, left))
        self._pos += len(data)
        return data


def _gyro(path: Path, start: int, end: int, error, max_samples: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(t, rate, topic) of the ULog in bytes [start, end) of the file."""
    from pyulog import ULog

    said = io.StringIO()          # pyulog prints a line per damaged record: one summary line instead
    try:
        with contextlib.redirect_stdout(said), open(path, "rb") as f:
            whole = start == 0 and end == path.stat().st_size
            ulog = ULog(str(path) if whole else _Window(f, start, end),
                        message_name_filter_list=[name for name, _ in TOPICS], disable_str_exceptions=True)
    except Exception as e:                # noqa: BLE001 - pyulog raises plain Exceptions on damage
        raise error(path, f"pyulog cannot read it: truncated or corrupt ULog ({type(e).__name__}: {e})"
                    ) from None
    finally:
        lines = [ln for ln in said.getvalue().splitlines() if ln.strip()]
        if lines:
            log.warning("%s: pyulog reported %d damaged or unexpected records (first: %s)", path, len(lines),
                        lines[0][:200])
    for name, cols in TOPICS:
        ds = [d for d in ulog.data_list if d.name == name and all(c in d.data for c in cols)]
        if ds:
            d = min(ds, key=lambda d: d.multi_id)
            if len(d.data["timestamp"]) > max_samples:
                raise error(path, f"{name}: over {max_samples} samples")
            t = np.asarray(d.data["timestamp"], dtype=np.float64) * 1e-6
            rate = np.stack([np.asarray(d.data[c], dtype=np.float64) for c in cols], axis=1)
            return t, rate, name
    raise error(path, "no gyro samples (expected a sensor_combined or vehicle_angular_velocity topic; the "
                      "log may be truncated)")
