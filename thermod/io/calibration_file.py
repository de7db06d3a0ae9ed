"""The ``[calibration]`` table of a TOML file (a daemon configuration, or the ``model.toml`` that
`thermod discrepancy` writes) → a validated `Calibration`."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from thermod.errors import ConfigError
from thermod.io.toml_tables import Key, Problems, Section, read_toml
from thermod.physics.calibration import GYRO_EFFECT_KEYS, RANGES, Calibration, CalibrationError


def _ranged(key: str, kind: type, doc: str = "") -> Key:
    lo, hi, lo_open, _ = RANGES[key]
    return Key(kind, lo=lo, hi=None if hi == float("inf") else hi, lo_open=lo_open, doc=doc)


# The keys whose range does not depend on other keys (their ranges: `physics.calibration.RANGES`);
# defaults are the base calibration's. cx, cy (within the image, with margin) and readout_s (at most
# one frame period) are checked against the width, height and frame rate read first.
SCHEMA: dict[str, Key] = {
    "width": _ranged("width", int, doc="image width (px)"),
    "height": _ranged("height", int, doc="image height (px)"),
    "fx": _ranged("fx", float, doc="focal length (px)"),
    "fy": _ranged("fy", float, doc="focal length (px)"),
    "tau_s": _ranged("tau_s", float, doc="thermal time constant τ (s)"),
    "frame_rate_hz": _ranged("frame_rate_hz", float),
    "wavelength_um": _ranged("wavelength_um", float, doc="PSF wavelength"),
    "f_number": _ranged("f_number", float),
    "psf_beta": _ranged("psf_beta", float),
    "pixel_pitch_um": _ranged("pixel_pitch_um", float),
    "rate_hz": _ranged("rate_hz", float, doc="gyro sample rate"),
    "time_offset_s": _ranged("time_offset_s", float, doc="gyro time - camera time"),
    "bias_rad_s": Key(tuple, length=(3,), doc="gyro bias (rad/s)"),
    "scale": Key(tuple, length=(1, 3), positive=True, doc="gyro scale: one for all axes, or per axis"),
    # ranges checked by Calibration itself (its CalibrationError names the key)
    **{k: Key(float) for k in GYRO_EFFECT_KEYS},
}


def calibration_from_table(path: str | Problems, table: Any, base: Calibration | None = None) -> Calibration:
    """Validate a [calibration] table; keys it omits keep `base`'s values (default: the paper camera).
    With a shared `Problems`, problems are recorded there (and `base` returned); otherwise raised."""
    s = Section(path, "calibration", table)
    d = base or Calibration()
    schema = {k: dataclasses.replace(key, default=getattr(d, k)) for k, key in SCHEMA.items()}
    kw: dict[str, Any] = s.read(schema)
    w, h = kw["width"], kw["height"]
    cx0, cy0 = (d.cx, d.cy) if base is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
    kw["cx"] = s.pop("cx", cx0, float, lo=-w, hi=2.0 * w)
    kw["cy"] = s.pop("cy", cy0, float, lo=-h, hi=2.0 * h)
    kw["readout_s"] = s.pop("readout_s", d.readout_s, float, lo=0.0, hi=1.0 / kw["frame_rate_hz"])
    if len(kw["scale"]) == 1:
        kw["scale"] = kw["scale"] * 3
    kw["R_cam_gyro"] = _rotation(s, d.R_cam_gyro)
    s.done()
    if not s.ok:
        return d
    try:
        return Calibration(**kw)
    except CalibrationError as e:  # the checks the keys share (e.g. the field of view): name the file
        s.problem(e.field, e.problem)
        if s.owns:
            s.problems.raise_if_any()
        return d


def _rotation(s: Section, default: tuple) -> tuple:
    """``R_cam_gyro``: a 3×3 rotation matrix (orthonormal, det +1)."""
    if not s.has("R_cam_gyro"):
        return default
    v = s.take("R_cam_gyro")
    ok = isinstance(v, list) and len(v) == 3 and all(
        isinstance(row, list) and len(row) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in row) for row in v)
    R = np.asarray(v, dtype=np.float64) if ok else None
    if not (ok and bool(np.all(np.isfinite(R)))):
        s.fail("R_cam_gyro", "a 3×3 array of numbers", v)
        return default
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        s.fail("R_cam_gyro", "a rotation matrix (orthonormal, det +1)", v)
        return default
    return tuple(tuple(float(x) for x in row) for row in R)


def load_calibration(path: str | os.PathLike, base: Calibration | None = None) -> Calibration:
    """The [calibration] table of a TOML file (a full configuration, or the `model.toml` written by
    `thermod discrepancy`), validated as the daemon validates it; keys it omits keep `base`'s values (e.g. the
    calibration stored in the recording being processed). Other tables are ignored."""
    p = Path(path)
    raw = read_toml(p)
    if "calibration" not in raw:
        raise ConfigError(f"{p}: no [calibration] table")
    return calibration_from_table(str(p), raw["calibration"], base)
