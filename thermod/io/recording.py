"""Recording format v1 (docs/design.md §3): one HDF5 file = one recording.

Every malformed input raises `RecordingError(path, field, problem)`; the message names the
file and the dataset/attribute (and the frame, where one is at fault) and says what was expected.

- `Reader(path)`: checks the attributes (through `Calibration`, the one validation of a
  calibration), then the declared shapes, dtypes and stored bytes of every dataset against them,
  before anything is allocated; holds the timeline and reads frames one at a time.
- `read(path)`: the whole recording in memory (refused beyond `memory_budget()`).
- `Writer(path)`: the one writer, incremental, into ``<path>.part`` renamed on `commit`;
  `write(path, rec)` is a whole `Recording` through it.
"""

from __future__ import annotations

import os
import posixpath
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from thermod.errors import RecordingError
from thermod.paths import input_problem, output_problem
from thermod.physics.calibration import CAMERA_KEYS, Calibration, CalibrationError

FORMAT = "thermod-recording"
VERSION = 1
REQUIRED_CAMERA_ATTRS = CAMERA_KEYS
# optional: a static overlay burnt into the frames (uint8 or bool [H, W], nonzero = overlay), found by
# the video import; deblurring keeps it out of the solve
OVERLAY_DATASET = "motion/overlay"
REQUIRED_GYRO_ATTRS = ("rate_hz", "R_cam_gyro", "bias_rad_s", "time_offset_s")


@dataclass
class Recording:
    """Frames (uint16 [N,H,W]) and gyro samples (raw, gyro frame) with their calibration.

    `extras` holds any other datasets by HDF5 path (e.g. "truth/frames"), `extra_attrs` the
    attributes of other groups by path (e.g. {"truth": {...}}); readers ignore what they do not know.
    """

    frames: np.ndarray
    t: np.ndarray
    gyro_t: np.ndarray
    gyro_rate: np.ndarray
    calibration: Calibration
    deblurred: np.ndarray | None = None
    deblurred_t: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    extra_attrs: dict[str, dict] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def validate(self, path="<memory>") -> None:
        _check_array(path, "camera/frames", self.frames, np.uint16, 3)
        n, h, w = self.frames.shape
        if (h, w) != (self.calibration.height, self.calibration.width):
            raise RecordingError(path, "camera/frames", f"frame shape {(h, w)} does not match attrs "
                                 f"height×width {(self.calibration.height, self.calibration.width)}")
        _check_times(path, "camera/t", self.t, n)
        _check_times(path, "gyro/t", self.gyro_t, None)
        _check_array(path, "gyro/rate", self.gyro_rate, None, 2)
        if self.gyro_rate.shape != (len(self.gyro_t), 3):
            raise RecordingError(path, "gyro/rate", f"expected shape ({len(self.gyro_t)}, 3) to match "
                                 f"gyro/t, got {self.gyro_rate.shape}")
        if not np.all(np.isfinite(self.gyro_rate)):
            raise RecordingError(path, "gyro/rate", "contains NaN or infinite values")
        if self.deblurred is not None:
            _check_array(path, "deblurred/frames", self.deblurred, np.float32, 3)
            if self.deblurred.shape != self.frames.shape:
                raise RecordingError(path, "deblurred/frames", f"expected shape {self.frames.shape}, "
                                     f"got {self.deblurred.shape}")


def _check_array(path, name, a, dtype, ndim):
    if not isinstance(a, np.ndarray):
        raise RecordingError(path, name, f"expected an array, got {type(a).__name__}")
    if dtype is not None and a.dtype != dtype:
        raise RecordingError(path, name, f"expected dtype {np.dtype(dtype).name}, got {a.dtype}")
    if a.ndim != ndim:
        raise RecordingError(path, name, f"expected {ndim} dimensions, got shape {a.shape}")


