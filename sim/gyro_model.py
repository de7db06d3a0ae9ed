"""Gyro error model: raw MEMS gyro samples from the true camera motion.

The static part of the error comes from the TRUE calibration (docs/design.md §2): the samples are in
the gyro frame and on the gyro clock, such that `calib.gyro_to_camera` with the true calibration
recovers the camera rate:

    ω_cam = R_cam_gyro · scale · (ω_gyro − bias)   ⇒   ω_gyro = scale⁻¹ R_cam_gyroᵀ ω_cam + bias
    camera time of a sample = t_gyro + time_offset_s

The random part (`GyroErrorModel`) follows the IEEE 952 error budget: white rate noise (angle
random walk), bias instability (flicker, Allan floor 0.664·B), rate random walk, plus the chip's
digital low-pass (group delay), range saturation, quantisation (LSB), sample-time jitter and
clock drift.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration

DEG = math.pi / 180.0


@dataclass(frozen=True)
class GyroErrorModel:
    """Random and electronic gyro errors (per axis, independent). Rates in °/s as on datasheets.

    noise_rms_deg_s      white rate noise per sample (°/s RMS at `rate_hz`); ARW = σ/√f·60 °/√h
    bias_instability_deg_s  B: flicker bias, PSD B²/(2πf) below `bias_corner_hz` → Allan floor 0.664·B
    rate_random_walk_deg_s_sqrt_s  K: bias random walk, Allan σ(T) = K √(T/3)
    resolution_deg_s     LSB (0 = continuous)
    range_deg_s          full-scale range (± saturation)
    jitter_s             RMS timing jitter of the sampling instant (the stamp stays on the grid)
    clock_drift_ppm      the gyro clock runs slow/fast: stamps drift away from camera time
    lowpass_hz           chip's digital low-pass (2nd-order Butterworth, group delay ≈ √2/(2π f_c))
    rate_hz              output data rate (None → the calibration's rate_hz)
    bias_corner_hz       above it the flicker bias rolls off (it never dominates the white noise)
    """

    noise_rms_deg_s: float = 0.0
    bias_instability_deg_s: float = 0.0
    rate_random_walk_deg_s_sqrt_s: float = 0.0
    resolution_deg_s: float = 0.0
    range_deg_s: float = math.inf
    jitter_s: float = 0.0
    clock_drift_ppm: float = 0.0
    lowpass_hz: float = 0.0
    rate_hz: float | None = None
    bias_corner_hz: float = 0.1

    @classmethod
    def paper(cls, **kw) -> GyroErrorModel:
        """The paper's Table 1 gyro: 0.05 °/s RMS noise, 0.0076 °/s resolution, ±200 °/s range,
        0.12 °/s bias drift (taken as the bias instability)."""
        return cls(**{**dict(noise_rms_deg_s=0.05, resolution_deg_s=0.0076, range_deg_s=200.0,
                             bias_instability_deg_s=0.12), **kw})

    def replace(self, **kw) -> GyroErrorModel:
        return dataclasses.replace(self, **kw)

    def arw_deg_rt_h(self, rate_hz: float) -> float:
        """Angle random walk (°/√h) of the white noise at `rate_hz`."""
        return self.noise_rms_deg_s / math.sqrt(rate_hz) * 60.0

    @classmethod
    def from_arw(cls, arw_deg_rt_h: float, rate_hz: float, **kw) -> GyroErrorModel:
        return cls(noise_rms_deg_s=arw_deg_rt_h / 60.0 * math.sqrt(rate_hz), rate_hz=rate_hz, **kw)

    def validate(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "rate_hz" and v is None:
                continue
            if f.name == "clock_drift_ppm":
                if not (np.isfinite(v) and abs(v) < 1e5):
                    raise ThermodError(f"gyro model clock_drift_ppm: expected |ppm| < 1e5, got {v!r}")
                continue
            if not isinstance(v, (int, float)) or math.isnan(v) or v < 0:
                raise ThermodError(f"gyro model {f.name}: expected a number ≥ 0, got {v!r}")
        if self.rate_hz is not None and not 0 < self.rate_hz < 1e6:
            raise ThermodError(f"gyro model rate_hz: expected 0 < rate < 1 MHz, got {self.rate_hz!r}")
        if self.range_deg_s == 0:
            raise ThermodError("gyro model range_deg_s: must be > 0")
        if self.bias_corner_hz <= 0:
            raise ThermodError(f"gyro model bias_corner_hz: must be > 0, got {self.bias_corner_hz!r}")

    def sample(self, omega_cam, t_start: float, t_end: float, calib: Calibration,
               rng: np.random.Generator, t_anchor: float | None = None) -> GyroSamples:
        """Raw samples covering camera times [t_start, t_end].

        omega_cam: callable(t_camera_s [n]) → [n, 3] true camera-frame rate (rad/s).
        calib: the TRUE calibration (R_cam_gyro, scale, bias, time_offset_s, rate_hz).
        t_anchor: camera time where the drifting gyro clock agrees with the camera clock
        (default t_start).
        """
        self.validate()
        rate = float(self.rate_hz or calib.rate_hz)
        if not t_end > t_start:
            raise ThermodError(f"gyro model: empty span [{t_start}, {t_end}]")
        t_anchor = t_start if t_anchor is None else float(t_anchor)
        clock = self.clock(calib, t_anchor)
        drift = clock.clock_drift_ppm * 1e-6
        # stamps on the gyro clock: a regular grid, read at the camera times the calibration maps them to
        g0 = float(clock.camera_time_to_gyro(t_start))
        n = int(math.floor((t_end - t_start) * rate / (1 + drift))) + 1
        t_gyro = g0 + np.arange(n) / rate
        t_true = clock.gyro_time_to_camera(t_gyro)
        if self.jitter_s > 0:
            t_true = t_true + self.jitter_s * rng.standard_normal(n)

        if self.lowpass_hz > 0:
            w_cam = self._lowpassed(omega_cam, t_true, rate)
        else:
            w_cam = np.asarray(omega_cam(t_true), dtype=np.float64).reshape(n, 3)
        w_gyro = calib.camera_to_gyro(w_cam)
        err = np.zeros((n, 3))
        if self.noise_rms_deg_s > 0:
            err += self.noise_rms_deg_s * DEG * rng.standard_normal((n, 3))
        if self.bias_instability_deg_s > 0:
            err += flicker_noise(n, 1.0 / rate, self.bias_instability_deg_s * DEG, rng, self.bias_corner_hz)
        if self.rate_random_walk_deg_s_sqrt_s > 0:
            k = self.rate_random_walk_deg_s_sqrt_s * DEG
            steps = k * math.sqrt(1.0 / rate) * rng.standard_normal((n, 3))
            err += np.cumsum(steps, axis=0)
        raw = w_gyro + err
        if math.isfinite(self.range_deg_s):
            raw = np.clip(raw, -self.range_deg_s * DEG, self.range_deg_s * DEG)
        if self.resolution_deg_s > 0:
            lsb = self.resolution_deg_s * DEG
            raw = np.round(raw / lsb) * lsb
        # what the camera really did at the sampling instants, for the truth record
        w_true = np.asarray(omega_cam(t_true), dtype=np.float64).reshape(n, 3)
        return GyroSamples(t_gyro, raw.astype(np.float32), t_true, w_true, rate)

    def clock(self, calib: Calibration, t_anchor: float) -> Calibration:
        """The calibration whose clock map (`Calibration.gyro_time_to_camera`) the samples follow:
        `calib`'s own, or this model's `clock_drift_ppm` with the clocks agreeing at camera time
        `t_anchor` (epoch t_anchor − time offset on the gyro clock)."""
        if not self.clock_drift_ppm:
            return calib
        if calib.clock_drift_ppm:
            raise ThermodError("gyro model clock_drift_ppm: the calibration has a clock drift already; "
                               "set one of the two")
        return calib.replace(clock_drift_ppm=float(self.clock_drift_ppm),
                             clock_epoch_s=float(t_anchor) - calib.time_offset_s)

    def _lowpassed(self, omega_cam, t_true, rate):
        """Sensed rate through the chip's 2nd-order Butterworth, run on an 8× oversampled grid
        started 10/f_c early so the filter has settled."""
        fs = 8.0 * max(rate, 4 * self.lowpass_hz)
        if self.lowpass_hz >= 0.5 * fs:
            raise ThermodError(f"gyro model lowpass_hz: {self.lowpass_hz} Hz is above the Nyquist rate")
        t0 = float(t_true.min()) - 10.0 / self.lowpass_hz
        tg = t0 + np.arange(int(math.ceil((float(t_true.max()) - t0) * fs)) + 2) / fs
        w = np.asarray(omega_cam(tg), dtype=np.float64).reshape(-1, 3)
        b, a = signal.butter(2, self.lowpass_hz, fs=fs)
        zi = signal.lfilter_zi(b, a)
        wf = np.stack([signal.lfilter(b, a, w[:, i], zi=zi * w[0, i])[0] for i in range(3)], axis=1)
        return np.stack([np.interp(t_true, tg, wf[:, i]) for i in range(3)], axis=1)


@dataclass
class GyroSamples:
    t: np.ndarray           # float64 [n] stamps on the gyro's mapped clock (what a recording stores)
    rate: np.ndarray        # float32 [n, 3] raw rad/s, gyro frame
    t_true: np.ndarray      # float64 [n] true camera-clock sampling instants
    omega_true: np.ndarray  # float64 [n, 3] true camera-frame rate at t_true
    rate_hz: float


def flicker_noise(n: int, dt: float, b: float, rng: np.random.Generator,
                  corner_hz: float = 0.1) -> np.ndarray:
    """[n, 3] flicker (1/f) bias noise: IEEE 952 PSD B²/(2πf) (two-sided level, i.e. one-sided
    B²/(πf)) below `corner_hz`, rolled off as 1/f³ above it so that it never masks the white noise
    at the sample rate. Its Allan deviation floor is √(2 ln2/π)·B ≈ 0.664 B for averaging times
    ≫ 1/(2π corner). Spectral synthesis on 2n points (first half kept: no periodic wrap)."""
    m = 2 * n
    f = np.fft.rfftfreq(m, dt)
    amp = np.zeros_like(f)
    s1 = b * b / (np.pi * f[1:]) / (1.0 + (f[1:] / corner_hz) ** 2)
    amp[1:] = np.sqrt(m * s1 / (4 * dt))
    X = amp[:, None] * (rng.standard_normal((f.size, 3)) + 1j * rng.standard_normal((f.size, 3)))
    return np.fft.irfft(X, n=m, axis=0)[:n]


def allan_deviation(x: np.ndarray, dt: float, taus: np.ndarray) -> np.ndarray:
    """Overlapping Allan deviation of a rate series x (1-D) for averaging times `taus` (s)."""
    x = np.asarray(x, dtype=np.float64)
    theta = np.r_[0.0, np.cumsum(x) * dt]                       # integrated angle
    out = np.empty(len(taus))
    for i, tau in enumerate(taus):
        m = int(round(tau / dt))
        if m < 1 or 2 * m >= len(theta):
            out[i] = np.nan
            continue
        d = theta[2 * m:] - 2 * theta[m:-m] + theta[:-2 * m]
        out[i] = np.sqrt(np.mean(d * d) / (2 * (m * dt) ** 2))
    return out


@dataclass(frozen=True)
class GyroDrift:
    """A gyro bias and a gyro → camera time offset that move during a run (temperature, a USB camera's
    unstamped frames): each starts at its ``*_0`` value and changes at a constant rate for
    ``ramp_s`` seconds of payload time, then holds. Added on top of the true calibration's.

    bias(t) = bias_0 + bias_rate · min(t, ramp_s)   (rad/s, gyro frame)
    offset(t) = offset_0 + offset_rate · min(t, ramp_s)   (s; camera time of a sample = stamp + offset)
    """

    bias_0: tuple = (0.0, 0.0, 0.0)
    bias_rate: tuple = (0.0, 0.0, 0.0)          # rad/s per s
    offset_0: float = 0.0
    offset_rate: float = 0.0                    # s per s
    ramp_s: float = math.inf

    def _elapsed(self, t) -> np.ndarray:
        return np.minimum(np.maximum(np.asarray(t, np.float64), 0.0), self.ramp_s)

    def bias(self, t) -> np.ndarray:
        """[..., 3] extra bias at payload time(s) t."""
        e = self._elapsed(t)[..., None]
        return np.asarray(self.bias_0, np.float64) + np.asarray(self.bias_rate, np.float64) * e

    def offset(self, t) -> np.ndarray:
        return self.offset_0 + self.offset_rate * self._elapsed(t)
