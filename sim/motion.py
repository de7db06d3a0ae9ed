"""Camera motion: angular velocity ω(t) in the camera frame (rad/s) and its integral R(t).

Conventions (docs/design.md §2): OpenCV camera frame (x right, y down, z forward), R(t) maps camera
vectors to world, dR/dt = R [ω]×. So ω_y > 0 is a pan to the right (yaw), ω_x > 0 tilts the
view up (pitch), ω_z > 0 rolls clockwise as seen by the camera.

Motion time `t` is seconds relative to the first frame of a simulation (negative before it), and
every motion is defined for all t. Specs for the CLI (angles in degrees, rates in °/s):

    static                      no motion
    pan:50[:yaw|pitch|roll]     constant rate (default axis yaw)
    roll:30                     constant roll rate (same as pan:30:roll)
    slew:90[:axis[:ramp_s[:hold_s]]]  gimbal slew: smooth ramp 0→90 °/s, hold, ramp back to 0
    shake:2                     hand-held shake, 2° RMS angle (1–12 Hz, 1/f), seeded
    vibration[:rms[:hz]]        vehicle vibration, RMS rate °/s around a fundamental + harmonics
    sway[:deg[:period_s]]       smooth periodic sway that returns exactly to its start
    log[:start_s]               replay of the real Betaflight gyro log (see GyroLog)
    multirotor[:roll_rms]       multirotor attitude motion, roll-dominant, RMS roll rate °/s (default 60)
    static:0.3+pan:50           sequence: each part but the last takes a duration (…:D or static:D)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit

from thermod.errors import ThermodError
from thermod.physics.geometry import integrate_rotations, jit_cores, trapezoid_step_into

DEG = math.pi / 180.0
AXES = {"pitch": 0, "x": 0, "yaw": 1, "y": 1, "roll": 2, "z": 2}


class Motion:
    """Base class: `omega(t)` → [n, 3] camera-frame rad/s at motion times t (s)."""

    spec: str = "?"

    def omega(self, t) -> np.ndarray:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.spec!r})"


@dataclass(repr=False)
class Static(Motion):
    spec: str = "static"

    def omega(self, t):
        return np.zeros((np.size(t), 3))


@dataclass(repr=False)
class Pan(Motion):
    """Constant rate ω (rad/s, camera frame)."""

    rate: tuple = (0.0, 50 * DEG, 0.0)
    spec: str = "pan"

    def omega(self, t):
        return np.broadcast_to(np.asarray(self.rate, float), (np.size(t), 3)).copy()


def pan(deg_s: float = 50.0, axis: str = "yaw") -> Pan:
    r = np.zeros(3)
    r[_axis(axis)] = deg_s * DEG
    return Pan(tuple(r), spec=f"pan:{deg_s:g}:{axis}")


@dataclass(repr=False)
class Slew(Motion):
    """Gimbal slew: raised-cosine ramp 0 → peak over `ramp_s`, hold, ramp back down (finite jerk)."""

    peak: float = 90 * DEG
    axis: int = 1
    ramp_s: float = 0.25
    hold_s: float = 0.5
    start_s: float = 0.0
    spec: str = "slew"

    def omega(self, t):
        t = np.atleast_1d(np.asarray(t, float)) - self.start_s
        r, h = self.ramp_s, self.hold_s
        up = 0.5 - 0.5 * np.cos(np.pi * np.clip(t / r, 0, 1))
        down = 0.5 - 0.5 * np.cos(np.pi * np.clip((r + h + r - t) / r, 0, 1))
        prof = np.where(t < r + h, up, down)
        out = np.zeros((t.size, 3))
        out[:, self.axis] = self.peak * prof
        return out


def slew(deg_s: float = 90.0, axis: str = "yaw", ramp_s: float = 0.25, hold_s: float = 0.5) -> Slew:
    return Slew(deg_s * DEG, _axis(axis), ramp_s, hold_s, spec=f"slew:{deg_s:g}:{axis}:{ramp_s:g}:{hold_s:g}")


@dataclass(repr=False)
class SumOfSines(Motion):
    """θ_a(t) = Σ A sin(2πft + φ) per axis, so ω_a = Σ 2πf A cos(2πft + φ) (small angles: ω ≈ θ̇)."""

    freqs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    amps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))     # rad (angle amplitude)
    phases: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    spec: str = "sines"

    def omega(self, t):
        t = np.atleast_1d(np.asarray(t, float))[:, None, None]
        w = 2 * np.pi * self.freqs
        return (w * self.amps * np.cos(w * t + self.phases)).sum(axis=1)


def shake(deg_rms: float = 2.0, seed: int = 0, n: int = 24) -> SumOfSines:
    """Hand-held shake: 1–12 Hz tremor with a 1/f angle spectrum; yaw and pitch at `deg_rms` RMS
    angle, roll at half of it. Seeded, so the same spec always gives the same motion."""
    rng = np.random.default_rng([seed, 1])
    f = np.exp(rng.uniform(np.log(1.0), np.log(12.0), (n, 3)))
    a = 1.0 / f
    a *= np.sqrt(2.0 / (a**2).sum(axis=0))                           # unit RMS angle per axis
    a *= deg_rms * DEG * np.array([1.0, 1.0, 0.5])
    return SumOfSines(f, a, rng.uniform(0, 2 * np.pi, (n, 3)), spec=f"shake:{deg_rms:g}")


def vibration(rms_deg_s: float = 10.0, hz: float = 45.0, seed: int = 0) -> SumOfSines:
    """Vehicle vibration: a fundamental `hz` (engine/rotor) with harmonics 2–4 and a spread of
    jittered lines around them; `rms_deg_s` RMS rate per axis (roll strongest)."""
    rng = np.random.default_rng([seed, 2])
    base = np.repeat(np.array([1.0, 2.0, 3.0, 4.0]), 4)
    f = (base * hz)[:, None] * rng.uniform(0.97, 1.03, (base.size, 3))
    w_rms = (1.0 / base)[:, None] * np.ones((1, 3))
    w_rms *= np.sqrt(2.0 / (w_rms**2).sum(axis=0))                  # unit RMS rate per axis
    w_rms *= rms_deg_s * DEG * np.array([0.8, 0.6, 1.0])
    amps = w_rms / (2 * np.pi * f)
    return SumOfSines(f, amps, rng.uniform(0, 2 * np.pi, f.shape), spec=f"vibration:{rms_deg_s:g}:{hz:g}")


@dataclass(repr=False)
class Sway(Motion):
    """Periodic orientation R(t) = exp([θ(t)]×), θ_a = A_a sin(2πt/T + φ_a): exactly back at the
    start after every period T (what a looping playback needs). ω = J_r(θ) θ̇."""

    amp: tuple = (1.0 * DEG, 2.0 * DEG, 0.5 * DEG)
    period_s: float = 2.0
    phase: tuple = (0.5 * np.pi, 0.0, 0.25 * np.pi)
    spec: str = "sway"

    def theta(self, t):
        t = np.atleast_1d(np.asarray(t, float))[:, None]
        return np.asarray(self.amp) * np.sin(2 * np.pi * t / self.period_s + np.asarray(self.phase))

    def omega(self, t):
        t = np.atleast_1d(np.asarray(t, float))[:, None]
        w = 2 * np.pi / self.period_s
        th = np.asarray(self.amp) * np.sin(w * t + np.asarray(self.phase))
        thd = np.asarray(self.amp) * w * np.cos(w * t + np.asarray(self.phase))
        n = np.linalg.norm(th, axis=1, keepdims=True)
        small = n < 1e-6
        n = np.where(small, 1.0, n)
        c1 = np.where(small, 0.5, (1 - np.cos(n)) / n**2)
        c2 = np.where(small, 1.0 / 6, (n - np.sin(n)) / n**3)
        cr = np.cross(th, thd)
        # Right Jacobian of SO(3): J_r = I − c1 [θ]× + c2 [θ]×²
        return thd - c1 * cr + c2 * np.cross(th, cr)


def sway(deg: float = 2.0, period_s: float = 2.0) -> Sway:
    return Sway((0.5 * deg * DEG, deg * DEG, 0.25 * deg * DEG), period_s, spec=f"sway:{deg:g}:{period_s:g}")


@dataclass(repr=False)
class GyroLog(Motion):
    """Replay of a real gyro log (time_us, roll, pitch, yaw in °/s), piecewise linear in time.

    Body axes are taken as aerospace FRD (x forward, y right, z down) with a forward-looking camera,
    so camera x (right) = body pitch axis, camera y (down) = body yaw axis, camera z (forward) =
    body roll axis: ω_cam = (pitch, yaw, roll). Motion time 0 is `start_s` into the log; outside
    the log the first/last rate is held.
    """

    t_log: np.ndarray = field(default_factory=lambda: np.zeros(1))
    w_cam: np.ndarray = field(default_factory=lambda: np.zeros((1, 3)))
    start_s: float = 0.0
    spec: str = "log"

    def omega(self, t):
        tq = np.atleast_1d(np.asarray(t, float)) + self.start_s
        return np.stack([np.interp(tq, self.t_log, self.w_cam[:, a]) for a in range(3)], axis=1)


def default_log_path() -> Path | None:
    from thermod.sim.scenes import shared_data_dir
    d = shared_data_dir()
    p = d / "gyro" / "betaflight_smooth_2khz.csv" if d else None
    return p if p and p.exists() else None


def load_gyro_log(path: str | os.PathLike | None = None, start_s: float = 0.0) -> GyroLog:
    """Read a Betaflight-style CSV (time_us, roll/pitch/yaw °/s, …), skipping the leading junk rows
    whose time base differs: the log starts at the first row after which time increases in
    steady 0.1–5 ms steps."""
    path = Path(path) if path is not None else default_log_path()
    if path is None or not path.exists():
        raise ThermodError(f"motion log: gyro log {path or 'shared/data/gyro/betaflight_smooth_2khz.csv'} "
                           "not found (set THERMOD_SHARED_DATA)")
    try:
        d = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=(0, 1, 2, 3))
    except (OSError, ValueError) as e:
        raise ThermodError(f"{path}: not a CSV with time_us,roll,pitch,yaw columns ({e})") from None
    if d.ndim != 2 or d.shape[0] < 10 or not np.all(np.isfinite(d)):
        raise ThermodError(f"{path}: expected ≥ 10 numeric rows of time_us,roll,pitch,yaw")
    dt = np.diff(d[:, 0])
    good = (dt > 100) & (dt < 5000)
    bad = np.flatnonzero(~good)
    first = int(bad[bad < len(dt) // 2].max() + 1) if np.any(bad < len(dt) // 2) else 0
    d = d[first:]
    keep = np.r_[True, np.diff(d[:, 0]) > 0]                       # drop any later repeats
    d = d[keep]
    t = (d[:, 0] - d[0, 0]) * 1e-6
    roll, pitch, yaw = d[:, 1], d[:, 2], d[:, 3]
    w = np.stack([pitch, yaw, roll], axis=1) * DEG
    if not 0 <= start_s < t[-1]:
        raise ThermodError(f"motion log:{start_s:g}: start must be within the log's 0–{t[-1]:.1f} s")
    return GyroLog(t, w, float(start_s), spec=f"log:{start_s:g}")


@dataclass(repr=False)
class Sequence(Motion):
    """Parts played one after another: part i covers motion time [start_i, start_i + dur_i),
    each evaluated in its own local time (0 at its start); the first part extends back before 0
    and the last part forever.

    The rate is continuous across a boundary: over the next part's first `blend_s` its rate is
    cross-faded from the previous part's (raised cosine). A real body cannot step its angular
    velocity (that takes infinite torque), and a sampled gyro cannot represent a step: interpolated
    linearly between 1 kHz samples, a step Δω leaves ½·Δω·Δt of attitude error (0.4 mrad for a
    50 °/s pan starting between samples), which any fit would then take for a time offset or a bias.
    """

    parts: list = field(default_factory=list)        # [(Motion, duration_s or None for the last)]
    spec: str = "sequence"
    blend_s: float = 0.03

    def omega(self, t):
        t = np.atleast_1d(np.asarray(t, float))
        out = np.zeros((t.size, 3))
        start = prev_start = 0.0
        for i, (m, dur) in enumerate(self.parts):
            last = i == len(self.parts) - 1
            sel = (t >= start if i else np.ones(t.size, bool)) & (True if last else t < start + dur)
            if np.any(sel):
                out[sel] = m.omega(t[sel] - start)
                if i and self.blend_s > 0:
                    u = (t[sel] - start) / self.blend_s
                    ramp = u < 1.0
                    if np.any(ramp):
                        s = 0.5 - 0.5 * np.cos(np.pi * u[ramp])[:, None]
                        prev = self.parts[i - 1][0].omega(t[sel][ramp] - prev_start)
                        out[np.flatnonzero(sel)[ramp]] = (1.0 - s) * prev + s * out[sel][ramp]
            if not last:
                prev_start = start
                start += dur
        return out


def static() -> Static:
    return Static()


def gyro_log(path: str | os.PathLike | None = None, start_s: float = 0.0) -> GyroLog:
    """The real gyro log (default shared/data/gyro/betaflight_smooth_2khz.csv) from `start_s`."""
    return load_gyro_log(path, start_s)


def sequence(parts: list[tuple[Motion, float | None]]) -> Sequence:
    """[(motion, duration_s), …, (last_motion, None)] played one after another."""
    if not parts or any(d is None or d <= 0 for _, d in parts[:-1]):
        raise ThermodError("motion sequence: every part but the last needs a duration > 0")
    return Sequence(list(parts), spec="+".join(m.spec for m, _ in parts))


def parse(spec: str | Motion, seed: int = 0) -> Motion:
    """Parse a motion spec ("pan:50", "static:0.3+pan:50", …); bad specs raise ThermodError."""
    if isinstance(spec, Motion):
        return spec
    if not isinstance(spec, str) or not spec.strip():
        raise ThermodError(f"--motion: expected a spec like 'pan:50', got {spec!r}")
    parts = [p.strip() for p in spec.split("+")]
    if len(parts) == 1:
        return _parse_one(parts[0], seed)[0]
    seq = []
    for i, p in enumerate(parts):
        m, dur = _parse_one(p, seed + i, want_duration=i < len(parts) - 1)
        seq.append((m, dur))
    return Sequence(seq, spec=spec)


def _parse_one(p: str, seed: int, want_duration: bool = False):
    name, *args = p.split(":")
    name = name.strip().lower()
    try:
        nums = [a for a in args]
        if name == "static":
            dur = float(nums[0]) if nums else None
            if want_duration and dur is None:
                raise ThermodError(f"--motion {p!r}: a static part inside a sequence needs a duration "
                                   "(static:SECONDS)")
            return Static(spec=p), dur
        if want_duration:
            # every non-final part of a sequence ends with its duration: pan:50:yaw:0.5 or pan:50:0.5
            if len(args) < 2:
                raise ThermodError(f"--motion {p!r}: a part inside a sequence needs its rate and a duration "
                                   "as the last field (e.g. pan:50:0.5 or pan:50:roll:0.5)")
            dur = float(args[-1])
            args = args[:-1]
        else:
            dur = None
        if name in ("pan", "roll", "tilt"):
            axis = {"pan": "yaw", "roll": "roll", "tilt": "pitch"}[name]
            rate = float(args[0]) if args else 50.0
            if len(args) > 1:
                axis = args[1]
            return pan(rate, axis), dur
        if name == "slew":
            vals = args + [None] * 4
            return slew(float(vals[0]) if vals[0] else 90.0, vals[1] or "yaw",
                        float(vals[2]) if vals[2] else 0.25, float(vals[3]) if vals[3] else 0.5), dur
        if name == "shake":
            return shake(float(args[0]) if args else 2.0, seed), dur
        if name in ("vibration", "vib"):
            return vibration(float(args[0]) if args else 10.0, float(args[1]) if len(args) > 1 else 45.0,
                             seed), dur
        if name == "sway":
            return sway(float(args[0]) if args else 2.0, float(args[1]) if len(args) > 1 else 2.0), dur
        if name == "log":
            return load_gyro_log(None, float(args[0]) if args else 0.0), dur
        if name == "multirotor":
            return multirotor(float(args[0]) if args else 60.0, seed), dur
    except (ValueError, IndexError) as e:
        raise ThermodError(f"--motion {p!r}: bad number ({e}); expected e.g. pan:50, slew:90:yaw, "
                           "shake:2, vibration:10:45, log:5, static:0.3+pan:50") from None
    except KeyError as e:
        raise ThermodError(f"--motion {p!r}: unknown axis {e}; expected yaw, pitch or roll") from None
    raise ThermodError(f"--motion {p!r}: unknown motion {name!r}; expected static, pan, roll, tilt, "
                       "slew, shake, vibration, sway, log or multirotor")


def _axis(a: str) -> int:
    return AXES[a.strip().lower()]


# --------------------------------------------------------------------------- orientation R(t)

jit_cores()   # the geometry's scalar cores, callable from _interp_R


@njit(cache=True, nogil=True)
def _interp_R(Rg, wg, g0, dt, tq):
    """R at times tq between grid points: a partial trapezoid step from the grid point before."""
    out = np.empty((tq.size, 3, 3))
    n = Rg.shape[0]
    w = np.empty(3)
    E = np.empty((3, 3))
    for k in range(tq.size):
        i = min(max(int(math.floor((tq[k] - g0) / dt)), 0), n - 2)
        s = tq[k] - (g0 + i * dt)
        f = s / dt
        for a in range(3):
            w[a] = wg[i, a] + f * (wg[i + 1, a] - wg[i, a])   # ω linear on the interval
        trapezoid_step_into(Rg[i], wg[i], w, s, E, out[k])
    return out


class Trajectory:
    """Orientation R(t) of a motion over absolute times [t_start, t_end], with R(t_ref) = I.

    Motion time is `t − t_ref`. ω is sampled on a uniform grid (`dt`, default 50 µs, coarsened for
    spans over 200 s to keep the grid ≤ 4 M points) and integrated with
    `thermod.physics.geometry.integrate_rotations`: the same rate semantics as the renderers.
    """

    def __init__(self, motion: Motion, t_ref: float, t_start: float, t_end: float, dt: float = 5e-5):
        if not t_start <= t_ref <= t_end:
            t_start, t_end = min(t_start, t_ref), max(t_end, t_ref)
        dt = max(dt, (t_end - t_start) / 4e6)
        self.motion, self.t_ref, self.dt = motion, float(t_ref), float(dt)
        n0 = int(math.ceil((t_ref - t_start) / dt)) + 2
        n1 = int(math.ceil((t_end - t_ref) / dt)) + 2
        self.g0 = t_ref - n0 * dt
        tg = self.g0 + dt * np.arange(n0 + n1 + 1)
        self.wg = np.ascontiguousarray(motion.omega(tg - t_ref), dtype=np.float64)
        if not np.all(np.isfinite(self.wg)):
            raise ThermodError(f"motion {motion.spec!r}: ω(t) is not finite")
        self.Rg = integrate_rotations(tg, self.wg, tg[n0])   # R(t_ref) = I
        self.t_start, self.t_end = float(tg[0]), float(tg[-1])

    def omega(self, t) -> np.ndarray:
        """True camera-frame rate (rad/s) at absolute times t."""
        return self.motion.omega(np.asarray(t, float) - self.t_ref)

    def R(self, t) -> np.ndarray:
        """R(t) (camera → world, world = the camera at t_ref) for absolute times t, [n, 3, 3]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return _interp_R(self.Rg, self.wg, self.g0, self.dt, np.ascontiguousarray(t))

    def max_rate(self, t0: float, t1: float) -> np.ndarray:
        """Peak |ω| per axis over [t0, t1] (sampled at the grid resolution)."""
        i0 = max(int((t0 - self.g0) / self.dt) - 1, 0)
        i1 = min(int((t1 - self.g0) / self.dt) + 2, len(self.wg))
        return np.abs(self.wg[i0:i1]).max(axis=0)


