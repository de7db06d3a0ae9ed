"""Recording format v1 (DESIGN.md §3): one HDF5 file = one recording.

Every malformed input raises `RecordingError(path, field, problem)`; the message names the
file and the dataset/attribute and says what was expected.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from thermod.errors import RecordingError
from thermod.physics.calibration import CAMERA_KEYS, Calibration

FORMAT = "thermod-recording"
VERSION = 1
REQUIRED_CAMERA_ATTRS = CAMERA_KEYS
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


def _read_attrs(path, f, group, required):
    if group not in f:
        raise RecordingError(path, group, "group missing")
    attrs = dict(f[group].attrs)
    for k in required:
        if k not in attrs:
            raise RecordingError(path, f"{group}.attrs['{k}']", "attribute missing")
    return attrs


def _read_dataset(path, f, name):
    if name not in f or not isinstance(f[name], h5py.Dataset):
        raise RecordingError(path, name, "dataset missing")
    return f[name][()]


def open_file(path: str | os.PathLike) -> h5py.File:
    """Open a recording read-only after checking that it is format v1 (caller closes it)."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise RecordingError(path, "file", "does not exist") from None
    except OSError as e:
        raise RecordingError(path, "file", f"not a readable HDF5 file ({e})") from None
    fmt = f.attrs.get("format")
    fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
    ver = f.attrs.get("version")
    ver = ver.item() if isinstance(ver, np.generic) else ver
    if fmt != FORMAT:
        f.close()
        raise RecordingError(path, "/.attrs['format']", f"expected {FORMAT!r}, got {fmt!r}")
    if not isinstance(ver, (int, float)) or int(ver) != VERSION:
        f.close()
        raise RecordingError(path, "/.attrs['version']", f"expected {VERSION}, got {ver!r}")
    return f


def _read_timeline(path, f):
    cam = _read_attrs(path, f, "camera", REQUIRED_CAMERA_ATTRS)
    gyr = _read_attrs(path, f, "gyro", REQUIRED_GYRO_ATTRS)
    try:
        calib = Calibration.from_attrs(cam, gyr)
    except (ValueError, TypeError) as e:
        raise RecordingError(path, "camera/gyro attrs", str(e)) from None
    t = np.asarray(_read_dataset(path, f, "camera/t"), dtype=np.float64)
    gyro_t = np.asarray(_read_dataset(path, f, "gyro/t"), dtype=np.float64)
    gyro_rate = _read_dataset(path, f, "gyro/rate")
    if gyro_rate.dtype != np.float32 and np.issubdtype(gyro_rate.dtype, np.floating):
        gyro_rate = gyro_rate.astype(np.float32)
    return calib, t, gyro_t, gyro_rate


def read_timeline(path: str | os.PathLike):
    """(frame times, gyro times, gyro rates, calibration) of a recording, validated as by `read`,
    without loading the frames (for replay, which reads them one at a time)."""
    path = Path(path)
    with open_file(path) as f:
        calib, t, gyro_t, gyro_rate = _read_timeline(path, f)
        if "camera/frames" not in f or not isinstance(f["camera/frames"], h5py.Dataset):
            raise RecordingError(path, "camera/frames", "dataset missing")
        frames = f["camera/frames"]
        stand_in = np.broadcast_to(np.zeros((), frames.dtype), frames.shape)  # shape and dtype only
    Recording(stand_in, t, gyro_t, gyro_rate, calib).validate(path)
    return t, gyro_t, gyro_rate, calib


def read(path: str | os.PathLike) -> Recording:
    """Read and validate a format-v1 recording."""
    path = Path(path)
    with open_file(path) as f:
        calib, t, gyro_t, gyro_rate = _read_timeline(path, f)
        frames = _read_dataset(path, f, "camera/frames")
        deb = deb_t = None
        if "deblurred" in f:
            deb = _read_dataset(path, f, "deblurred/frames")
            deb_t = np.asarray(_read_dataset(path, f, "deblurred/t"), dtype=np.float64)
        extras, extra_attrs = {}, {}
        known = {"camera/frames", "camera/t", "gyro/t", "gyro/rate", "deblurred/frames", "deblurred/t"}

        def visit(name, obj):
            if name in known or name in ("camera", "gyro", "deblurred"):
                return  # the v1 core, read above (optional datasets beside it are kept as extras)
            if isinstance(obj, h5py.Dataset):
                extras[name] = obj[()]
            elif len(obj.attrs):
                extra_attrs[name] = dict(obj.attrs)

        f.visititems(visit)
    rec = Recording(frames, t, gyro_t, gyro_rate, calib, deb, deb_t, extras, extra_attrs)
    rec.validate(path)
    return rec


def write(path: str | os.PathLike, rec: Recording) -> None:
    """Write `rec` in format v1 (atomically: a temp file renamed into place)."""
    path = Path(path)
    rec.validate(path)
    tmp = path.with_name(path.name + ".part")
    n, h, w = rec.frames.shape
    with h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        cam = f.create_group("camera")
        cam.create_dataset("frames", data=rec.frames, chunks=(1, h, w) if n else None)
        cam.create_dataset("t", data=np.asarray(rec.t, np.float64))
        for k, v in rec.calibration.camera_attrs().items():
            cam.attrs[k] = v
        gyr = f.create_group("gyro")
        gyr.create_dataset("t", data=np.asarray(rec.gyro_t, np.float64))
        gyr.create_dataset("rate", data=np.asarray(rec.gyro_rate, np.float32))
        for k, v in rec.calibration.gyro_attrs().items():
            gyr.attrs[k] = v
        if rec.deblurred is not None:
            d = f.create_group("deblurred")
            d.create_dataset("frames", data=rec.deblurred.astype(np.float32, copy=False),
                             chunks=(1, h, w) if n else None)
            d.create_dataset("t", data=np.asarray(rec.t if rec.deblurred_t is None else rec.deblurred_t))
        for name, arr in rec.extras.items():
            f.create_dataset(name, data=arr)
        for name, attrs in rec.extra_attrs.items():
            g = f.require_group(name)
            for k, v in attrs.items():
                g.attrs[k] = v
    os.replace(tmp, path)
