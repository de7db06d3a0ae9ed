"""Flight-like simulator recordings with no static lead-in, for the discrepancy tests (tests/calib) and
benchmarks; no pytest here.

`flight_recording(effects, seconds, size, seed, real_log)` renders with the simulator's independent
fine-time renderer (`thermod.sim.synth.simulate`, never `thermod.calib.forward`) a camera that is
moving from before its first frame: the real Betaflight gyro log (`sim.motion.gyro_log`, from
``seed``·0.7 s into it) when `real_log`, else the synthetic multirotor attitude `sim.motion.flight`
(pitch/yaw/roll 8/15/12 °/s RMS), so a bare clone runs too. NETD 50 mK unless `effects` says
otherwise; the scene is the seeded procedural texture.

`REAL_LOG` says whether the log is there (../shared/data); the hidden-effect tests use it when it is
(`flight(...)`), so they run on real flight motion here and on the synthetic one on a bare clone;
their thresholds hold on both (each test says what was measured on which).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.io.recording import Recording
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim.synth import simulate, truth_calibration

REAL_LOG = mo.default_log_path() is not None
SIZE = (160, 120)          # frames; analysed at full resolution (at 80×60 the texture's detail is
WORK_WIDTH = 160           # averaged away: the noise floor doubles against the motion signal)
SECONDS = 0.4              # 20 frames at 50 Hz


@dataclass
class FlightRecording:
    rec: Recording
    nominal: Calibration       # what the file's attributes claim (the model under test)
    truth: Calibration         # what the world was rendered with


def nominal_calibration(size=(160, 120)) -> Calibration:
    """The paper's camera scaled to `size` (width, height): same field of view, fewer pixels."""
    w, h = size
    intr = Calibration().intrinsics.scaled(w / Calibration().width)
    return Calibration(width=w, height=h, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy)


def log_motion(path, start_s: float) -> mo.GyroLog:
    """The attitude of a flight-controller log (`thermod.io.flightlog`: Betaflight blackbox, PX4 ULog, …)
    from `start_s` into it, seen by a forward-looking upright camera (`FORWARD_CAMERA_FROM_FRD`)."""
    from thermod.io.flightlog import FORWARD_CAMERA_FROM_FRD, read_flight_log

    fl = read_flight_log(path)
    t = fl.t - fl.t[0]
    if not 0 <= start_s < t[-1]:
        raise ValueError(f"{path}: start {start_s:g} s is outside the log's 0–{t[-1]:.1f} s")
    return mo.GyroLog(t, fl.rate @ FORWARD_CAMERA_FROM_FRD.T, float(start_s), spec=f"{path}:{start_s:g}")


def flight_motion(seed: int = 0, real_log: bool = False, vibration_deg_s: float = 0.0,
                  log_start_s: float | None = None, log=None) -> mo.Motion:
    """The flight attitude (module docstring), plus a 10 Hz rotor vibration of `vibration_deg_s` RMS
    (harmonics to 40 Hz: the broadband content a gyro low-pass needs to be told from a delay).
    `log_start_s`: where in the real log the flight starts (default 0.7·seed + 1.0 s); `log`: another
    flight-controller log to take it from (`log_motion`) instead of the Betaflight CSV."""
    start = 0.7 * seed + 1.0 if log_start_s is None else log_start_s
    if log is not None:
        m = log_motion(log, start)
    else:
        m = mo.gyro_log(None, start_s=start) if real_log else mo.flight(seed=seed)
    return mo.Summed(m, mo.vibration(vibration_deg_s, 10.0, seed)) if vibration_deg_s else m


def flight_recording(effects: dict | None = None, seconds: float = 0.4, size=(160, 120), seed: int = 0,
                     real_log: bool = False, scene="texture",
                     vibration_deg_s: float = 0.0, log_start_s: float | None = None,
                     log=None) -> FlightRecording:
    """A recording of `seconds` at `size` with hidden `effects` (the simulator's vocabulary) and flight
    motion (see the module docstring; `log`: a flight-controller log's instead, `log_motion`); returns
    it with its nominal and true calibrations."""
    nominal = nominal_calibration(size)
    motion = flight_motion(seed, real_log, vibration_deg_s, log_start_s, log)
    rec = simulate(scene, motion, seconds, nominal, {"netd": 0.05, **(effects or {})}, seed=seed)
    return FlightRecording(rec, nominal, truth_calibration(rec))


def flight(effects: dict | None = None, **kw) -> FlightRecording:
    """`flight_recording` at the tests' SIZE and SECONDS, on the real log when it is there."""
    kw = {"seconds": SECONDS, "size": SIZE, "real_log": REAL_LOG, **kw}
    return flight_recording(effects, **kw)


