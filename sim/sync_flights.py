"""Simulated "bring your own flight" inputs for the sync tests and benchmark: an AGC'd 8-bit video that
starts somewhere inside a longer gyro log, with the camera mounted on the flight controller in one of
the 24 axis-aligned orientations. The truth (offset, mount, bias) is hidden from the sync and kept here.

Motion: the real Betaflight log (/work/shared/data/gyro) when present, its own time base the log's;
otherwise a procedural flight (`sim.motion.flight` plus a rotor-like multirotor motion) over a 40 s log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.geometry import Intrinsics
from thermod.sim import motion as mo
from thermod.sim.synth import simulate
from thermod.sync import MOUNTS

WIDTH, HEIGHT = 160, 120
#: a 640-px core behind a 50° lens, at a quarter of its size
IFOV_DEG = 50.0 / 640 * 4
FPS = 50.0
TAU_S = 0.008
LOG_RATE_HZ = 1000.0
T_VIDEO0 = 100.0            # the simulator's video clock at the first frame


def real_log() -> mo.GyroLog | None:
    return mo.gyro_log(None, 0.0) if mo.default_log_path() is not None else None


@dataclass
class SyncFlight:
    frames: np.ndarray          # uint8 [N, H, W], AGC'd
    frame_t: np.ndarray
    gyro_t: np.ndarray          # the log's clock
    gyro_rate: np.ndarray       # rad/s, flight-controller frame
    intrinsics: Intrinsics
    tau_s: float
    true_offset_s: float        # t_cam = t_gyro + offset
    mount_index: int            # ω_cam = MOUNTS[i] ω_gyro (before the misalignment)
    misalignment_rad: np.ndarray
    bias_rad_s: np.ndarray
    motion: str
    raw: np.ndarray | None = None   # uint16 [N, H, W]: the detector counts before the AGC
    drift_ppm: float = 0.0          # the log's clock runs at 1 + ε against the video's

    @property
    def true_R(self) -> np.ndarray:
        from thermod.physics.geometry import so3_exp
        return so3_exp(self.misalignment_rad) @ MOUNTS[self.mount_index]


def agc_8bit(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A camera's automatic gain control: each frame's 1–99 % range stretched to about 10–245 with a
    jittered gain and level (a few % a frame), rounded to 8 bits."""
    out = np.empty(frames.shape, np.uint8)
    for k, f in enumerate(frames.astype(np.float64)):
        lo, hi = np.percentile(f, (1.0, 99.0))
        gain = 235.0 / max(hi - lo, 1.0) * (1.0 + 0.05 * rng.standard_normal())
        level = 10.0 + 8.0 * rng.standard_normal()
        out[k] = np.clip(np.round(level + gain * (f - lo)), 0, 255).astype(np.uint8)
    return out


def procedural_motion(seed: int) -> mo.Motion:
    return mo.Summed(mo.flight((35.0, 15.0, 50.0), seed), mo.multirotor(40.0, seed))


def make_flight(seed: int = 0, seconds: float = 3.0, *, motion: str = "auto", static: bool = False,
                log_s: float = 40.0, mount_index: int | None = None, bias=(0.01, -0.006, 0.004),
                misalignment=(0.01, -0.008, 0.012), gyro_noise_deg_s: float = 0.5,
                netd: float = 0.05, width: int = WIDTH, effects: dict | None = None,
                drift_ppm: float = 0.0) -> SyncFlight:
    """A video of `seconds` somewhere in a log of `log_s` (the real log's length when it is used),
    `width` px wide (4:3, a 50° field of view); `effects` are hidden simulator effects (the nominal
    τ and readout stay `TAU_S` and 0). `drift_ppm`: the log's clock runs at 1 + ε against the video's,
    the two agreeing at the video's middle (so `true_offset_s` holds there)."""
    rng = np.random.default_rng([seed, 24])
    log = real_log() if motion in ("auto", "real") else None
    if motion == "real" and log is None:
        raise FileNotFoundError("the real Betaflight log is not in the shared data")
    if log is not None:
        log_t = np.arange(0.0, log.t_log[-1], 1.0 / LOG_RATE_HZ)
        source, name = log, "real log"
    else:
        log_t = np.arange(0.0, log_s, 1.0 / LOG_RATE_HZ)
        source, name = procedural_motion(seed), "procedural"
    start = float(rng.uniform(1.0, log_t[-1] - seconds - 1.0))
    video_motion = mo.Static() if static else _Shifted(source, start)
    height = width * HEIGHT // WIDTH
    f_px = width / WIDTH / math.radians(IFOV_DEG)        # the same 50° field of view at any width
    cal = Calibration(width=width, height=height, fx=f_px, fy=f_px,
                      cx=(width - 1) / 2, cy=(height - 1) / 2, tau_s=TAU_S, frame_rate_hz=FPS)
    hidden = {"netd": netd, **(effects or {})}
    rec = simulate("texture", video_motion, seconds, cal, effects=hidden, seed=seed, truth=False)
    mount = int(rng.integers(0, len(MOUNTS))) if mount_index is None else int(mount_index)
    from thermod.physics.geometry import so3_exp
    R = so3_exp(np.asarray(misalignment, float)) @ MOUNTS[mount]
    eps = drift_ppm * 1e-6
    epoch = start + 0.5 * (round(seconds * FPS) - 1) / FPS
    w_cam = source.omega(log_t + eps * (log_t - epoch))          # the log's stamps run at 1 + ε
    rate = w_cam @ R + np.asarray(bias, float)             # ω_gyro = Rᵀ ω_cam + b
    rate += math.radians(gyro_noise_deg_s) * rng.standard_normal(rate.shape)
    frames = agc_8bit(rec.frames, rng)
    return SyncFlight(frames, rec.t.copy(), log_t, rate, cal.intrinsics, TAU_S, T_VIDEO0 - start, mount,
                      np.asarray(misalignment, float), np.asarray(bias, float),
                      "static" if static else f"{name} from {start:.2f} s", rec.frames, drift_ppm)


class _Shifted(mo.Motion):
    """`inner` from `start_s` on: motion time 0 is `start_s` of the log."""

    def __init__(self, inner: mo.Motion, start_s: float):
        self.inner, self.start_s, self.spec = inner, float(start_s), f"{inner.spec}@{start_s:.2f}"

    def omega(self, t):
        return self.inner.omega(np.atleast_1d(np.asarray(t, float)) + self.start_s)
