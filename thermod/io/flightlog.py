"""Gyro from flight-controller logs, through the flight stacks' own well-kept parsers.

`read_flight_log(path)` returns a `FlightLog`: the gyro samples of one log, on the log's own clock,
as angular rates in one stated body frame. Parsers: telemetry-parser (Gyroflow's: Betaflight/INAV
blackbox ``.bbl``/``.bfl``, ArduPilot ``.bin``, Gyroflow ``.gcsv``, and the other formats it detects),
pyulog (PX4 ``.ulg``: ``sensor_combined``, else ``vehicle_angular_velocity``), and a reader of the
``time`` and ``gyroADC`` columns of a Betaflight/INAV CSV (Blackbox Explorer's export and
blackbox_decode's, in the units its column names state; telemetry-parser reads neither reliably).
A text log behind a UTF-8 byte order mark is read without it.

The rules it keeps: `t` is float64 s on the log's own clock, never shifted (the offset to the video
is the sync's to find); `rate` is float64 [N, 3] rad/s in the frame `frame` names — ``"FRD"`` (the
flight controller's body frame; Betaflight's FLU rates become (roll, −pitch, −yaw)), ``"imu"`` (a
gcsv logger's own axes, its `orientation` string kept unapplied) or ``"gyroflow"`` (other formats).
A file with several logs (one per arming, or files joined end to end) gives the longest
(`log_index` picks another); ArduPilot's interleaved IMU instances give the first. A camera mount
is a proper rotation ``camera_from_body`` (ω_camera = camera_from_body · ω_body;
`FORWARD_CAMERA_FROM_FRD` for a forward, upright camera).

`write_gcsv`, `write_betaflight_csv` and `write_ardupilot_bin` write formats telemetry-parser reads
back. Errors are `FlightLogError` naming the file; sizes and sample counts are bounded. Clocks,
axes and orientation strings: docs/design.md §3, "Flights from other tools".
"""

from __future__ import annotations

import array
import contextlib
import csv
import logging
import math
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from thermod.errors import FileError
from thermod.paths import input_problem, output_problem

log = logging.getLogger(__name__)

MAX_FILE_BYTES = 4 * 2**30
MAX_TP_FILE_BYTES = 64 * 2**20     # telemetry-parser formats: ~1.4 kB of Python objects per sample
MAX_CSV_BYTES = 2**30              # a Betaflight CSV is read a row at a time into 32 bytes per sample
MAX_BAD_ROW_FRACTION = 0.001       # unreadable CSV rows a log may have (a cut last row, a corrupt frame)
HEAD_BYTES = 1 << 16               # where a text log's header rows are looked for
BOM = b"\xef\xbb\xbf"                # a UTF-8 byte order mark, as Windows editors and exporters write it
PROBE_BYTES = (2**15, 2**18, 2**20)  # telemetry() holds ~700 bytes of Python objects per byte read
SEGMENT_GAP_S = 1.0
MAX_SAMPLES = 200_000_000          # 8 kHz for ~7 hours
MIN_RATE_HZ, MAX_RATE_HZ = 10.0, 100_000.0
MAX_DROPPED_FRACTION = 0.001       # isolated out-of-order samples a log may have
MAX_CLOCK_S = 1e10                 # ~300 years; float64 still resolves 2 µs there
# no MEMS gyro reads this (the widest full scale, ±4000 °/s, is 70 rad/s); a log in °/s read as rad/s
# exceeds it as soon as the camera turns at 80 °/s
MAX_GYRO_RAD_S = 80.0
DEG = math.pi / 180.0

# ω_cam = M · ω_FRD for a camera looking along the body's x axis, upright (its x right = body y,
# its y down = body z, its z forward = body x)
FORWARD_CAMERA_FROM_FRD = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
# Betaflight's gyroADC axes (x forward, y left, z up) → FRD
FRD_FROM_BETAFLIGHT = np.diag([1.0, -1.0, -1.0])