# --------------------------------------------------------------------------- appended motions
# Rate proportions of the real Betaflight log (shared/data/gyro/betaflight_smooth_2khz.csv, 39 s of
# flight): RMS roll 61, pitch 43, yaw 14 °/s; half its rate power lies below ~1 Hz, 90 % below ~2 Hz.
MULTIROTOR_AXIS_SHARE = (0.70, 0.23, 1.0)      # (pitch, yaw, roll) RMS rate relative to roll
MULTIROTOR_BAND_HZ = (1.0, 4.0)


def multirotor(roll_deg_s: float = 60.0, seed: int = 0, n: int = 5) -> SumOfSines:
    """Multirotor attitude motion, procedural and seeded (no data needed): roll dominates, as in
    flight. `roll_deg_s` is the RMS roll rate; pitch and yaw follow the real log's proportions
    (`MULTIROTOR_AXIS_SHARE`). `n` lines per axis, geometrically spaced over 1–4 Hz (the attitude
    loop's corrections; a 2 s loop keeps them distinct after snapping to whole cycles), each with
    the same rate amplitude and a seeded phase: a flat rate spectrum, roll angles of ~8° RMS.

    Roll (ω_z) turns the image about the principal point, so the blur grows with the distance from
    it: the motion that makes spatially varying deblurring matter. A sum of sines: a looping
    playback snaps its frequencies to whole cycles per loop (`thermod.sim.playback.loop_motion`).
    """
    if not roll_deg_s >= 0:
        raise ThermodError(f"motion multirotor:{roll_deg_s}: expected an RMS roll rate ≥ 0 °/s")
    rng = np.random.default_rng([seed, 3])
    lo, hi = MULTIROTOR_BAND_HZ
    f = np.repeat(np.geomspace(lo, hi, n)[:, None], 3, axis=1)
    rate_amp = np.full((n, 3), math.sqrt(2.0 / n))                 # unit RMS rate per axis
    rate_amp *= roll_deg_s * DEG * np.asarray(MULTIROTOR_AXIS_SHARE)
    return SumOfSines(f, rate_amp / (2 * np.pi * f), rng.uniform(0, 2 * np.pi, (n, 3)),
                      spec=f"multirotor:{roll_deg_s:g}")


