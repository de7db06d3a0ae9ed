"""The one parameter set shared by the simulator, the renderer, the daemon and the discrepancy fit.

Keys are the recording attributes of docs/design.md §3 (format v1): camera intrinsics, detector τ,
optics, rolling readout, and the gyro → camera calibration
`ω_cam = R_cam_gyro · scale · (ω_gyro − bias)`, sampled at `t_gyro + time_offset_s`.

Three gyro-side effects precondition the raw samples before that map (`condition_gyro`; all off by
default): a clipped range (`gyro_range_rad_s`: clipped runs are replaced by a smooth continuation),
the chip's digital low-pass (`gyro_lowpass_hz`: a regularised inverse of a 2nd-order Butterworth)
and clock drift (`clock_drift_ppm`: the gyro clock runs at 1 + ε against the camera's,
``t_cam = t_gyro + time_offset_s + ε (t_gyro − clock_epoch_s)``, so `time_offset_s` is the offset
at the gyro-clock epoch `clock_epoch_s`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from thermod.errors import ThermodError
from thermod.physics import gyro_effects
from thermod.physics.effects import GYRO_CONDITIONING_FIELDS
from thermod.physics.geometry import Intrinsics, so3_exp

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "tau_s", "frame_rate_hz", "wavelength_um",
               "f_number", "psf_beta", "pixel_pitch_um", "readout_s")
GYRO_KEYS = ("rate_hz", "R_cam_gyro", "bias_rad_s", "time_offset_s", "scale", "clock_drift_ppm",
             "clock_epoch_s", "gyro_lowpass_hz", "gyro_range_rad_s", "gyro_clip_gain")
# Gyro-side effect fields (scalars; 0 = off, except the clip gain whose neutral value is 1).
GYRO_EFFECT_KEYS = GYRO_CONDITIONING_FIELDS
assert GYRO_KEYS[5:] == GYRO_EFFECT_KEYS, "physics.effects and GYRO_KEYS disagree on the gyro's fields"

# The paper's SBTI setup: FLIR A655sc-like, IFOV 0.0391°, τ = 8 ms, 640×480 at 50 Hz, 17 µm pitch.
PAPER_IFOV_RAD = math.radians(0.0391)

# What a pinhole camera can be: a field of view between a long telephoto's and a wide angle's.
MIN_FOV_DEG, MAX_FOV_DEG = 0.1, 175.0
MAX_SIDE_PX = 16384
# A detector time constant no detector has (microbolometers: 3–20 ms) still renders (the renderer was
# checked down to 1e-8 s), but a positive 1e-300 from a corrupt file underflows it: bound it physically.
MIN_TAU_S, MAX_TAU_S = 1e-6, 1.0
# Eq. 19's σ in pixels: a lens blurring beyond this is no imaging camera, and the PSF kernel (radius
# 3σ, squared) is allocated from it — from file contents, so it is bounded.
MAX_PSF_SIGMA_PX = 64.0
ROTATION_TOL = 1e-4     # |R Rᵀ − I| allowed: six printed decimals, not a shear

#: The range of each scalar field that does not depend on another field: (lo, hi, lo_open, unit). The
#: one range check, read by `Calibration` and by the TOML reader (`thermod.io.calibration_file`, which
#: reports every bad key of a file at once).
RANGES: dict[str, tuple[float, float, bool, str]] = {
    "width": (1, MAX_SIDE_PX, False, "px"), "height": (1, MAX_SIDE_PX, False, "px"),
    "fx": (0.0, math.inf, True, "px"), "fy": (0.0, math.inf, True, "px"),
    "tau_s": (MIN_TAU_S, MAX_TAU_S, False, "s"),
    "frame_rate_hz": (0.0, 10000.0, True, "Hz"), "rate_hz": (0.0, 100000.0, True, "Hz"),
    "wavelength_um": (0.1, 100.0, False, "µm"), "f_number": (0.1, 100.0, False, ""),
    "psf_beta": (0.0, 1.0, True, ""), "pixel_pitch_um": (0.0, 1000.0, True, "µm"),
    "time_offset_s": (-1.0, 1.0, False, "s"),
}


def range_text(key: str) -> str:
    """What `RANGES` allows for `key`, as an error message says it."""
    lo, hi, lo_open, unit = RANGES[key]
    if lo == 0 and lo_open and hi == math.inf:
        return "a positive number" + (f" ({unit})" if unit else "")
    return f"a value in {'(' if lo_open else '['}{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")


class CalibrationError(ThermodError, ValueError):
    """A calibration value out of range or of the wrong type. `field` is the key (a recording
    attribute / [calibration] key), `problem` says what was expected; callers prefix the source."""

    def __init__(self, field: str, problem: str):
        self.field, self.problem = field, problem
        super().__init__(f"{field}: {problem}")


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
    clock_drift_ppm: float = 0.0
    clock_epoch_s: float = 0.0
    gyro_lowpass_hz: float = 0.0
    gyro_range_rad_s: float = 0.0
    gyro_clip_gain: float = 1.0
    # One recording's fitted continuation gain per clipped run (`gyro_effects.continuations` of its whole
    # series; the discrepancy fit's): not a property of the payload, so never written out, and a live
    # stream's windows, which see parts of runs, use `gyro_clip_gain`.
    gyro_clip_run_gains: tuple = ()
    extra: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __post_init__(self):
        """Normalise the types (numpy → Python, arrays → tuples) and check every range: an invalid
        calibration cannot exist, whatever built it (config, --set, recording attributes, reload)."""
        set_ = object.__setattr__
        for k in ("width", "height"):
            set_(self, k, _integer(k, getattr(self, k), *RANGES[k][:2]))
        for k in _FLOAT_KEYS:
            set_(self, k, _number(k, getattr(self, k)))
        for k, (lo, hi, lo_open, _) in RANGES.items():
            v = getattr(self, k)
            if not ((lo < v) if lo_open else (lo <= v)) or not v <= hi:
                raise CalibrationError(k, f"expected {range_text(k)}, got {v!r}")
        for k, side in (("fx", self.width), ("fy", self.height)):
            fov = math.degrees(2.0 * math.atan(0.5 * side / getattr(self, k)))
            if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
                raise CalibrationError(k, f"expected a focal length giving a field of view in "
                                          f"[{MIN_FOV_DEG}°, {MAX_FOV_DEG}°] over {side} px, got "
                                          f"{getattr(self, k)!r} ({fov:.3g}°)")
        if not self.psf_sigma_px <= MAX_PSF_SIGMA_PX:
            raise CalibrationError("psf", f"expected an optical PSF σ ≤ {MAX_PSF_SIGMA_PX:g} px (Eq. 19: "
                                          f"0.45·wavelength_um·f_number/psf_beta/pixel_pitch_um), got "
                                          f"{self.psf_sigma_px:.4g} px from wavelength_um="
                                          f"{self.wavelength_um!r}, f_number={self.f_number!r}, "
                                          f"psf_beta={self.psf_beta!r}, "
                                          f"pixel_pitch_um={self.pixel_pitch_um!r}")
        period = 1.0 / self.frame_rate_hz
        if not 0 <= self.readout_s <= period * (1 + 1e-9):
            raise CalibrationError("readout_s", f"expected a value in [0, {period:.6g}] s (one frame "
                                                f"period), got {self.readout_s!r}")
        _check_gyro_effects(self)
        set_(self, "gyro_clip_run_gains", _run_gains(self))
        set_(self, "bias_rad_s", _vector("bias_rad_s", self.bias_rad_s, (3,)))
        if not all(abs(x) <= MAX_GYRO_RANGE_RAD_S for x in self.bias_rad_s):   # no gyro measures more
            raise CalibrationError("bias_rad_s", f"expected 3 numbers within ±{MAX_GYRO_RANGE_RAD_S:.4g} "
                                                 f"rad/s (±10000 °/s), got {list(self.bias_rad_s)}")
        scale = _vector("scale", self.scale, (1, 3))
        scale = scale * 3 if len(scale) == 1 else scale
        if not all(0 < x <= MAX_GYRO_SCALE for x in scale):
            raise CalibrationError("scale", f"expected 1 or 3 numbers in (0, {MAX_GYRO_SCALE:g}], "
                                            f"got {list(scale)}")
        set_(self, "scale", scale)
        set_(self, "R_cam_gyro", _rotation("R_cam_gyro", self.R_cam_gyro))

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
        """The same optics with β chosen so that Eq. 19 gives `sigma_px`. σ below the diffraction
        limit (β = 1) is not a lens: CalibrationError."""
        s = _number("psf_sigma_px", sigma_px)
        limit = 0.45 * self.wavelength_um * self.f_number / self.pixel_pitch_um
        if not s >= limit:
            raise CalibrationError("psf_sigma_px", f"expected at least the diffraction limit {limit:.4g} px "
                                                   f"(Eq. 19 with β = 1), got {sigma_px!r}")
        return dataclasses.replace(self, psf_beta=float(limit / s))

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
        t, r = self.condition_gyro(t_gyro, rate_gyro)
        unbiased = r - np.asarray(self.bias_rad_s)
        rate = unbiased @ self.gyro_to_camera_matrix.T
        return t + self.time_offset_s, rate

    @property
    def has_gyro_effects(self) -> bool:
        return bool(self.clock_drift_ppm or self.gyro_lowpass_hz or self.gyro_range_rad_s)

    def condition_gyro(self, t_gyro, rate_gyro, whole_series: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Raw samples as an ideal gyro on a drift-free clock would give them (float64; gyro frame,
        bias kept): clipped runs reconstructed, the low-pass inverted, the clock drift removed
        (times on the gyro clock rescaled about `clock_epoch_s`; `time_offset_s` is added by
        `gyro_to_camera`). A no-op copy when none of the three is set. `whole_series`: the samples
        are the series `gyro_clip_run_gains` were fitted on (else one gain for every run)."""
        t = np.asarray(t_gyro, np.float64)
        r = np.asarray(rate_gyro, np.float64)
        if r.ndim == 2 and len(r) >= 4:
            if self.gyro_range_rad_s > 0:
                runs = self.gyro_clip_run_gains if whole_series else ()
                r = gyro_effects.unclip(t, r, self.gyro_range_rad_s, self.gyro_clip_gain, runs)
            if self.gyro_lowpass_hz > 0:
                r = gyro_effects.inverse_lowpass(t, r, self.gyro_lowpass_hz)
        if self.clock_drift_ppm:
            t = self.gyro_clock_to_ideal(t)
        return t, r

    @property
    def gyro_condition_margin_s(self) -> float:
        """Gyro time `condition_gyro` needs either side of a span: the inverse filter's reach
        (8/f_c) and a clipped run's (50 ms)."""
        m = 0.0
        if self.gyro_lowpass_hz > 0:
            m = max(m, 8.0 / self.gyro_lowpass_hz)
        if self.gyro_range_rad_s > 0:
            m = max(m, 0.05)
        return m

    def condition_window(self, t_gyro, rate_gyro, t_cam_lo: float, t_cam_hi: float):
        """`condition_gyro` of the samples covering camera times [t_cam_lo, t_cam_hi] (plus the
        margin the corrections need): what a kernel renderer passed a whole ring buffer needs."""
        t = np.asarray(t_gyro)
        if not self.has_gyro_effects:
            return t, rate_gyro
        m = self.gyro_condition_margin_s + 2.0 / self.rate_hz
        lo, hi = self.camera_time_to_gyro(np.array([t_cam_lo, t_cam_hi]))
        i0, i1 = np.searchsorted(t, [lo - m, hi + m])
        i0, i1 = max(int(i0) - 2, 0), min(int(i1) + 2, len(t))
        return self.condition_gyro(t[i0:i1], np.asarray(rate_gyro)[i0:i1], whole_series=False)

    def gyro_clock_to_ideal(self, t_gyro):
        """Gyro-clock stamps → drift-free gyro time: t + ε (t − epoch)."""
        eps = self.clock_drift_ppm * 1e-6
        return np.asarray(t_gyro, np.float64) + eps * (np.asarray(t_gyro, np.float64) - self.clock_epoch_s)

    def gyro_time_to_camera(self, t_gyro):
        """Camera-clock time of gyro stamps: t + time_offset_s + ε (t − clock_epoch_s)."""
        return self.gyro_clock_to_ideal(t_gyro) + self.time_offset_s

    def camera_time_to_gyro(self, t_cam):
        """Inverse of `gyro_time_to_camera`: the gyro stamp read at camera time t_cam."""
        eps = self.clock_drift_ppm * 1e-6
        t = np.asarray(t_cam, np.float64) - self.time_offset_s
        return (t + eps * self.clock_epoch_s) / (1.0 + eps)

    def camera_to_gyro(self, rate_cam: np.ndarray) -> np.ndarray:
        """Inverse of the rate part of `gyro_to_camera`: what an ideal gyro reads (gyro frame, with
        its bias) for camera-frame rates [n, 3] — ω_gyro = (R_cam_gyro · scale)⁻¹ ω_cam + bias."""
        w = np.asarray(rate_cam, np.float64)
        g = np.linalg.solve(self.gyro_to_camera_matrix, w.reshape(-1, 3).T).T + np.asarray(self.bias_rad_s)
        return g.reshape(w.shape)

    def replace(self, **changes) -> Calibration:
        return dataclasses.replace(self, **changes)

    def with_camera_gyro(self, rate_hz: float) -> Calibration:
        """This camera with the gyro part of rates measured from its own pictures: camera-frame samples
        at `rate_hz` on the frames' clock (every other gyro key at its neutral default: no mounting,
        bias, scale, offset, drift, filter or clipping)."""
        neutral = {f.name: f.default for f in dataclasses.fields(self) if f.name in GYRO_KEYS[1:]}
        return dataclasses.replace(self, rate_hz=float(rate_hz), **neutral)

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
            **{k: float(getattr(self, k)) for k in GYRO_EFFECT_KEYS},
        }

    def as_dict(self) -> dict:
        """Plain JSON/TOML-friendly dict with the recording attribute names."""
        d = {k: _plain(v) for k, v in {**self.camera_attrs(), **self.gyro_attrs()}.items()}
        return d

    @classmethod
    def from_attrs(cls, camera: dict, gyro: dict | None = None) -> Calibration:
        """Build from recording attributes (missing keys keep their defaults). Values may be numpy
        scalars or one-element arrays; anything else raises CalibrationError naming the key."""
        kw = {k: _scalar(k, camera[k]) for k in CAMERA_KEYS if k in camera}
        gyro = gyro or {}
        for k in ("rate_hz", "time_offset_s", *GYRO_EFFECT_KEYS):
            if k in gyro:
                kw[k] = _scalar(k, gyro[k])
        for k in ("R_cam_gyro", "bias_rad_s", "scale"):
            if k in gyro:
                kw[k] = gyro[k]
        return cls(**kw)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        return cls.from_attrs(d, d)