def clipping_range(motion: mo.Motion, seconds: float, fraction: float = 0.7, fps: float = 50.0) -> float:
    """A gyro range (rad/s) at `fraction` of `motion`'s peak rate while a recording of `seconds` at
    `fps` is exposed (its first frame's 5τ history to its last frame), so the clipped swings are
    ones the frames see."""
    t = np.arange(-0.05, seconds - 1.0 / fps + 1e-9, 1e-3)
    return round(fraction * float(np.abs(motion.omega(t)).max()), 3)


def excess(gap: float, floor: float) -> float:
    """Gap above the noise floor (what an effect can remove)."""
    return math.sqrt(max(gap * gap - floor * floor, 0.0))


_CACHE: dict = {}


def analysed(key: str, effects: dict | None = None, edit=None, **kw):
    """(FlightRecording, analysis) of `flight(effects, **kw)` (then `edit(rec)` if given) analysed at
    WORK_WIDTH with every candidate, computed once per test process."""
    from thermod.calib import discrepancy as D

    if key not in _CACHE:
        fr = flight(effects, **kw)
        if edit is not None:
            fr.rec = edit(fr.rec)
        d = D.prepare(fr.rec, fr.nominal, name=key, work_width=WORK_WIDTH)
        _CACHE[key] = (fr, D.analyse([d], D.Model(fr.nominal)))
    return _CACHE[key]


def high_contrast_scene(calib: Calibration, shape=None, scene="texture"):
    """The seeded scene stretched to a 30 K span (1–99 %: a hot vehicle on a cool field) on the sphere
    at `calib`'s angular pixel size; `shape` (rows, cols) of the texture, twice the frame by default
    (as the simulator makes its procedural scenes). Blur then mixes very different levels."""
    from thermod.sim import detector as sim_detector
    from thermod.sim import scenes as sim_scenes

    tex = sim_scenes.load_scene(scene, shape or (2 * calib.height, 2 * calib.width), 0)
    m = float(np.median(tex))
    lo, hi = np.percentile(tex, [1, 99])
    t2 = (m + (tex - m) * (30.0 * 40.0 / (hi - lo))).astype(np.float32)
    return sim_detector.SphereScene(t2, calib.fx, calib.fy)


def vignetting_drift(rec: Recording, corner_loss: float, t_from: float) -> Recording:
    """`rec` with a vignetting that grows linearly from `t_from` to `corner_loss` (fraction of the
    signal lost in the corners) at the end — a lens barrel warming up; not in the vocabulary. The
    noiseless render is darkened, the same noise realisation added back."""
    clean = rec.extras["truth/blurry_noiseless"]
    noise = rec.frames.astype(np.float32) - clean
    h, w = clean.shape[1:]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    frames = rec.frames.copy()
    t1 = rec.t[-1]
    for k in np.flatnonzero(rec.t >= t_from):
        a = corner_loss * (rec.t[k] - t_from) / (t1 - t_from)
        frames[k] = np.clip(np.rint(clean[k] * (1 - a * r2) + noise[k]), 0, 65535).astype(np.uint16)
    rec.frames = frames
    return rec


def assert_named_from_flight(hidden: str, effects: dict, candidates, check, *, seconds: float = 1.0,
                             size=(640, 480), work_width: int = 160, vibration_deg_s: float = 0.0) -> None:
    """`hidden` ("effect" or "effect@start_s") simulated on the real log's attitude from `start_s` (1.0
    by default), analysed motion-only among `candidates`: the effect is named first, `check(ana,
    fitted_calib, true_calib)` holds, the gap's excess over the floor is at least halved and nothing is
    left unexplained."""
    from thermod.calib import discrepancy as D

    effect, _, start = hidden.partition("@")
    fr = flight_recording(effects, seconds=seconds, size=size, real_log=True, vibration_deg_s=vibration_deg_s,
                          log_start_s=float(start) if start else None)
    d = D.prepare(fr.rec, fr.nominal, name=hidden, work_width=work_width)
    ana = D.analyse([d], D.Model(fr.nominal), candidates=candidates)
    assert ana.reference == "motion", ana.reference
    assert ana.named[:1] == [effect], ana.named
    assert check(ana, ana.model.calib, fr.truth), ana.steps
    left, before = excess(ana.gap_final, ana.noise_floor), excess(ana.gap_initial, ana.noise_floor)
    assert left <= 0.5 * before, (ana.gap_initial, ana.gap_final, ana.noise_floor)
    assert not ana.unexplained, (ana.gap_final, ana.noise_floor)
