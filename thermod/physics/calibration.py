"""The one parameter set shared by the simulator, the renderer, the daemon and the discrepancy fit.

Keys are the recording attributes of DESIGN.md §3 (format v1): camera intrinsics, detector τ,
optics, rolling readout, and the gyro → camera calibration
`ω_cam = R_cam_gyro · scale · (ω_gyro − bias)`, sampled at `t_gyro + time_offset_s`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from thermod.physics.geometry import Intrinsics, so3_exp

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "tau_s", "frame_rate_hz", "wavelength_um",
               "f_number", "psf_beta", "pixel_pitch_um", "readout_s")
GYRO_KEYS = ("rate_hz", "R_cam_gyro", "bias_rad_s", "time_offset_s", "scale")

# The paper's SBTI setup: FLIR A655sc-like, IFOV 0.0391°, τ = 8 ms, 640×480 at 50 Hz, 17 µm pitch.
PAPER_IFOV_RAD = math.radians(0.0391)


@dataclass(frozen=True)
class Calibration:
    width: int = 640
    height: int = 480
    fx: float = 1.0 / PAPER_IFOV_RAD
    fy: float = 1.0 / PAPER_IFOV_RAD
    cx: float = 319.5
    cy: float = 239.5
    tau_s: float = 0.008
    frame_rate_hz: float = 50.0
    wavelength_um: float = 10.0
    f_number: float = 1.0
    psf_beta: float = 0.6
    pixel_pitch_um: float = 17.0
    readout_s: float = 0.0
    rate_hz: float = 1000.0
    R_cam_gyro: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    bias_rad_s: tuple = (0.0, 0.0, 0.0)
    time_offset_s: float = 0.0
    scale: tuple = (1.0, 1.0, 1.0)
    extra: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    # ----------------------------------------------------------------- derived
    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(int(self.width), int(self.height), self.fx, self.fy, self.cx, self.cy)

    @property
    def K(self) -> np.ndarray:
        return self.intrinsics.K

    @property
    def psf_sigma_um(self) -> float:
        """Eq. 19: σ = 0.45 λ F# / β (µm)."""
        return 0.45 * self.wavelength_um * self.f_number / self.psf_beta

    @property
    def psf_sigma_px(self) -> float:
        return self.psf_sigma_um / self.pixel_pitch_um

    def with_psf_sigma_px(self, sigma_px: float) -> Calibration:
        """The same optics with β chosen so that Eq. 19 gives `sigma_px`."""
        beta = 0.45 * self.wavelength_um * self.f_number / (sigma_px * self.pixel_pitch_um)
        return dataclasses.replace(self, psf_beta=float(beta))

    @property
    def R_cam_gyro_matrix(self) -> np.ndarray:
        return np.asarray(self.R_cam_gyro, dtype=np.float64).reshape(3, 3)

    @property
    def scale_vector(self) -> np.ndarray:
        s = np.asarray(self.scale, dtype=np.float64).ravel()
        return np.full(3, s[0]) if s.size == 1 else s

    @property
    def gyro_to_camera_matrix(self) -> np.ndarray:
        """M such that ω_cam = M (ω_gyro − bias)."""
        return self.R_cam_gyro_matrix @ np.diag(self.scale_vector)

    def gyro_to_camera(self, t_gyro: np.ndarray, rate_gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw gyro samples → (camera-clock times, calibrated camera-frame rates, float64)."""
        unbiased = np.asarray(rate_gyro, np.float64) - np.asarray(self.bias_rad_s)
        rate = unbiased @ self.gyro_to_camera_matrix.T
        return np.asarray(t_gyro, np.float64) + self.time_offset_s, rate

    def camera_to_gyro(self, rate_cam: np.ndarray) -> np.ndarray:
        """Inverse of the rate part of `gyro_to_camera`: what an ideal gyro reads (gyro frame, with
        its bias) for camera-frame rates [n, 3] — ω_gyro = (R_cam_gyro · scale)⁻¹ ω_cam + bias."""
        w = np.asarray(rate_cam, np.float64)
        g = np.linalg.solve(self.gyro_to_camera_matrix, w.reshape(-1, 3).T).T + np.asarray(self.bias_rad_s)
        return g.reshape(w.shape)

    def replace(self, **changes) -> Calibration:
        return dataclasses.replace(self, **changes)

    def with_misalignment(self, rotvec_rad) -> Calibration:
        """Compose an extra gyro→camera rotation (camera side) onto R_cam_gyro."""
        R = so3_exp(rotvec_rad) @ self.R_cam_gyro_matrix
        return dataclasses.replace(self, R_cam_gyro=_tuple2(R))

    # ------------------------------------------------------------ (de)serialise
    def camera_attrs(self) -> dict:
        return {k: _plain(getattr(self, k)) for k in CAMERA_KEYS}

    def gyro_attrs(self) -> dict:
        return {
            "rate_hz": float(self.rate_hz),
            "R_cam_gyro": self.R_cam_gyro_matrix,
            "bias_rad_s": np.asarray(self.bias_rad_s, dtype=np.float64),
            "time_offset_s": float(self.time_offset_s),
            "scale": self.scale_vector,
        }

    def as_dict(self) -> dict:
        """Plain JSON/TOML-friendly dict with the recording attribute names."""
        d = {k: _plain(v) for k, v in {**self.camera_attrs(), **self.gyro_attrs()}.items()}
        return d

    @classmethod
    def from_attrs(cls, camera: dict, gyro: dict | None = None) -> Calibration:
        """Build from recording attributes (missing keys keep their defaults). Raises KeyError/ValueError."""
        kw = {}
        for k in CAMERA_KEYS:
            if k in camera:
                kw[k] = int(camera[k]) if k in ("width", "height") else float(camera[k])
        gyro = gyro or {}
        if "rate_hz" in gyro:
            kw["rate_hz"] = float(gyro["rate_hz"])
        if "time_offset_s" in gyro:
            kw["time_offset_s"] = float(gyro["time_offset_s"])
        if "R_cam_gyro" in gyro:
            R = np.asarray(gyro["R_cam_gyro"], dtype=np.float64)
            if R.shape != (3, 3):
                raise ValueError(f"R_cam_gyro must be 3×3, got shape {R.shape}")
            kw["R_cam_gyro"] = _tuple2(R)
        if "bias_rad_s" in gyro:
            b = np.asarray(gyro["bias_rad_s"], dtype=np.float64).ravel()
            if b.shape != (3,):
                raise ValueError(f"bias_rad_s must have 3 values, got {b.size}")
            kw["bias_rad_s"] = tuple(float(x) for x in b)
        if "scale" in gyro:
            s = np.asarray(gyro["scale"], dtype=np.float64).ravel()
            if s.size not in (1, 3):
                raise ValueError(f"scale must have 1 or 3 values, got {s.size}")
            kw["scale"] = tuple(float(x) for x in (np.full(3, s[0]) if s.size == 1 else s))
        return cls(**kw)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        return cls.from_attrs(d, d)


def _tuple2(R: np.ndarray) -> tuple:
    return tuple(tuple(float(x) for x in row) for row in np.asarray(R))


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v