def axis_aligned_rotations() -> np.ndarray:
    """The 24 proper rotations whose entries are 0 or ±1 (the axis-aligned camera mounts), [24, 3, 3],
    in a fixed order: the signed permutation matrices with determinant +1, sorted by their entries
    (the identity is the last)."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.array(sorted(out, key=lambda m: tuple(m.ravel())))


class FlightLogError(FileError):
    """A flight log cannot be read as asked: names the file and what was expected."""


@dataclass(frozen=True)
class FlightLog:
    """One log's gyro: times t [N] (float64 s, strictly increasing, the log's own clock), rates
    [N, 3] (float64 rad/s in `frame`, module docstring), the median sample rate (Hz), the
    source format ("betaflight", "betaflight-csv", "ardupilot", "gcsv", "px4-ulog", or
    telemetry-parser's name of another format), the file, which log of a multi-log file it is,
    and how many out-of-order samples were dropped."""

    path: str
    source_format: str
    t: np.ndarray
    rate: np.ndarray
    rate_hz: float
    frame: str
    orientation: str = ""
    log_index: int = 0
    n_logs: int = 1
    n_dropped: int = 0
    model: str = ""

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0])

    def __len__(self) -> int:
        return len(self.t)


# ----------------------------------------------------------------------------------------- reading
def read_flight_log(path: str | os.PathLike, log_index: int | None = None) -> FlightLog:
    """Read the gyro of a flight-controller log (module docstring).

    A file that holds several logs (a Betaflight ``.bbl`` with one log per arming: parts of the
    clock split at steps back or pauses over `SEGMENT_GAP_S`) gives the longest unless `log_index`
    (0-based) picks one; `FlightLog.n_logs` says how many there are."""
    path = Path(path)
    if (problem := input_problem(path)) is not None:
        raise FlightLogError(path, problem)
    size = path.stat().st_size
    if size == 0:
        raise FlightLogError(path, "empty file (expected a flight-controller log)")
    if size > MAX_FILE_BYTES:
        raise FlightLogError(path, f"{size / 2**30:.1f} GiB, over the {MAX_FILE_BYTES / 2**30:.0f} GiB "
                                   "this reader accepts; cut the log to the flight")
    with open(path, "rb") as f:
        head = f.read(HEAD_BYTES)
    if head.startswith(b"ULog\x01\x12\x35"):
        return _read_ulog(path, log_index)
    if (columns := _betaflight_csv_columns(head)) is not None:
        return _read_betaflight_csv(path, *columns, log_index)
    if head.startswith(BOM):
        return _without_bom(path, log_index, gcsv=head[len(BOM):].startswith(b"GYROFLOW IMU LOG"))
    if head.startswith(b"GYROFLOW IMU LOG"):
        _check_gcsv_header(path)
    return _read_telemetry_parser(path, log_index)


def _without_bom(path: Path, log_index: int | None, gcsv: bool) -> FlightLog:
    """A text log behind a UTF-8 byte order mark: telemetry-parser recognises no format behind one, so
    it reads a copy without it; errors and the log still name `path`. `gcsv`: a .gcsv's header is
    checked first, as without the mark."""
    _check_tp_size(path)
    with tempfile.TemporaryDirectory(prefix="thermod-log-") as d:
        plain = Path(d) / path.name
        with open(path, "rb") as src, open(plain, "wb") as dst:
            src.seek(len(BOM))
            shutil.copyfileobj(src, dst)
        try:
            if gcsv:
                _check_gcsv_header(plain)
            log = _read_telemetry_parser(plain, log_index)
        except FlightLogError as e:
            raise FlightLogError(path, e.problem) from None
    return replace(log, path=str(path))


def _check_tp_size(path: Path) -> None:
    if path.stat().st_size > MAX_TP_FILE_BYTES:
        raise FlightLogError(path, f"{path.stat().st_size / 2**20:.0f} MiB, over the "
                                   f"{MAX_TP_FILE_BYTES / 2**20:.0f} MiB this reader accepts for this "
                                   "format (telemetry-parser holds every sample in memory); cut the log")


# ------------------------------------------------------------------------------- Betaflight CSV
def _betaflight_csv_columns(head: bytes) -> tuple[int, list[str], str] | None:
    """(0-based line of the column names, the names, the firmware) if the file's first bytes are a
    Betaflight/INAV CSV — Blackbox Explorer's export (quoted ``"Product"``/``"Firmware revision"``
    rows, then ``"loopIteration","time",…``) or blackbox_decode's (``loopIteration, time (us), …``,
    units in brackets) — else None."""
    text = head.removeprefix(BOM).decode("utf-8", "replace")
    if "loopIteration" not in text:
        return None
    firmware = ""
    for i, line in enumerate(text.splitlines()):
        row = next(csv.reader([line], skipinitialspace=True), [])
        if not row:
            continue
        if row[0].strip() == "loopIteration":
            return i, [c.strip() for c in row], firmware
        if len(row) == 2 and row[0].strip() == "Firmware revision":
            firmware = row[1].strip()
        elif row[0].strip().lstrip("-").replace(".", "", 1).isdigit():
            return None                                  # a data row before the names: not this format
    return None


def _split_unit(name: str) -> tuple[str, str]:
    """``"gyroADC[0] (deg/s)"`` → (``"gyroADC[0]"``, ``"deg/s"``); no bracket → (name, "")."""
    base, _, unit = name.partition(" (")
    return base.strip(), unit.rstrip(")").strip() if unit else ""


TIME_UNITS_S = {"": 1e-6, "us": 1e-6, "s": 1.0}           # blackbox_decode --unit-frame-time
GYRO_UNITS_RAD_S = {"": DEG, "raw": DEG, "deg/s": DEG, "rad/s": 1.0}   # --unit-rotation; raw is °/s


def _csv_layout(path: Path, names: list[str]) -> tuple[list[int], float, float, bool]:
    """(columns of time and gyroADC[0..2], seconds per time unit, rad/s per gyro unit, whether the
    time is Betaflight's 32-bit µs counter) from a row of column names."""
    split = [_split_unit(n) for n in names]
    where = {base: (i, unit) for i, (base, unit) in reversed(list(enumerate(split)))}
    if "time" not in where:
        raise FlightLogError(path, f"no time column in the CSV's column names (expected loopIteration, "
                                   f"time, …; got {', '.join(names[:4])}, …)")
    missing = [f"gyroADC[{k}]" for k in range(3) if f"gyroADC[{k}]" not in where]
    if missing:
        raise FlightLogError(path, f"no {', '.join(missing)} column: expected the gyro in gyroADC[0..2] (was "
                                   "the gyro left out of the blackbox fields or of the export?)")
    cols = [where["time"][0]] + [where[f"gyroADC[{k}]"][0] for k in range(3)]
    t_unit, g_units = where["time"][1], {where[f"gyroADC[{k}]"][1] for k in range(3)}
    if t_unit not in TIME_UNITS_S:
        raise FlightLogError(path, f"time column in {t_unit!r}: expected us or s")
    if len(g_units) != 1 or not g_units <= GYRO_UNITS_RAD_S.keys():
        raise FlightLogError(path, f"gyroADC columns in {' and '.join(sorted(map(repr, g_units)))}: expected "
                                   "one of raw (°/s), deg/s or rad/s for all three")
    return cols, TIME_UNITS_S[t_unit], GYRO_UNITS_RAD_S[g_units.pop()], t_unit != "s"


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _read_betaflight_csv(path: Path, names_line: int, names: list[str], firmware: str,
                         log_index: int | None) -> FlightLog:
    """The ``time`` and ``gyroADC[0..2]`` columns of a Betaflight CSV, a row at a time (the other
    columns are not kept). Betaflight and INAV log the gyro in °/s about x forward, y left, z up; a
    blackbox_decode export states other units in brackets. A row that does not parse (a last row cut
    by a crash, a corrupt frame's ``X`` time, ``NaN``) is skipped, up to `MAX_BAD_ROW_FRACTION`.
    Exports joined end to end are read as one: each header's rows are skipped and its column names
    taken, and the 32-bit µs time wrapping past 2³² µs (71.6 min after power-up) is carried on."""
    size = path.stat().st_size
    if size > MAX_CSV_BYTES:
        raise FlightLogError(path, f"{size / 2**20:.0f} MiB, over the {MAX_CSV_BYTES / 2**20:.0f} MiB this "
                                   "reader accepts for a Betaflight CSV; cut the log to the flight")
    cols, t_scale, g_scale, wraps = _csv_layout(path, names)
    values = array.array("d")
    n_rows = n_bad = 0
    first_bad = ""
    try:
        with open(path, encoding="utf-8-sig", errors="replace", newline="") as f:
            for _ in range(names_line + 1):
                f.readline()
            for row in csv.reader(f, skipinitialspace=True):
                if not row:
                    continue
                head = row[0].strip()
                if head == "loopIteration":                 # the names of a log joined after the first
                    cols, t_scale, g_scale, more = _csv_layout(path, [c.strip() for c in row])
                    wraps = wraps and more
                    continue
                if len(row) == 2 and not _is_number(head):   # a header row ("Product", "Firmware revision")
                    continue
                n_rows += 1
                try:
                    v = [float(row[c]) for c in cols]
                    if not all(math.isfinite(x) for x in v):
                        raise ValueError
                except (ValueError, IndexError):
                    n_bad += 1
                    first_bad = first_bad or f"data row {n_rows}: {','.join(row)[:80]!r}"
                    continue
                values.extend((v[0] * t_scale, v[1] * g_scale, v[2] * g_scale, v[3] * g_scale))
                if len(values) > 4 * MAX_SAMPLES:
                    raise FlightLogError(path, f"over {MAX_SAMPLES} gyro samples, the most this reader takes")
    except (csv.Error, UnicodeError) as e:
        raise FlightLogError(path, f"not readable as CSV after {n_rows} data rows ({e})") from None
    if n_bad > max(1, MAX_BAD_ROW_FRACTION * n_rows) or 0 < n_bad == n_rows:
        raise FlightLogError(path, f"{n_bad} of {n_rows} data rows without a number for time and "
                                   f"gyroADC[0..2] (first: {first_bad}): a corrupt or damaged export")
    if n_bad:
        log.warning("%s: skipped %d unreadable data row(s) of %d (%s)", path, n_bad, n_rows, first_bad)
    a = np.frombuffer(values, dtype=np.float64).reshape(-1, 4)
    t = _unwrap_us32(a[:, 0]) if wraps else a[:, 0]
    rate = a[:, 1:] @ FRD_FROM_BETAFLIGHT.T
    t, rate, index, n_logs, lone = _pick_log(path, t, rate, log_index)
    return _finish(path, "betaflight-csv", t, rate, "FRD", "", index, n_logs,
                   f"BlackBox {firmware}".strip(), lone)


US32_S = 2**32 * 1e-6      # Betaflight's time field: µs since power-up in 32 bits, 4294.967296 s


def _unwrap_us32(t: np.ndarray) -> np.ndarray:
    """Times (s) of a 32-bit µs counter carried past its wrap: a step back that lands within
    `SEGMENT_GAP_S` after 2³² µs gains 2³² µs (blackbox_decode and Blackbox Explorer do this
    themselves; other exporters write the counter as it is)."""
    if len(t) < 2:
        return t
    dt = np.diff(t)
    wrap = (dt < 0) & (dt + US32_S > 0) & (dt + US32_S <= SEGMENT_GAP_S)
    if not np.any(wrap):
        return t
    return t + US32_S * np.r_[0, np.cumsum(wrap)]


def _pick_log(path: Path, t: np.ndarray, rate: np.ndarray, log_index: int | None
              ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """(t, rate, index, number of logs, lone outliers dropped) of the log `log_index` picks (the
    longest by default) among the parts of the clock `_segments` finds, lone wild stamps dropped."""
    t, rate, lone = _without_lone_outliers(path, t, rate)
    segments = _segments(t)
    index = _chosen(path, [b - a for a, b in segments], log_index)
    lo, hi = segments[index]
    return t[lo:hi], rate[lo:hi], index, len(segments), lone


def _chosen(path: Path, sizes: list, log_index: int | None) -> int:
    """The index of the log `log_index` (0-based) names among logs of these `sizes`, or of the
    largest; a FlightLogError when there is no such log."""
    if log_index is None:
        return int(np.argmax(sizes))
    if 0 <= log_index < len(sizes):
        return int(log_index)
    raise FlightLogError(path, f"log {log_index}: the file holds {len(sizes)} log(s)")


def _without_lone_outliers(path: Path, t: np.ndarray, rate: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(t, rate, count) without the lone wild stamps of `_lone_outliers` (a glitch to drop, not a
    boundary between logs), checking the clock is one a log keeps: out-of-order stamps no more than
    `MAX_DROPPED_FRACTION` (a clock that repeats every stamp is refused here, before dropping them
    leaves nothing to judge) and the others within ±`MAX_CLOCK_S`."""
    lone = _lone_outliers(t)
    n = int(np.sum(lone))
    if n > MAX_DROPPED_FRACTION * len(t):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise FlightLogError(path, f"gyro sample {i} at {_secs(t[i])} s is not after the one before "
                                   f"({_secs(t[i - 1])} s): expected strictly increasing times ({n} of "
                                   f"{len(t)} samples out of order or repeated)")
    far = ~(np.abs(t) <= MAX_CLOCK_S) & ~lone
    if np.any(far):
        i = int(np.argmax(far))
        raise FlightLogError(path, f"gyro sample {i} at {t[i]:.6g} s: expected a log clock within "
                                   f"±{MAX_CLOCK_S:.0e} s (a corrupt time, or times in the wrong unit)")
    return t[~lone], rate[~lone], n


def _check_gcsv_header(path: Path, max_bytes: int = 1 << 16) -> None:
    """A .gcsv header's `orientation` and `tscale` checked before telemetry-parser reads them (it
    panics on a bad orientation, and a non-number tscale leaves every time empty)."""
    with open(path, "rb") as f:
        lines = f.read(max_bytes).decode("utf-8", "replace").splitlines()
    for line in lines[1:]:
        key, _, value = line.partition(",")
        key, value = key.strip(), value.strip()
        if key == "t" or key[:1].isdigit():
            return                                          # the column names: the header is over
        if key == "orientation":
            _check_orientation(path, value)
        if key in ("tscale", "gscale"):
            try:
                ok = math.isfinite(float(value)) and float(value) > 0
            except ValueError:
                ok = False
            if not ok:
                raise FlightLogError(path, f"{key} {value!r}: expected a positive number")


def _read_telemetry_parser(path: Path, log_index: int | None) -> FlightLog:
    """telemetry-parser's `normalized_imu()` carries the gyro alone (its `telemetry()` returns every
    logged field as Python objects: 470 MB for a 0.66 MB blackbox log), but re-bases the times on
    the file's first gyro sample and rotates the axes into Gyroflow's frame. The raw samples of a
    short prefix of the file give that first time and the axis mapping, which are undone here."""
    _check_tp_size(path)
    with tempfile.TemporaryDirectory(prefix="thermod-log-") as d:
        # alone in a folder: telemetry-parser reads a sibling NAME.gcsv instead of the file it is given
        alone = Path(d) / path.name
        alone.symlink_to(path.resolve())
        parser = _tp_call(path, lambda: _tp_parser(alone))
        camera, model = str(parser.camera or ""), str(parser.model or "")
        imu = _tp_call(path, parser.normalized_imu)
        rows = [r for r in (imu or []) if isinstance(r, dict) and r.get("gyro") is not None]
        if not rows:      # before the probe, which would parse every other field of the file's first MiB
            raise FlightLogError(path, f"no gyro samples in this {camera or 'log'} (gyro logging disabled, "
                                       "or the file is truncated)")
        if len(rows) > MAX_SAMPLES:
            raise FlightLogError(path, f"{len(rows)} gyro samples, over the {MAX_SAMPLES} this reader "
                                       "accepts")
        probe = _probe_prefix(path, Path(d) / "prefix")
    try:
        a = np.array([(r["timestamp_ms"], *r["gyro"]) for r in rows], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise FlightLogError(path, "gyro samples without a time and three rates (corrupt log)") from None
    fmt, frame = _family(path, camera)
    if probe is None:
        raise FlightLogError(path, "no gyro sample with a time in the first "
                                   f"{PROBE_BYTES[-1] // 2**20} MiB (expected a flight-controller log)")
    t0, orientation = probe
    t = a[:, 0] * 1e-3 + t0
    normalized = a[:, 1:4] * DEG
    if fmt.startswith("betaflight") or fmt == "ardupilot":
        # both families land in Gyroflow's frame as G = (−z, −y, −x) of FRD (module docstring)
        rate = -normalized[:, ::-1]
    elif fmt == "gcsv":
        rate = _unorient(path, normalized, orientation)
    else:
        rate, frame = normalized, "gyroflow"
    finite = np.isfinite(t) & np.all(np.isfinite(rate), axis=1)
    if not np.all(finite):
        raise FlightLogError(path, f"{int(np.sum(~finite))} gyro samples with non-finite time or rate")
    if fmt == "ardupilot":
        t, rate = _first_imu(path, t, rate)
    t, rate, index, n_logs, lone = _pick_log(path, t, rate, log_index)
    return _finish(path, fmt, t, rate, frame, orientation if frame == "imu" else "", index, n_logs,
                   f"{camera} {model}".strip(), lone)


def _secs(x: float) -> str:
    """A log time for a message: µs digits, unless it is too large for them to mean anything."""
    return f"{x:.6f}" if abs(x) < 1e9 else f"{x:.6g}"


def _lone_outliers(t: np.ndarray) -> np.ndarray:
    """Samples whose stamp is out of order with both neighbours while the neighbours agree with each
    other (within `SEGMENT_GAP_S`)."""
    bad = np.zeros(len(t), dtype=bool)
    if len(t) >= 3:
        prev, cur, nxt = t[:-2], t[1:-1], t[2:]
        bad[1:-1] = ~((prev < cur) & (cur < nxt)) & (prev < nxt) & (nxt - prev < SEGMENT_GAP_S)
    return bad


def _tp_parser(path: Path):
    import telemetry_parser

    return telemetry_parser.Parser(str(path))


@contextlib.contextmanager
def _rust_stderr(path: Path):
    """File descriptor 2 into a temporary file while telemetry-parser runs: a Rust panic prints its
    message (and with RUST_BACKTRACE a backtrace) there before it arrives as an exception, which
    says the same. After a panic the capture goes to the debug log; else it is passed on to stderr.
    The redirection is process-wide: logs are read by offline commands, one at a time."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):        # no fd 2 (an embedding host): nothing to keep clean
        yield
        return
    panicked = False
    with tempfile.TemporaryFile() as cap:
        os.dup2(cap.fileno(), 2)
        try:
            yield
        except BaseException:
            panicked = True
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            cap.seek(0)
            said = cap.read(1 << 16)
            if panicked or b"panicked at" in said:
                if said:
                    log.debug("%s: telemetry-parser said: %s", path, said.decode("utf-8", "replace"))
            elif said:
                cap.seek(0)
                while block := cap.read(1 << 16):
                    os.write(2, block)


def _tp_call(path: Path, fn):
    """Call into telemetry-parser; its failures (a Rust panic arrives as a BaseException) become a
    FlightLogError naming the file, and the panic's own print is kept off stderr."""
    try:
        with _rust_stderr(path):
            return fn()
    except BaseException as e:            # noqa: BLE001 - pyo3's PanicException derives from BaseException
        if isinstance(e, (KeyboardInterrupt, SystemExit, MemoryError)):
            raise
        msg = str(e) or type(e).__name__
        if "Unsupported file format" in msg:
            raise FlightLogError(path, "not a log format telemetry-parser or pyulog reads (expected a "
                                       "Betaflight .bbl/.bfl, a Betaflight CSV from Blackbox Explorer or "
                                       "blackbox_decode with loopIteration, time and gyroADC[0..2] columns, "
                                       "ArduPilot .bin, Gyroflow .gcsv or PX4 .ulg)") from None
        if "No metadata" in msg:
            raise FlightLogError(path, "no gyro samples (no telemetry in the file, or it is truncated)"
                                 ) from None
        raise FlightLogError(path, f"the parser failed: truncated or corrupt ({' '.join(msg.split())[:300]})"
                             ) from None


def _probe_prefix(path: Path, folder: Path) -> tuple[float, str] | None:
    """(time of the file's first gyro sample, the gyro's orientation tag) from telemetry-parser's raw
    samples of the file's first bytes (growing prefixes, then the whole file); None if there is none."""
    folder.mkdir()
    size = path.stat().st_size
    with open(path, "rb") as f:
        for n in PROBE_BYTES:
            f.seek(0)
            part = folder / path.name
            part.write_bytes(f.read(min(n, size)))
            try:
                with _rust_stderr(path):
                    samples = _tp_parser(part).telemetry()
            except BaseException as e:    # noqa: BLE001 - a cut record can make the parser panic
                if isinstance(e, (KeyboardInterrupt, SystemExit, MemoryError)):
                    raise
                samples = None
            for s in samples or []:
                g = s.get("Gyroscope") if isinstance(s, dict) else None
                data = g.get("Data") if isinstance(g, dict) else None
                if isinstance(data, list) and data and isinstance(data[0], dict) and "t" in data[0]:
                    t0 = data[0]["t"]
                    if not (isinstance(t0, (int, float)) and math.isfinite(t0)):
                        raise FlightLogError(path, f"its first gyro sample's time is {t0!r}: expected a "
                                                   "finite number (a .gcsv's tscale must be one)")
                    o = g.get("Orientation")
                    return float(t0), (o if isinstance(o, str) else "")
            if n >= size:
                break
    return None


def _check_orientation(path: Path, orientation: str) -> None:
    """An orientation string is three of X, Y, Z, each once (lower case negates that axis)."""
    if len(orientation) != 3 or sorted(orientation.upper()) != ["X", "Y", "Z"]:
        raise FlightLogError(path, f"orientation {orientation!r}: expected a permutation of X, Y, Z "
                                   "(a lower-case letter negates that axis)")


def _unorient(path: Path, g: np.ndarray, orientation: str) -> np.ndarray:
    """Undo Gyroflow's axis mapping: out[i] = ±raw[axis] for each letter (lower case negates)."""
    o = orientation or "xzY"                       # telemetry-parser's default for a gcsv without one
    _check_orientation(path, o)
    raw = np.empty_like(g)
    for i, c in enumerate(o):
        raw[:, "XYZ".index(c.upper())] = g[:, i] * (1.0 if c.isupper() else -1.0)
    return raw


def _segments(t: np.ndarray) -> list[tuple[int, int]]:
    """[lo, hi) index ranges between discontinuities of the log clock: a step back or a pause of more
    than `SEGMENT_GAP_S` (the separate logs of one .bbl, an FC reboot)."""
    if len(t) < 2:
        return [(0, len(t))]
    dt = np.diff(t)
    cuts = np.flatnonzero((dt < -SEGMENT_GAP_S) | (dt > SEGMENT_GAP_S)) + 1
    edges = [0, *cuts.tolist(), len(t)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _family(path: Path, camera: str) -> tuple[str, str]:
    """(source_format, frame) from telemetry-parser's camera type."""
    if camera == "BlackBox":
        with open(path, "rb") as f:
            csv = b"H Product:Blackbox" not in f.read(4096)
        return ("betaflight-csv" if csv else "betaflight"), "FRD"
    if camera == "ArduPilot":
        return "ardupilot", "FRD"
    with open(path, "rb") as f:
        head = f.read(16)
    if head.startswith((b"GYROFLOW IMU LOG", b"CAMERA IMU LOG")):
        return "gcsv", "imu"
    return (camera or "unknown").lower(), "gyroflow"


def _first_imu(path: Path, t: np.ndarray, rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ArduPilot logs each IMU instance in turn under one message name, and telemetry-parser merges
    them in file order without the instance number: k interleaved streams, stamped at the same or
    nearly the same time. Their signature is an interval sequence that is irregular as a whole
    (0 or a few µs, then a loop period) and regular in every k-th sample; the first instance (the
    primary IMU) is kept."""
    if len(t) < 8:
        return t, rate
    dt = np.diff(t)
    if not (np.any(dt <= 0) or _irregular(dt)):
        return t, rate
    for k in (2, 3, 4):
        streams = [t[j::k] for j in range(k)]
        if len(streams[0]) - len(streams[-1]) <= 1 and all(
                len(s) > 2 and np.all(np.diff(s) > 0) and not _irregular(np.diff(s)) for s in streams):
            return t[0::k], rate[0::k]
    return t, rate          # not an interleave: _finish judges the times


def _irregular(dt: np.ndarray) -> bool:
    """Intervals of two kinds: the 90th percentile over 1.5 × the 10th (one sensor's loop jitter is a
    few %; interleaved instances alternate a few µs with a loop period)."""
    q10, q90 = np.percentile(dt, (10, 90))
    return bool(q10 <= 0 or q90 > 1.5 * q10)


def _read_ulog(path: Path, log_index: int | None) -> FlightLog:
    """PX4's gyro (`thermod.io.ulog`); of ULog files joined end to end, the longest by default."""
    from thermod.io import ulog

    logs, failed = ulog.gyro_logs(path, FlightLogError, MAX_SAMPLES)
    if failed:
        log.warning("%s: %d of the %d ULog files joined in it read without gyro (%s)", path, failed[0],
                    failed[0] + len(logs), failed[1])
    index = _chosen(path, [t[-1] - t[0] if len(t) else -1.0 for t, _, _ in logs], log_index)
    t, rate, name = logs[index]
    t, rate, lone = _without_lone_outliers(path, t, rate)
    return _finish(path, "px4-ulog", t, rate, "FRD", "", index, len(logs), f"PX4 {name}", lone)


def _finish(path: Path, fmt: str, t: np.ndarray, rate: np.ndarray, frame: str, orientation: str,
            index: int, n_logs: int, model: str, dropped_before: int = 0) -> FlightLog:
    """Check the samples: finite, ≥ 2, times strictly increasing (isolated out-of-order samples,
    ≤ 0.1 %, are dropped and counted), and a median rate within 10 Hz – 100 kHz."""
    if len(t) < 2:
        raise FlightLogError(path, f"{len(t)} gyro sample(s): expected a log of at least 2")
    ok = np.isfinite(t) & np.all(np.isfinite(rate), axis=1)
    if not np.all(ok):
        raise FlightLogError(path, f"{int(np.sum(~ok))} gyro samples with non-finite time or rate")
    wild = np.any(np.abs(rate) > MAX_GYRO_RAD_S, axis=1)
    if np.any(wild):
        raise FlightLogError(path, f"{int(np.sum(wild))} gyro samples over {MAX_GYRO_RAD_S:g} rad/s (a MEMS "
                                   "gyro's full scale is at most ±4000 °/s, 70 rad/s): rates in °/s read as "
                                   "rad/s (a .gcsv's gscale must turn its numbers to rad/s) or a corrupt log")
    keep = np.ones(len(t), dtype=bool)
    running = np.maximum.accumulate(t)
    keep[1:] = t[1:] > running[:-1]
    dropped = int(np.sum(~keep)) + dropped_before
    if dropped > MAX_DROPPED_FRACTION * (len(t) + dropped_before):
        if np.all(keep):
            raise FlightLogError(path, f"{dropped_before} of {len(t) + dropped_before} gyro samples out of "
                                       "order with both neighbours: expected strictly increasing times")
        i = int(np.flatnonzero(~keep)[0])
        raise FlightLogError(path, f"gyro sample {i} at {_secs(t[i])} s is not after the one before "
                                   f"({_secs(t[i - 1])} s): expected strictly increasing times "
                                   f"({dropped} of {len(t) + dropped_before} samples out of order)")
    t, rate = t[keep], rate[keep]
    dt = np.diff(t)
    med = float(np.median(dt))
    hz = 1.0 / med if med > 0 else 0.0
    if not MIN_RATE_HZ <= hz <= MAX_RATE_HZ:
        raise FlightLogError(path, f"gyro sample rate {hz:.3g} Hz (median interval {med:.3g} s): expected "
                                   f"{MIN_RATE_HZ:g}–{MAX_RATE_HZ:g} Hz")
    return FlightLog(str(path), fmt, np.ascontiguousarray(t), np.ascontiguousarray(rate), hz, frame,
                     orientation, index, n_logs, dropped, model)


# ----------------------------------------------------------------------------------------- writing
def write_gcsv(path: str | os.PathLike, t: np.ndarray, rate_rad_s: np.ndarray, *, orientation: str = "XYZ",
               gscale: float = 1e-6, tscale: float = 1e-6, vendor: str = "thermod", note: str = "",
               extra: dict | None = None) -> Path:
    """Write a Gyroflow ``.gcsv`` (version 1.3): integer times in units of `tscale` s and
    integer rates in units of `gscale` rad/s, with the axes as given and the IMU-to-camera
    `orientation` string for Gyroflow (three of X/Y/Z, lower case negates). For rates already in
    the camera frame of docs/design.md §2, `GCSV_ORIENTATION_OPENCV_CAMERA` is the string that
    tells Gyroflow so. `extra` adds header rows (e.g. frame_readout_time in ms)."""
    path = Path(path)
    t, rate = _check_series(path, t, rate_rad_s)
    _check_orientation(path, orientation)
    if not (gscale > 0 and tscale > 0):
        raise FlightLogError(path, "gscale and tscale must be > 0")
    ticks = np.round(t / tscale).astype(np.int64)
    if np.any(np.diff(ticks) <= 0):
        raise FlightLogError(path, f"times closer than tscale {tscale:g} s: choose a finer tscale")
    lsb = np.round(rate / gscale)
    if np.any(np.abs(lsb) > 2**53):
        raise FlightLogError(path, "rates too large for gscale: choose a coarser gscale")
    header = [("version", "1.3"), ("id", "thermod"), ("orientation", orientation), ("vendor", vendor),
              ("tscale", repr(float(tscale))), ("gscale", repr(float(gscale)))]
    if note:
        header.append(("note", note.replace(",", ";").replace("\n", " ")))
    header += [(str(k), str(v)) for k, v in (extra or {}).items()]
    lines = ["GYROFLOW IMU LOG"] + [f"{k},{v}" for k, v in header] + ["t,gx,gy,gz"]
    body = np.column_stack([ticks, lsb.astype(np.int64)])
    _atomic_text(path, "\n".join(lines) + "\n", body)
    return path


# Gyroflow's axes from the orientation strings telemetry-parser gives ArduPilot ("zyx") and
# Betaflight ("ZYx"): G = (−z, −y, −x) of FRD; for OpenCV camera rates (x right = FRD y, y down =
# FRD z, z forward = FRD x, forward camera) that is G = (−y, −x, −z) of the camera's axes.
GCSV_ORIENTATION_OPENCV_CAMERA = "yxz"


def write_betaflight_csv(path: str | os.PathLike, t: np.ndarray, rate_frd_rad_s: np.ndarray, *,
                         integer_deg_s: bool = True, firmware: str = "Betaflight 4.4.0 (thermod)"
                         ) -> Path:
    """Write a Betaflight blackbox CSV as Blackbox Explorer exports it (quoted header row,
    ``loopIteration``, ``time`` in µs, ``gyroADC[0..2]`` roll/pitch/yaw in °/s about Betaflight's
    x forward, y left, z up). Rates are given in FRD rad/s (module docstring); `integer_deg_s`
    quantises to 1 °/s as Betaflight 4's log does."""
    path = Path(path)
    t, rate = _check_series(path, t, rate_frd_rad_s)
    us = np.round(t * 1e6).astype(np.int64)
    if np.any(np.diff(us) <= 0) or us[0] < 0:
        raise FlightLogError(path, "times must be ≥ 0 and increase by ≥ 1 µs (Betaflight logs µs since boot)")
    deg = (rate @ FRD_FROM_BETAFLIGHT.T) / DEG
    lines = ['"Product","Blackbox flight data recorder by Nicholas Sherlock"',
             f'"Firmware revision","{firmware}"',
             '"loopIteration","time","gyroADC[0]","gyroADC[1]","gyroADC[2]"']
    cols = np.column_stack([np.arange(len(us)), us])
    if integer_deg_s:
        body = np.column_stack([cols, np.round(deg).astype(np.int64)])
    else:
        body = [f"{a},{b},{x:.4f},{y:.4f},{z:.4f}" for (a, b), (x, y, z) in zip(cols, deg, strict=True)]
    _atomic_text(path, "\n".join(lines) + "\n", body)
    return path


def write_ardupilot_bin(path: str | os.PathLike, t: np.ndarray, rate_frd_rad_s: np.ndarray, *,
                       n_imus: int = 1, stagger_s: float = 5e-6) -> Path:
    """Write an ArduPilot DataFlash ``.bin`` holding FMT records and one ``IMU`` record
    (TimeUS µs since boot, instance I, GyrX/Y/Z rad/s FRD, AccX/Y/Z m/s² = 0) per sample and IMU;
    with `n_imus` > 1 each sample is logged once per instance in turn, as ArduPilot logs its IMUs,
    instance i stamped `stagger_s`·i later (instance i's rates are the same plus 0.001·i rad/s, so
    the instances can be told apart)."""
    import struct

    path = Path(path)
    t, rate = _check_series(path, t, rate_frd_rad_s)
    us = np.round(t * 1e6).astype(np.int64)
    if np.any(np.diff(us) <= 0) or us[0] < 0:
        raise FlightLogError(path, "times must be ≥ 0 and increase by ≥ 1 µs (ArduPilot logs µs since boot)")
    if not 1 <= n_imus <= 3:
        raise FlightLogError(path, f"n_imus {n_imus}: expected 1–3")

    def fmt(msg_type, length, name, form, cols):
        return struct.pack("<3BBB4s16s64s", 0xA3, 0x95, 0x80, msg_type, length, name.encode(), form.encode(),
                           cols.encode())

    imu = struct.Struct("<3BQB6f")
    out = [fmt(0x80, 89, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"),
           fmt(0x81, imu.size, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")]
    step = int(round(stagger_s * 1e6))
    if n_imus > 1 and not 0 <= step * (n_imus - 1) < np.min(np.diff(us)):
        raise FlightLogError(path, f"stagger {stagger_s} s: the instances must fit between samples")
    for k in range(len(us)):
        for i in range(n_imus):
            w = rate[k] + 0.001 * i
            out.append(imu.pack(0xA3, 0x95, 0x81, int(us[k]) + i * step, i, *w.tolist(), 0.0, 0.0, 0.0))
    _atomic_write(path, lambda f: f.write(b"".join(out)), text=False)
    return path


def _check_series(path: Path, t, rate) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=np.float64)
    rate = np.asarray(rate, dtype=np.float64)
    if t.ndim != 1 or len(t) < 2 or rate.shape != (len(t), 3):
        raise FlightLogError(path, f"expected times [N ≥ 2] and rates [N, 3], got {t.shape} and {rate.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(rate))):
        raise FlightLogError(path, "times and rates must be finite")
    if np.any(np.diff(t) <= 0):
        raise FlightLogError(path, "times must increase strictly")
    return t, rate


def _atomic_text(path: Path, header: str, body) -> None:
    def write(f) -> None:
        f.write(header)
        if isinstance(body, np.ndarray):
            np.savetxt(f, body, fmt="%d", delimiter=",")
        else:
            f.write("\n".join(body) + "\n")

    _atomic_write(path, write, text=True)


def _atomic_write(path: Path, write, *, text: bool) -> None:
    """`write(f)` into ``<path>.part`` (ASCII text or bytes), renamed over `path` (the output rule of
    `thermod.paths.output_problem` first); a failure removes the part and names `path`."""
    if (problem := output_problem(path)) is not None:
        raise FlightLogError(path, problem)
    part = path.with_name(path.name + ".part")
    try:
        with open(part, "w", encoding="ascii", newline="\n") if text else open(part, "wb") as f:
            write(f)
        os.replace(part, path)
    except OSError as e:
        try:
            part.unlink(missing_ok=True)
        except OSError:
            pass
        raise FlightLogError(path, f"cannot write it ({e.strerror or e})") from None
