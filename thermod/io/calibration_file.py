"""The ``[calibration]`` table of a TOML file (a daemon configuration, or the ``model.toml`` that
`thermod discrepancy` writes) → a validated `Calibration`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from thermod.errors import ConfigError
from thermod.io.toml_tables import Section, read_toml
from thermod.physics.calibration import GYRO_EFFECT_KEYS, Calibration, CalibrationError


def calibration_from_table(path: str, table: Any, base: Calibration | None = None) -> Calibration:
    """Validate a [calibration] table; keys it omits keep `base`'s values (default: the paper camera)."""
    s = Section(path, "calibration", table)
    d = base or Calibration()
    kw: dict[str, Any] = {}
    kw["width"] = s.pop("width", d.width, int, lo=8, hi=16384)
    kw["height"] = s.pop("height", d.height, int, lo=8, hi=16384)
    for k in ("fx", "fy"):
        kw[k] = s.pop(k, getattr(d, k), float, lo=0.0, lo_open=True)
    cx0, cy0 = (d.cx, d.cy) if base is not None else ((kw["width"] - 1) / 2.0, (kw["height"] - 1) / 2.0)
    kw["cx"] = s.pop("cx", cx0, float, lo=-kw["width"], hi=2.0 * kw["width"])
    kw["cy"] = s.pop("cy", cy0, float, lo=-kw["height"], hi=2.0 * kw["height"])
    kw["tau_s"] = s.pop("tau_s", d.tau_s, float, lo=0.0, lo_open=True, hi=1.0)
    kw["frame_rate_hz"] = s.pop("frame_rate_hz", d.frame_rate_hz, float, lo=0.0, lo_open=True, hi=10000.0)
    kw["wavelength_um"] = s.pop("wavelength_um", d.wavelength_um, float, lo=0.1, hi=100.0)
    kw["f_number"] = s.pop("f_number", d.f_number, float, lo=0.1, hi=100.0)
    kw["psf_beta"] = s.pop("psf_beta", d.psf_beta, float, lo=0.0, lo_open=True, hi=1.0)
    kw["pixel_pitch_um"] = s.pop("pixel_pitch_um", d.pixel_pitch_um, float, lo=0.0, lo_open=True, hi=1000.0)
    kw["readout_s"] = s.pop("readout_s", d.readout_s, float, lo=0.0, hi=1.0 / kw["frame_rate_hz"])
    kw["rate_hz"] = s.pop("rate_hz", d.rate_hz, float, lo=0.0, lo_open=True, hi=100000.0)
    kw["time_offset_s"] = s.pop("time_offset_s", d.time_offset_s, float, lo=-1.0, hi=1.0)
    kw["bias_rad_s"] = s.pop_floats("bias_rad_s", d.bias_rad_s, (3,))
    for k in GYRO_EFFECT_KEYS:      # ranges checked by Calibration (CalibrationError below names the key)
        kw[k] = s.pop(k, getattr(d, k), float)
    sc = s.pop_floats("scale", d.scale, (1, 3), positive=True)
    kw["scale"] = sc * 3 if len(sc) == 1 else sc
    if s.has("R_cam_gyro"):
        v = s.t.pop("R_cam_gyro")
        ok = isinstance(v, list) and len(v) == 3 and all(
            isinstance(row, list) and len(row) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in row) for row in v)
        R = np.asarray(v, dtype=np.float64) if ok else None
        ok = ok and bool(np.all(np.isfinite(R)))
        if not ok:
            raise s.fail("R_cam_gyro", "a 3×3 array of numbers", v)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise s.fail("R_cam_gyro", "a rotation matrix (orthonormal, det +1)", v)
        kw["R_cam_gyro"] = tuple(tuple(float(x) for x in row) for row in R)
    else:
        kw["R_cam_gyro"] = d.R_cam_gyro
    s.done()
    try:
        return Calibration(**kw)
    except CalibrationError as e:  # the checks the keys share (e.g. the field of view): name the file
        raise ConfigError(f"{path}: calibration.{e.field}: {e.problem}") from None


def load_calibration(path: str | os.PathLike, base: Calibration | None = None) -> Calibration:
    """The [calibration] table of a TOML file (a full configuration, or the `model.toml` written by
    `thermod discrepancy`), validated as the daemon validates it; keys it omits keep `base`'s values (e.g. the
    calibration stored in the recording being processed). Other tables are ignored."""
    p = Path(path)
    raw = read_toml(p)
    if "calibration" not in raw:
        raise ConfigError(f"{p}: no [calibration] table")
    return calibration_from_table(str(p), raw["calibration"], base)