_FLOAT_KEYS = ("fx", "fy", "cx", "cy", "tau_s", "frame_rate_hz", "wavelength_um", "f_number", "psf_beta",
               "pixel_pitch_um", "readout_s", "rate_hz", "time_offset_s", *GYRO_EFFECT_KEYS)

# Ranges of the gyro-side effect fields: a crystal is within ±100 ppm, an RC-clocked MEMS ODR within
# a few %; a DLPF below 1 Hz or above Nyquist is no DLPF; MEMS full scales are ±125…±4000 °/s.
MAX_CLOCK_DRIFT_PPM = 1e5
MIN_LOWPASS_HZ = 1.0
MAX_GYRO_RANGE_RAD_S = math.radians(10000.0)
MAX_CLIP_GAIN = 10.0
MAX_GYRO_SCALE = 100.0      # a sensitivity error of a few %, or a units slip (deg as rad: ×57.3), not more


def _check_gyro_effects(c: Calibration) -> None:
    if not abs(c.clock_drift_ppm) <= MAX_CLOCK_DRIFT_PPM:
        raise CalibrationError("clock_drift_ppm", f"expected a gyro clock drift within "
                                                  f"±{MAX_CLOCK_DRIFT_PPM:g} ppm (±10 %), "
                                                  f"got {c.clock_drift_ppm!r}")
    if not abs(c.clock_epoch_s) <= 1e10:
        raise CalibrationError("clock_epoch_s", f"expected a gyro-clock time within ±1e10 s, "
                                                f"got {c.clock_epoch_s!r}")
    nyq = 0.5 * c.rate_hz
    if c.gyro_lowpass_hz != 0 and not MIN_LOWPASS_HZ <= c.gyro_lowpass_hz < nyq:
        raise CalibrationError("gyro_lowpass_hz", f"expected 0 (none) or a cutoff in [{MIN_LOWPASS_HZ:g}, "
                                                  f"{nyq:g}) Hz (below the gyro's Nyquist rate), "
                                                  f"got {c.gyro_lowpass_hz!r}")
    if c.gyro_range_rad_s != 0 and not 0 < c.gyro_range_rad_s <= MAX_GYRO_RANGE_RAD_S:
        raise CalibrationError("gyro_range_rad_s", f"expected 0 (not clipped) or a full-scale range in "
                                                   f"(0, {MAX_GYRO_RANGE_RAD_S:.4g}] rad/s, "
                                                   f"got {c.gyro_range_rad_s!r}")
    if not 0 <= c.gyro_clip_gain <= MAX_CLIP_GAIN:
        raise CalibrationError("gyro_clip_gain", f"expected a gain in [0, {MAX_CLIP_GAIN:g}] for the "
                                                 f"continuation of clipped runs, got {c.gyro_clip_gain!r}")