def _check_times(path, name, t, n):
    if not isinstance(t, np.ndarray) or t.ndim != 1:
        raise RecordingError(path, name, f"expected a 1-D float64 array, got {getattr(t, 'shape', t)}")
    if n is not None and len(t) != n:
        raise RecordingError(path, name, f"expected {n} times (one per frame), got {len(t)}")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise RecordingError(path, name, f"NaN or infinite timestamp at index {bad}")
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        bad = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise RecordingError(path, name, f"time must be strictly increasing; index {bad} "
                             f"({t[bad]!r}) does not follow {t[bad - 1]!r}")


# ------------------------------------------------------------------------------------- reading
# h5py reports damage inside a file (flipped bytes, a truncated chunk, a wrong type) as any of these.
_H5_ERRORS = (OSError, RuntimeError, ValueError, KeyError, TypeError, IndexError, OverflowError,
              AttributeError, UnicodeError)


class _Guard:
    """`with _Guard(path, field, frame)`: an h5py failure becomes a RecordingError naming them."""

    def __init__(self, path, field: str, frame: int | None = None):
        self.path, self.field, self.frame = path, field, frame

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if kind is not None and issubclass(kind, _H5_ERRORS) and not issubclass(kind, RecordingError):
            where = "" if self.frame is None else f"frame {self.frame}: "
            raise RecordingError(self.path, self.field, f"{where}cannot be read: damaged or not the "
                                 f"declared type ({kind.__name__}: {e})") from None
        return False


