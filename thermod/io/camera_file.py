"""A camera description (``CAMERA.toml``) → the camera half of a `Calibration`.

What a user of a thermal camera knows, in a ``[camera]`` table:

    [camera]
    width = 640                 # px
    height = 512
    hfov_deg = 32.0             # one of: hfov_deg, focal_length_mm (with pixel_pitch_um), fx (px)
    pixel_pitch_um = 12.0
    frame_rate_hz = 60.0
    tau_s = 0.010               # the detector's thermal time constant (a video-only import fits it
                                # from the pictures when it is left out)
    readout_s = 0.0             # rolling readout, first row to last (0 = unknown or global)
    f_number = 1.0              # optional, with wavelength_um: the Eq. 19 optical PSF

The focal length in pixels is ``fx = fy = (width / 2) / tan(hfov / 2)`` from a horizontal field of
view, or ``focal_length_mm / pixel_pitch_um · 1000``; the principal point is the image centre unless
``cx``/``cy`` are given. A file with a ``[calibration]`` table instead (a thermod configuration, or the
``model.toml`` of `thermod discrepancy`) is read as that table (`thermod.io.calibration_file`).

Presets for common cores ship in ``config/cameras/`` (`preset_path`); each says where its numbers
come from.
"""

from __future__ import annotations

import math
import os
from importlib import resources
from pathlib import Path

from thermod.errors import ConfigError
from thermod.io.calibration_file import calibration_from_table
from thermod.io.toml_tables import Section, read_toml
from thermod.physics.calibration import Calibration, CalibrationError

FOCAL_KEYS = ("hfov_deg", "focal_length_mm", "fx")


def preset_names() -> list[str]:
    """The camera presets shipped with thermod (file stems of config/cameras/*.toml)."""
    root = resources.files("thermod.configs").joinpath("cameras")
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def preset_path(name: str) -> Path:
    """The file of preset `name`; a ConfigError listing the presets when there is none."""
    names = preset_names()
    if name not in names:
        raise ConfigError(f"camera preset {name!r}: unknown; the presets are {', '.join(names)}")
    return Path(str(resources.files("thermod.configs").joinpath("cameras", f"{name}.toml")))


def camera_from_table(path: str, table, base: Calibration | None = None, *,
                      tau_required: bool = True) -> Calibration:
    """Validate a ``[camera]`` table; what it omits keeps `base`'s values (default: `Calibration()`).
    Every bad key is reported in one ConfigError naming the file. `tau_required`: whether ``tau_s``
    must be given (a caller that fits τ itself passes False, and asks `states_tau`)."""
    s = Section(path, "camera", table)
    d = base or Calibration()
    width = s.pop("width", None, int, lo=8, hi=16384, required=True)
    height = s.pop("height", None, int, lo=8, hi=16384, required=True)
    given = [k for k in FOCAL_KEYS if s.has(k)]
    if len(given) != 1:
        s.problem(FOCAL_KEYS[0], f"expected exactly one of {', '.join(FOCAL_KEYS)} (the focal length), got "
                                 f"{', '.join(given) or 'none'}")
    pitch_given = s.has("pixel_pitch_um")
    pitch = s.pop("pixel_pitch_um", d.pixel_pitch_um, float, lo=0.0, lo_open=True, hi=1000.0)
    hfov = s.pop("hfov_deg", None, float, lo=0.1, hi=175.0)
    focal_mm = s.pop("focal_length_mm", None, float, lo=0.0, lo_open=True, hi=10000.0)
    fx = s.pop("fx", None, float, lo=0.0, lo_open=True)
    if focal_mm is not None and not pitch_given:
        s.problem("pixel_pitch_um", "missing (focal_length_mm needs the pitch)")
    kw = dict(cx=s.pop("cx", None, float), cy=s.pop("cy", None, float),
              frame_rate_hz=s.pop("frame_rate_hz", None, float, lo=0.0, lo_open=True, hi=10000.0,
                                  required=True),
              tau_s=s.pop("tau_s", None if tau_required else d.tau_s, float, lo=0.0, lo_open=True, hi=1.0,
                          required=tau_required),
              f_number=s.pop("f_number", d.f_number, float, lo=0.1, hi=100.0),
              wavelength_um=s.pop("wavelength_um", d.wavelength_um, float, lo=0.1, hi=100.0),
              readout_s=s.pop("readout_s", 0.0, float, lo=0.0, hi=1.0))
    s.done()      # every problem so far, at once
    if kw["readout_s"] > 1.0 / kw["frame_rate_hz"]:
        raise ConfigError(f"{path}: camera.readout_s: expected at most one frame period "
                          f"({1.0 / kw['frame_rate_hz']:.4g} s), got {kw['readout_s']!r}")
    if hfov is not None:
        fx = 0.5 * width / math.tan(math.radians(hfov) / 2.0)
    elif focal_mm is not None:
        fx = focal_mm * 1000.0 / pitch
    for k, side in (("cx", width), ("cy", height)):
        if kw[k] is not None and not -side <= kw[k] <= 2 * side:
            raise ConfigError(f"{path}: camera.{k}: expected a value in [{-side}, {2 * side}] px, "
                              f"got {kw[k]!r}")
    kw.update(width=width, height=height, fx=fx, fy=fx, pixel_pitch_um=pitch,
              cx=(width - 1) / 2.0 if kw["cx"] is None else kw["cx"],
              cy=(height - 1) / 2.0 if kw["cy"] is None else kw["cy"])
    try:
        return d.replace(**kw)
    except CalibrationError as e:
        raise ConfigError(f"{path}: camera.{e.field}: {e.problem}") from None


def load_camera(path: str | os.PathLike, base: Calibration | None = None, *,
                tau_required: bool = True) -> Calibration:
    """The calibration a CAMERA.toml describes: its ``[camera]`` table, or else its ``[calibration]``
    table. Anything else is a ConfigError naming the file."""
    p = Path(path)
    raw = read_toml(p)
    if "camera" in raw:
        return camera_from_table(str(p), raw["camera"], base, tau_required=tau_required)
    if "calibration" in raw:
        return calibration_from_table(str(p), raw["calibration"], base)
    raise ConfigError(f"{p}: expected a [camera] table (width, height, hfov_deg, frame_rate_hz, tau_s, …) "
                      "or a [calibration] table")


def states_tau(path: str | os.PathLike) -> bool:
    """Whether a CAMERA.toml gives the detector's τ (``tau_s`` in its [camera] or [calibration] table)."""
    raw = read_toml(Path(path))
    return any(isinstance(raw.get(t), dict) and "tau_s" in raw[t] for t in ("camera", "calibration"))