def _run_gains(c: Calibration) -> tuple:
    v = c.gyro_clip_run_gains
    n = len(v) if isinstance(v, (tuple, list, np.ndarray)) else -1
    if n < 0:
        raise CalibrationError("gyro_clip_run_gains", f"expected a sequence of gains, got {_show(v)}")
    g = _vector("gyro_clip_run_gains", v, (n,)) if n else ()
    if g and not c.gyro_range_rad_s > 0:
        raise CalibrationError("gyro_clip_run_gains", "expected none without a clipping range "
                                                      "(gyro_range_rad_s)")
    if not all(0 <= x <= MAX_CLIP_GAIN for x in g):
        raise CalibrationError("gyro_clip_run_gains", f"expected gains in [0, {MAX_CLIP_GAIN:g}], "
                                                      f"got {list(g)}")
    return g


def _scalar(key, v):
    """A number stored as an attribute: Python/numpy scalar or a one-element array, as is."""
    if isinstance(v, np.ndarray) and v.size == 1 and v.dtype.kind in "iuf":
        return v.reshape(()).item()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _number(key: str, v) -> float:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise CalibrationError(key, f"expected a number, got {_show(v)}")
    try:
        x = float(v)
    except OverflowError:       # an integer beyond any float (JSON integers are unbounded)
        raise CalibrationError(key, f"expected a finite number, got an integer of {len(str(abs(v)))} "
                                    "digits") from None
    if not math.isfinite(x):
        raise CalibrationError(key, f"expected a finite number, got {x!r}")
    return x