def memory_budget() -> int:
    """Bytes a whole-file read may allocate: half the machine's memory."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 4 << 30


def _gib(n: int) -> str:
    return f"{n / 2**30:.3g} GiB"


def _dataset(path, f, name, kinds: str, ndim: int | None, shape_ok=None, expected: str = "") -> h5py.Dataset:
    """The dataset `name`, its dtype kind in `kinds` and its declared shape checked before any read."""
    with _Guard(path, name):
        obj = f.get(name)
        if not isinstance(obj, h5py.Dataset):
            raise RecordingError(path, name, "dataset missing" if obj is None else "expected a dataset, "
                                 "found a group")
        dt, shape = obj.dtype, obj.shape
        if dt.kind not in kinds or dt.shape != () or shape is None:
            raise RecordingError(path, name, f"expected {expected or _kinds(kinds)}, got dtype {dt}")
        if ndim is not None and len(shape) != ndim or (shape_ok is not None and not shape_ok(shape)):
            want = expected or f"{ndim} dimensions"
            raise RecordingError(path, name, f"expected {want}, got shape {shape}")
        declared = int(np.prod(shape, dtype=np.float64)) * dt.itemsize
        if obj.compression is None and obj.scaleoffset is None and dt.kind != "O" and declared:
            stored = obj.id.get_storage_size()
            if stored < declared:  # an unfiltered dataset stores every byte it declares
                raise RecordingError(path, name, f"declares shape {shape} ({_gib(declared)}) but the file "
                                     f"holds {stored} bytes of it: truncated or never written")
    return obj


def _kinds(kinds: str) -> str:
    names = {"u": "unsigned integers", "i": "integers", "f": "floats"}
    return " or ".join(names.get(k, f"dtype kind {k!r}") for k in kinds)


def _attrs(path, f, group: str, required) -> dict:
    with _Guard(path, f"{group}.attrs"):
        g = f.get(group)
        if not isinstance(g, h5py.Group):
            raise RecordingError(path, group, "group missing")
        attrs = {}
        for k in g.attrs:
            with _Guard(path, f"{group}.attrs['{k}']"):
                attrs[k] = g.attrs[k]
    for k in required:
        if k not in attrs:
            raise RecordingError(path, f"{group}.attrs['{k}']", "attribute missing")
    return attrs


def open_file(path: str | os.PathLike) -> h5py.File:
    """Open a recording read-only after checking that it is format v1 (caller closes it)."""
    path = Path(path)
    if (problem := input_problem(path)) is not None:
        raise RecordingError(path, "file", problem)
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise RecordingError(path, "file", "does not exist") from None
    except IsADirectoryError:
        raise RecordingError(path, "file", "is a directory, expected an HDF5 file") from None
    except _H5_ERRORS as e:
        raise RecordingError(path, "file", f"not a readable HDF5 file ({e})") from None
    try:
        with _Guard(path, "/.attrs"):
            fmt = f.attrs.get("format")
            ver = f.attrs.get("version")
        fmt = fmt.decode(errors="replace") if isinstance(fmt, bytes) else fmt
        ver = ver.item() if isinstance(ver, np.generic) else ver
        if not isinstance(fmt, str) or fmt != FORMAT:
            raise RecordingError(path, "/.attrs['format']", f"expected {FORMAT!r}, got {_short(fmt)}")
        if isinstance(ver, bool) or not isinstance(ver, (int, float)) or ver != VERSION:
            raise RecordingError(path, "/.attrs['version']", f"expected {VERSION}, got {_short(ver)}")
    except BaseException:
        f.close()
        raise
    return f


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


def _calibration(path, camera: dict, gyro: dict) -> Calibration:
    try:
        return Calibration.from_attrs(camera, gyro)
    except CalibrationError as e:
        group = "camera" if e.field in CAMERA_KEYS else "gyro"
        raise RecordingError(path, f"{group}.attrs['{e.field}']", e.problem) from None


def _times(path, name, ds: h5py.Dataset) -> np.ndarray:
    with _Guard(path, name):
        t = np.asarray(ds[()], dtype=np.float64)
    _check_times(path, name, t, None)
    return t


def _readable(obj) -> None:
    """Read every attribute and dataset type of `obj` and what it holds (h5py decodes them lazily: a
    damaged string type, e.g. an unknown character set, raises only when read)."""
    def touch(_name, o) -> None:
        for k in o.attrs:
            o.attrs[k]
        if isinstance(o, h5py.Dataset):
            o.dtype  # noqa: B018 - decoding the type is the check

    touch("", obj)
    if isinstance(obj, h5py.Group):
        obj.visititems(touch)


class Reader:
    """An open format-v1 recording: calibration, frame times and gyro samples in memory, frames read
    one at a time (`frame(i)`, iteration), so memory stays bounded however long the recording.

    Everything a reader needs is checked on opening, before anything is allocated from the file's
    declarations: the calibration attributes (via `Calibration`), the declared shapes and dtypes
    against them, and that the file holds the bytes it declares. A frame that cannot be read later
    raises RecordingError naming the file, the dataset and the frame. `max_timeline_bytes` lowers what
    the timeline may take below `memory_budget()`.
    """

    def __init__(self, path: str | os.PathLike, max_timeline_bytes: int | None = None):
        self.path = Path(path)
        self._budget = memory_budget() if max_timeline_bytes is None else min(memory_budget(),
                                                                             max_timeline_bytes)
        self._f = open_file(self.path)
        try:
            self._open()
        except BaseException:
            self._f.close()
            raise

    def _open(self) -> None:
        path, f = self.path, self._f
        cam = _attrs(path, f, "camera", REQUIRED_CAMERA_ATTRS)
        gyr = _attrs(path, f, "gyro", REQUIRED_GYRO_ATTRS)
        self.calibration = c = _calibration(path, cam, gyr)
        hw = (c.height, c.width)
        self._frames = _dataset(path, f, "camera/frames", "u", 3, lambda s: s[1:] == hw,
                                f"uint16 [N, height, width] = [N, {hw[0]}, {hw[1]}] (from the camera "
                                f"attributes)")
        if self._frames.dtype != np.uint16:
            raise RecordingError(path, "camera/frames", f"expected dtype uint16, got {self._frames.dtype}")
        n = self._frames.shape[0]
        ds_t = _dataset(path, f, "camera/t", "iuf", 1, lambda s: s == (n,),
                        f"float64 times, one per frame: shape ({n},)")
        ds_gt = _dataset(path, f, "gyro/t", "iuf", 1, None, "float64 times [M]")
        m = ds_gt.shape[0]
        ds_gr = _dataset(path, f, "gyro/rate", "f", 2, lambda s: s == (m, 3),
                         f"float32 rates of shape ({m}, 3) to match gyro/t")
        need = 8 * (n + m) + ds_gr.dtype.itemsize * 3 * m + 4 * 3 * m   # the timeline, its float32 copy
        if need > self._budget:
            raise RecordingError(path, "gyro/t", f"the timeline alone ({n} frame times, {m} gyro samples) "
                                 f"needs {_gib(need)}, more than the {_gib(self._budget)} allowed")
        self.t = _times(path, "camera/t", ds_t)
        self.gyro_t = _times(path, "gyro/t", ds_gt)
        with _Guard(path, "gyro/rate"):
            stored = np.asarray(ds_gr[()])
        ok = np.abs(stored) <= np.finfo(np.float32).max         # False for NaN
        if not np.all(ok):
            bad = int(np.flatnonzero(~np.all(ok, axis=1))[0])
            v = stored[bad][~ok[bad]][0]
            raise RecordingError(path, "gyro/rate", f"value {float(v)!r} at sample {bad}: expected finite "
                                 "rad/s within float32's range")
        self.gyro_rate = stored.astype(np.float32)

    # ------------------------------------------------------------------------------ frames
    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self.calibration.height, self.calibration.width

    def __len__(self) -> int:
        return self.n_frames

    def frame(self, i: int) -> np.ndarray:
        """Frame `i` (uint16 [H, W])."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} of {self.n_frames}")
        return self._read_row(self._frames, "camera/frames", i)

    def __iter__(self):
        """The frames in order, one in memory at a time."""
        for i in range(self.n_frames):
            yield self.frame(i)

    def _read_row(self, ds: h5py.Dataset, name: str, i: int) -> np.ndarray:
        out = np.empty(ds.shape[1:], ds.dtype)
        with _Guard(self.path, name, i):
            ds.read_direct(out, np.s_[i])
        return out

    # ------------------------------------------------------------------------------ the rest
    def names(self) -> list[str]:
        """Paths of the datasets beside the v1 core (e.g. "truth/frames")."""
        out = []

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and name not in _CORE:
                out.append(name)
        with _Guard(self.path, "/"):
            self._f.visititems(visit)
        return out

    def group_attrs(self) -> dict[str, dict]:
        """Attributes of the groups beside /camera and /gyro, by path."""
        out = {}

        def visit(name, obj):
            if name not in ("camera", "gyro", "deblurred") and isinstance(obj, h5py.Group) and len(obj.attrs):
                out[name] = {k: obj.attrs[k] for k in obj.attrs}
        with _Guard(self.path, "/"):
            self._f.visititems(visit)
        return out

    def overlay(self) -> np.ndarray | None:
        """The static overlay's mask (bool [H, W]) when the recording has one (`OVERLAY_DATASET`)."""
        with _Guard(self.path, OVERLAY_DATASET):
            if OVERLAY_DATASET not in self._f:
                return None
        hw = self.frame_shape
        ds = _dataset(self.path, self._f, OVERLAY_DATASET, "ub", 2, lambda s: s == hw,
                      f"uint8 [height, width] = [{hw[0]}, {hw[1]}], nonzero on the overlay")
        with _Guard(self.path, OVERLAY_DATASET):
            return np.asarray(ds[()]) != 0

    def dataset(self, name: str) -> h5py.Dataset:
        """An optional dataset by path, shape and storage checked (not read)."""
        return _dataset(self.path, self._f, name, "biufcSOUV", None)

    def copy_extras_into(self, dst: h5py.File) -> None:
        """Copy everything beside the v1 core and an earlier /deblurred result (e.g. /truth, /record,
        camera/frame_id) into another file, HDF5 to HDF5: attributes byte for byte, data never held
        in memory."""
        def copy(obj, parent_name: str, name: str):
            with _Guard(self.path, f"{parent_name}/{name}".lstrip("/")):
                _readable(obj)          # copied byte for byte, it must read back from the output
                self._f.copy(obj, dst.require_group(parent_name), name=name)

        with _Guard(self.path, "/"):
            top = list(self._f.items())
        for name, obj in top:
            if name in ("camera", "gyro") and isinstance(obj, h5py.Group):
                with _Guard(self.path, name):
                    inner = [(k, v) for k, v in obj.items() if f"{name}/{k}" not in _CORE]
                for k, v in inner:
                    copy(v, name, k)
            elif name != "deblurred":
                copy(obj, "/", name)

    def close(self) -> None:
        try:
            self._f.close()
        except _H5_ERRORS:  # pragma: no cover - closing a damaged file
            pass

    def __enter__(self) -> Reader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_CORE = {"camera/frames", "camera/t", "gyro/t", "gyro/rate", "deblurred/frames", "deblurred/t"}