def flight(rms_deg_s: tuple = (8.0, 15.0, 12.0), seed: int = 0, n: int = 12) -> SumOfSines:
    """Multirotor-like flight attitude: pitch, yaw and roll rates (`rms_deg_s`, camera x, y, z) from sums
    of sines between 0.3 and 6 Hz (slow manoeuvres to gusts, rate spectrum falling as 1/√f), moving
    from t = −∞ (no static lead-in). Seeded, so the same arguments always give the same motion."""
    rng = np.random.default_rng([seed, 3])
    f = np.exp(rng.uniform(np.log(0.3), np.log(6.0), (n, 3)))
    w_rms = 1.0 / np.sqrt(f)
    w_rms *= np.sqrt(2.0 / (w_rms**2).sum(axis=0))                  # unit RMS rate per axis
    w_rms *= np.asarray(rms_deg_s, float) * DEG
    amps = w_rms / (2 * np.pi * f)
    spec = "flight:" + ":".join(f"{r:g}" for r in rms_deg_s)
    return SumOfSines(f, amps, rng.uniform(0, 2 * np.pi, (n, 3)), spec=spec)


class Summed(Motion):
    """Several motions at once, their rates added (a flight attitude plus a rotor vibration)."""

    def __init__(self, *parts: Motion):
        if not parts:
            raise ThermodError("summed motion: expected at least one part")
        self.parts, self.spec = parts, "+".join(p.spec for p in parts)

    def omega(self, t):
        return sum(p.omega(t) for p in self.parts)