def _integer(key: str, v, lo: int, hi: int) -> int:
    x = _number(key, v)
    if x != int(x) or not lo <= x <= hi:
        raise CalibrationError(key, f"expected an integer in [{lo}, {hi}], got {_show(v)}")
    return int(x)


def _vector(key: str, v, sizes: tuple[int, ...]) -> tuple:
    try:
        a = np.asarray(v)
    except (TypeError, ValueError):
        a = np.asarray(None)
    want = " or ".join(map(str, sizes))
    if a.dtype.kind not in "iuf" or a.ndim > 1 or a.size not in sizes:
        raise CalibrationError(key, f"expected {want} numbers, got {_show(v)}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(key, f"expected finite numbers, got {a.tolist()}")
    return tuple(float(x) for x in a.ravel())


def _rotation(key: str, v) -> tuple:
    try:
        R = np.asarray(v)
    except (TypeError, ValueError):
        R = np.asarray(None)
    if R.dtype.kind not in "iuf" or R.shape not in ((3, 3), (9,)):
        raise CalibrationError(key, f"expected a 3×3 rotation matrix, got {_show(v)}")
    R = R.astype(np.float64).reshape(3, 3)
    if not np.all(np.isfinite(R)):
        raise CalibrationError(key, "expected a 3×3 rotation matrix, got non-finite values")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOL or np.linalg.det(R) < 0:
        raise CalibrationError(key, f"expected a rotation matrix (orthonormal within {ROTATION_TOL}, "
                                    f"det +1), "
                                    f"got {R.round(6).tolist()} (|R Rᵀ − I| = {err:.3g}, "
                                    f"det {np.linalg.det(R):.3g})")
    return _tuple2(R)


def _show(v) -> str:
    """A short repr of an offending value (a huge array would flood the message)."""
    if isinstance(v, np.ndarray):
        return f"an array of shape {v.shape} and dtype {v.dtype}" if v.size > 9 else repr(v.tolist())
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


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