def read_timeline(path: str | os.PathLike):
    """(frame times, gyro times, gyro rates, calibration) of a recording, validated as by `read`,
    without loading the frames (for replay, which reads them one at a time)."""
    with Reader(path) as r:
        return r.t, r.gyro_t, r.gyro_rate, r.calibration


def read(path: str | os.PathLike) -> Recording:
    """Read and validate a whole format-v1 recording into memory. Refuses one that needs more than
    `memory_budget()`; `Reader` iterates over the frames of any size instead."""
    with Reader(path) as r:
        path = r.path
        n, (h, w) = r.n_frames, r.frame_shape
        extras_names = r.names()
        has_deb = isinstance(r._f.get("deblurred/frames"), h5py.Dataset) or "deblurred" in r._f
        deb_ds = deb_t_ds = None
        if has_deb:
            deb_ds = _dataset(path, r._f, "deblurred/frames", "f", 3, lambda s: s == (n, h, w),
                              f"float32 frames of shape {(n, h, w)}, like camera/frames")
            deb_t_ds = _dataset(path, r._f, "deblurred/t", "iuf", 1, lambda s: s == (n,),
                                f"one time per frame, shape ({n},)")
        extra_ds = {name: r.dataset(name) for name in extras_names}
        need = n * h * w * (2 + (4 if has_deb else 0))
        need += sum(d.size * d.dtype.itemsize for d in extra_ds.values())
        if need > memory_budget():
            raise RecordingError(path, "camera/frames", f"reading the whole recording needs {_gib(need)}, "
                                 "more than half this machine's memory; iterate over its frames with "
                                 "thermod.io.recording.Reader instead")
        frames = np.empty((n, h, w), np.uint16)
        for i in range(n):
            frames[i] = r._read_row(r._frames, "camera/frames", i)
        deb = deb_t = None
        if has_deb:
            deb = np.empty((n, h, w), np.float32)
            for i in range(n):
                deb[i] = r._read_row(deb_ds, "deblurred/frames", i)
            deb_t = _times(path, "deblurred/t", deb_t_ds)
        extras = {}
        for name, ds in extra_ds.items():
            with _Guard(path, name):
                extras[name] = ds[()]
        extra_attrs = r.group_attrs()
        rec = Recording(frames, r.t, r.gyro_t, r.gyro_rate, r.calibration, deb, deb_t, extras, extra_attrs)
    rec.validate(path)
    return rec


# ------------------------------------------------------------------------------------- writing
class Writer:
    """Format v1 written incrementally into ``<path>.part`` and renamed into place by `commit`: the
    one writer of recordings (`write`, `thermod record`, `thermod deblur`).

    `append` grows a dataset one row at a time on disk (a frame is one chunk), so memory stays flat
    however long the recording; `put` writes a whole dataset; `commit` adds the format and the
    calibration attributes, checks the layout and renames. Until then an existing file at `path` is
    untouched; `abort` removes the ``.part`` file, or keeps it (with what was received) when asked.
    """

    def __init__(self, path: str | os.PathLike, suffix: str = ".part"):
        self.path = Path(path)
        self.part = self.path.with_name(self.path.name + suffix)
        if (problem := output_problem(self.path)) is not None:
            raise RecordingError(self.path, "file", problem)
        try:
            self.file = h5py.File(self.part, "w")
        except (OSError, ValueError) as e:
            raise RecordingError(self.path, "file", f"cannot create {self.part} ({e})") from None
        self.rows: dict[str, int] = {}       # appended datasets → rows written

    def reserve(self, name: str, n: int, row_shape: tuple, dtype) -> None:
        """Create dataset `name` for `n` rows to be `append`ed (no resize per row; what is not
        filled is trimmed by `commit`)."""
        # chunks of at most 64 kB: a frame is one chunk (read one at a time), times and gyro samples
        # are thousands to a chunk
        row_bytes = int(np.prod(row_shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        chunks = (max(1, min(4096, 65536 // max(row_bytes, 1))), *row_shape)
        self.file.create_dataset(name, (n, *row_shape), dtype, maxshape=(None, *row_shape), chunks=chunks)
        self.rows[name] = 0

    def append(self, name: str, row, dtype=None) -> None:
        """Add one row (a frame, a time …) to dataset `name`, created on first use from the row."""
        row = np.asarray(row, dtype=dtype)
        if name not in self.rows:
            self.reserve(name, 0, row.shape, row.dtype)
        ds, n = self.file[name], self.rows[name]
        if n >= ds.shape[0]:
            ds.resize(n + 1, axis=0)
        if row.ndim:
            ds.write_direct(np.ascontiguousarray(row, ds.dtype), dest_sel=np.s_[n])
        else:
            ds[n] = row
        self.rows[name] = n + 1

    def extend(self, name: str, rows, dtype=None) -> None:
        """Add rows (along the first axis) to dataset `name`, created on first use from them."""
        rows = np.asarray(rows, dtype=dtype)
        if not len(rows):
            return
        if name not in self.rows:
            self.reserve(name, 0, rows.shape[1:], rows.dtype)
        ds, n = self.file[name], self.rows[name]
        if n + len(rows) > ds.shape[0]:
            ds.resize(n + len(rows), axis=0)
        ds[n:n + len(rows)] = rows
        self.rows[name] = n + len(rows)

    def rewrite(self, name: str, data) -> None:
        """Replace the rows of a dataset made by `append`/`extend` (its length may change)."""
        data = np.asarray(data)
        if name not in self.rows:
            self.reserve(name, 0, data.shape[1:], data.dtype)
        ds = self.file[name]
        ds.resize(len(data), axis=0)
        if len(data):
            ds[...] = data
        self.rows[name] = len(data)

    def _trim(self) -> None:
        for name, n in self.rows.items():
            if self.file[name].shape[0] != n:
                self.file[name].resize(n, axis=0)

    def append_frame(self, image: np.ndarray, t: float) -> None:
        """A camera frame (uint16 [H, W]) and its time."""
        self.append("camera/frames", image, np.uint16)
        self.append("camera/t", t, np.float64)

    def put(self, name: str, data, *, chunk_rows: bool = False) -> None:
        """A whole dataset; `chunk_rows` stores each row as one chunk (frames: read one at a time)."""
        data = np.asarray(data)
        chunks = (1, *data.shape[1:]) if chunk_rows and data.ndim > 1 and len(data) else None
        self.file.create_dataset(name, data=data, chunks=chunks)

    def set_attrs(self, group: str, attrs: dict) -> None:
        """Attributes of a group (created if missing) or of a dataset already created."""
        g = self.file.get(group)
        if not isinstance(g, h5py.Dataset):
            g = self.file.require_group(group)
        for k, v in attrs.items():
            g.attrs[k] = v

    def flush(self) -> None:
        self.file.flush()

    def sort_frames(self) -> int:
        """Put frames that arrived out of time order in order, with every dataset appended in step
        with them (same number of rows); of frames with the same time the first is kept. Returns
        how many were dropped as repeats."""
        if "camera/t" not in self.file:
            return 0
        self._trim()
        t = self.file["camera/t"][()]
        order = np.argsort(t, kind="stable")
        keep = np.ones(len(order), bool)
        keep[1:] = np.diff(t[order]) > 0
        order, dropped = order[keep], int((~keep).sum())
        if not np.array_equal(order, np.arange(len(t))):
            self._reorder(order, len(t))
        return dropped

    def commit(self, calibration: Calibration) -> Path:
        """Add the format and calibration attributes, check the layout, rename into place."""
        self._trim()
        f = self.file
        if "camera/frames" not in f:
            f.create_dataset("camera/frames", (0, calibration.height, calibration.width), np.uint16)
            f.create_dataset("camera/t", (0,), np.float64)
        n, *hw = f["camera/frames"].shape
        if tuple(hw) != (calibration.height, calibration.width):
            raise RecordingError(self.path, "camera/frames", f"frame shape {tuple(hw)} does not match the "
                                 f"calibration's height×width {(calibration.height, calibration.width)}")
        _check_times(self.path, "camera/t", f["camera/t"][()], n)
        for name in ("gyro/t", "gyro/rate"):
            if name not in f:
                raise RecordingError(self.path, name, "dataset missing")
        gt, gr = f["gyro/t"], f["gyro/rate"]
        if gr.shape != (gt.shape[0], 3):
            raise RecordingError(self.path, "gyro/rate", f"expected shape ({gt.shape[0]}, 3) to match "
                                 f"gyro/t, got {gr.shape}")
        f.attrs["format"], f.attrs["version"] = FORMAT, VERSION
        self.set_attrs("camera", calibration.camera_attrs())
        self.set_attrs("gyro", calibration.gyro_attrs())
        f.close()
        os.replace(self.part, self.path)
        return self.path

    def _reorder(self, order: np.ndarray, n: int) -> None:
        """Rewrite the spool with the per-frame datasets in `order` (the others as they are)."""
        src = self.file
        tmp = self.path.with_name(self.path.name + ".sorting")
        per_frame = {name for name, rows in self.rows.items() if rows == n}
        with h5py.File(tmp, "w") as dst:
            def visit(name, obj):
                if isinstance(obj, h5py.Group):
                    g = dst.require_group(name)
                elif name in per_frame:
                    ds = dst.create_dataset(name, (len(order), *obj.shape[1:]), obj.dtype,
                                            maxshape=(None, *obj.shape[1:]), chunks=obj.chunks)
                    for j, i in enumerate(order):
                        ds[j] = obj[i]
                    g = ds
                else:
                    src.copy(obj, dst.require_group(posixpath.dirname(name) or "/"),
                             name=posixpath.basename(name))
                    return
                for k, v in obj.attrs.items():
                    g.attrs[k] = v
            src.visititems(visit)
            for k, v in src.attrs.items():
                dst.attrs[k] = v
        src.close()
        os.replace(tmp, self.part)
        self.file = h5py.File(self.part, "r+")
        self.rows.update(dict.fromkeys(per_frame, len(order)))

    def abort(self, keep: bool = False) -> None:
        """Close without completing; the ``.part`` file is removed unless `keep`."""
        try:
            if self.file.id.valid:
                self.file.close()
        except _H5_ERRORS:
            pass
        if not keep:
            self.part.unlink(missing_ok=True)

    def __enter__(self) -> Writer:
        return self

    def __exit__(self, kind, e, tb) -> None:
        if kind is not None or self.file.id.valid:   # not committed: nothing half-written is left
            self.abort()


def write(path: str | os.PathLike, rec: Recording) -> None:
    """Write `rec` in format v1 (atomically: a temp file renamed into place)."""
    rec.validate(path)
    with Writer(path) as w:
        w.put("camera/frames", rec.frames, chunk_rows=True)
        w.put("camera/t", np.asarray(rec.t, np.float64))
        w.put("gyro/t", np.asarray(rec.gyro_t, np.float64))
        w.put("gyro/rate", np.asarray(rec.gyro_rate, np.float32))
        if rec.deblurred is not None:
            w.put("deblurred/frames", rec.deblurred.astype(np.float32, copy=False), chunk_rows=True)
            deb_t = rec.t if rec.deblurred_t is None else rec.deblurred_t
            w.put("deblurred/t", np.asarray(deb_t, np.float64))
        for name, arr in rec.extras.items():
            w.put(name, arr)
        for name, attrs in rec.extra_attrs.items():
            w.set_attrs(name, attrs)
        w.commit(rec.calibration)
