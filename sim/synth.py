"""`simulate(...)`: a complete recording (frames + raw gyro) with known, hidden truth.

The rule it keeps: the file's attributes carry the NOMINAL calibration (what the user believes); the
named `effects` change the TRUTH the world is rendered with — the vocabulary the discrepancy workflow
has to explain: ``time_offset``, ``rolling_readout``, ``gyro_bias``, ``gyro_scale``, ``misalignment``,
``time_constant``, ``optical_psf``, ``netd``, ``fpn``, ``gain_nonuniformity``, ``quantisation_bits``,
``detector_nonlinearity``, ``gyro_noise``, ``clock_drift``, ``gyro_lowpass``, ``gyro_saturation``,
``parallax`` and ``ffc_event`` (units, meanings and value syntax: docs/design.md §8, "The
simulator's effects"; `clock_drift_ppm` and `gyro_lowpass_hz` are older names).

The truth goes to `extra_attrs["truth"]` (true calibration attributes, effects, specs) and
`extras["truth/..."]`: `frames` (the sharp view at each frame time, no PSF), `blurry_noiseless`,
under rolling readout `frames_rolling` (each row's sharp view at its own read time),
`gyro_t_camera` and `gyro_omega_camera` (true sampling instants on the camera clock and the true
camera rate there) and `frame_R` (R(t_k), camera→world, world = the camera at the first frame).
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Mapping
from contextlib import contextmanager

import numpy as np

from thermod.errors import ThermodError
from thermod.io.recording import Recording
from thermod.physics.calibration import Calibration
from thermod.physics.detector import default_photon_exposure_s
from thermod.physics.effects import EFFECTS, canonical
from thermod.sim import detector as det
from thermod.sim import motion as mo
from thermod.sim import scenes
from thermod.sim.gyro_model import DEG, GyroErrorModel
from thermod.sim.parallax import NearGround

MAX_BYTES = 6e9          # the whole recording is built in memory


def check_effects(effects: Mapping | None) -> dict:
    """Validate effect names and values; returns {name: float or 3-tuple}."""
    out = {}
    for name, v in dict(effects or {}).items():
        name = canonical(name)
        if name not in EFFECTS:
            raise ThermodError(f"--effect {name}: unknown effect; known: {', '.join(EFFECTS)}")
        a = np.asarray(v, dtype=np.float64).ravel() if not isinstance(v, str) else None
        if a is None or not np.all(np.isfinite(a)):
            raise ThermodError(f"--effect {name}={v!r}: expected a finite number")
        sizes = EFFECTS[name].sizes
        if a.size not in sizes:
            raise ThermodError(f"--effect {name}: expected {' or '.join(map(str, sizes))} value(s), "
                               f"got {a.size}")
        out[name] = float(a[0]) if a.size == 1 else tuple(float(x) for x in a)
    for name in ("rolling_readout", "time_constant", "optical_psf", "netd", "fpn", "gain_nonuniformity",
                 "gyro_noise"):
        if name in out and out[name] < 0:
            raise ThermodError(f"--effect {name}={out[name]}: must be ≥ 0")
    _check_gyro_effects(out)
    if "gyro_scale" in out and np.any(np.asarray(out["gyro_scale"]) <= 0):
        raise ThermodError(f"--effect gyro_scale={out['gyro_scale']}: must be > 0")
    if "detector_nonlinearity" in out and abs(out["detector_nonlinearity"]) > 1:
        raise ThermodError(f"--effect detector_nonlinearity={out['detector_nonlinearity']}: expected |c| ≤ 1 "
                           "(c = 1: +100 % response 1000 counts above the level)")
    if "ffc_event" in out:
        _ffc_event(out).validate()
    if "parallax" in out:
        NearGround(*out["parallax"])
    return out


def _ffc_event(fx: Mapping) -> det.FFCEvent | None:
    """The `ffc_event` effect (T_START, DURATION[, STEP_COUNTS]) as a detector `FFCEvent`, or None."""
    if "ffc_event" not in fx:
        return None
    return det.FFCEvent(*(float(v) for v in fx["ffc_event"]))


def true_calibration(nominal: Calibration, effects: Mapping, t_anchor: float = 0.0) -> Calibration:
    """The calibration the world is rendered with: the nominal one changed by the effects (a clock
    drift agrees with the camera clock at camera time `t_anchor`)."""
    c = nominal
    if "time_offset" in effects:
        c = c.replace(time_offset_s=c.time_offset_s + effects["time_offset"])
    if "rolling_readout" in effects:
        c = c.replace(readout_s=effects["rolling_readout"])
    if "gyro_bias" in effects:
        b = np.asarray(c.bias_rad_s, float) + np.broadcast_to(np.asarray(effects["gyro_bias"], float), (3,))
        c = c.replace(bias_rad_s=tuple(float(x) for x in b))
    if "gyro_scale" in effects:
        s = c.scale_vector * np.broadcast_to(np.asarray(effects["gyro_scale"], float), (3,))
        c = c.replace(scale=tuple(float(x) for x in s))
    if "misalignment" in effects:
        c = c.with_misalignment(effects["misalignment"])
    if "time_constant" in effects:
        c = c.replace(tau_s=effects["time_constant"])
    if "optical_psf" in effects:
        c = c.with_psf_sigma_px(effects["optical_psf"]) if effects["optical_psf"] > 0 else c
    return _true_gyro_effects(c, effects, t_anchor)


def simulate(scene="texture", motion="pan:50", seconds: float = 1.0, calib: Calibration | None = None,
             effects: Mapping | None = None, seed: int = 0, frame_rate: float | None = None,
             gyro: GyroErrorModel | None = None, progress: bool = False, *, kind: str = "thermal",
             exposure_s: float | None = None, step_px: float = 0.5, history_tau: float = 8.0,
             t0: float = 100.0, truth: bool = True, method: str = "fine", compression: float = 20.0,
             slow_fps: float = 50.0, movers=()) -> Recording:
    """Simulate a recording (format v1 `Recording`) of `seconds` at `frame_rate` (default the
    calibration's) of `scene` (spec, array or `detector.SphereScene`) under `motion` (spec or
    `motion.Motion`; motion time 0 = the first frame, read at host-like time `t0`).

    The gyro (`gyro`, default ideal; `GyroErrorModel.paper()` for Table 1) covers at least 0.1 s and
    the `history_tau`·τ history before the first frame (so its 5τ kernel is complete) and 50 ms
    after the last. Random streams are seeded: scene, motion, sensor noise and gyro noise all follow
    `seed`. kind="photon" renders a box-exposure detector (Eq. 2) for comparisons.
    `truth=False` leaves out the float32 truth stacks (smaller files).
    method="time_compression": the paper's synthesis instead of the fine-time renderer — sharp views
    of a slow camera (`slow_fps`, motion `compression`× slower) re-timed into the fast motion
    (`detector.render_time_compressed`); thermal detector only, no rolling readout.
    `movers`: `thermod.sim.movers.HotObject`s, warm bodies moving in the world (fine-time renderer).
    `progress`: True for a progress bar, or a callable(frames rendered) called after each frame (an
    exception it raises ends the simulation).
    """
    _check_method(method, kind, effects)
    nominal = _nominal_calibration(calib, frame_rate)
    fps = float(nominal.frame_rate_hz)
    n = _frame_count(seconds, nominal)
    fx = check_effects(effects)
    t_frames = t0 + np.arange(n) / fps
    truth_cal = true_calibration(nominal, fx, t_anchor=float(t_frames[0]))
    psf_sigma = fx.get("optical_psf", nominal.psf_sigma_px)
    gyro = _gyro_with_effects(gyro or GyroErrorModel(), fx)
    sensor = _sensor_effects(fx)

    mot = mo.parse(motion, seed)
    sc = _sphere_scene(scene, truth_cal, seed)
    traj, gyro_lo, gyro_hi = _trajectory(mot, t_frames, truth_cal, kind, exposure_s, history_tau)
    hook = contextlib.nullcontext(progress) if callable(progress) else _progress_bar(n if progress else 0)
    with hook as bar:
        if method == "fine":
            par = (NearGround(*fx["parallax"], seed=seed, t_ref=float(t_frames[0])) if "parallax" in fx
                   else None)
            r = det.render(sc, traj, t_frames, truth_cal, kind=kind, exposure_s=exposure_s,
                           psf_sigma_px=psf_sigma, step_px=step_px, history_tau=history_tau, progress=bar,
                           parallax=par, movers=movers)
        else:
            if movers:
                raise ThermodError("simulate: moving objects need the fine-time renderer (method='fine')")
            r = det.render_time_compressed(sc, traj, t_frames, truth_cal, compression=compression,
                                           slow_fps=slow_fps, psf_sigma_px=psf_sigma, history_tau=history_tau,
                                           progress=bar)
    rng_sensor, rng_gyro = np.random.default_rng([seed, 10]), np.random.default_rng([seed, 11])
    frames = det.apply_sensor(r.frames, sensor, rng_sensor, float(np.median(sc.texture)),
                              t_frames=t_frames - t_frames[0], nuc_rng=np.random.default_rng([seed, 12]))
    gs = gyro.sample(traj.omega, gyro_lo, gyro_hi, truth_cal, rng_gyro, t_anchor=t_frames[0])

    run = {"psf_sigma_px": float(psf_sigma), "scene": _spec_str(scene), "motion": mot.spec, "seed": int(seed),
           "detector": kind, "step_px": float(step_px), "history_tau": float(history_tau),
           "t_ref": float(t_frames[0]), "n_steps": int(r.n_steps), "max_step_px": float(r.max_step_px),
           "method": method, "counts_per_k": float(sensor.counts_per_k), "effects_json": json.dumps(fx),
           "gyro_model_json": json.dumps(_jsonable(gyro)), "effects": ",".join(sorted(fx)) if fx else ""}
    if method == "time_compression":
        run.update(compression=float(compression), slow_fps=float(slow_fps))
    extras = _truth_extras(r, gs, traj.R(t_frames), truth)
    if sensor.nuc is not None:
        extras["truth/ffc_frozen"] = sensor.nuc.frozen(t_frames - t_frames[0])
    return Recording(frames, t_frames, gs.t, gs.rate, nominal, extras=extras,
                     extra_attrs={"truth": _truth_attrs(truth_cal, run, fx)})


def _check_method(method: str, kind: str, effects: Mapping | None = None) -> None:
    """Reject unknown synthesis methods and time compression of a photon detector."""
    if method not in ("fine", "time_compression"):
        raise ThermodError(f"simulate: method must be 'fine' or 'time_compression', got {method!r}")
    if method == "time_compression" and "parallax" in (effects or {}):
        raise ThermodError("simulate: parallax needs the fine-time renderer (method='fine')")
    if method == "time_compression" and kind != "thermal":
        raise ThermodError("simulate: time compression synthesises the thermal detector only")


def _nominal_calibration(calib: Calibration | None, frame_rate: float | None) -> Calibration:
    """The calibration the user believes (default `Calibration()`), at `frame_rate` if given."""
    nominal = calib or Calibration()
    if frame_rate is not None:
        if not 0 < frame_rate <= 10000:
            raise ThermodError(f"--fps: expected 0 < fps ≤ 10000, got {frame_rate}")
        nominal = nominal.replace(frame_rate_hz=float(frame_rate))
    _check_calibration(nominal)
    return nominal


def _frame_count(seconds: float, calib: Calibration) -> int:
    """Frames in `seconds` at the calibration's frame rate; the whole recording must fit in memory."""
    fps = float(calib.frame_rate_hz)
    if not (isinstance(seconds, (int, float)) and 0 < seconds <= 3600):
        raise ThermodError(f"--seconds: expected 0 < seconds ≤ 3600, got {seconds!r}")
    n = int(round(seconds * fps))
    if n < 1:
        raise ThermodError(f"--seconds {seconds}: shorter than one frame at {fps} Hz")
    per_frame = int(calib.width) * int(calib.height) * (2 + 4 * 3)   # uint16 out + 3 float32 truth stacks
    if n * per_frame > MAX_BYTES:
        raise ThermodError(f"--seconds {seconds}: {n} frames need ~{n * per_frame / 1e9:.1f} GB in memory "
                           f"(limit {MAX_BYTES / 1e9:.0f} GB); shorten the run or shrink the frame")
    return n


def _gyro_with_effects(gyro: GyroErrorModel, fx: Mapping) -> GyroErrorModel:
    """The gyro error model with the effects' noise, clock drift and low-pass applied."""
    changes = {}
    if "gyro_noise" in fx:
        changes["noise_rms_deg_s"] = fx["gyro_noise"] / DEG
    changes.update(_gyro_effect_changes(gyro, fx))
    return gyro.replace(**changes)


def _sensor_effects(fx: Mapping) -> det.SensorEffects:
    """The read-out electronics the effects ask for (validated)."""
    sensor = det.SensorEffects(netd_k=fx.get("netd", 0.0), fpn_k=fx.get("fpn", 0.0),
                               gain_nonuniformity=fx.get("gain_nonuniformity", 0.0),
                               nonlinearity=fx.get("detector_nonlinearity", 0.0),
                               quantisation_bits=fx.get("quantisation_bits", 16), nuc=_ffc_event(fx))
    sensor.validate()
    return sensor


def _trajectory(mot: mo.Motion, t_frames: np.ndarray, calib: Calibration, kind: str,
                exposure_s: float | None, history_tau: float) -> tuple[mo.Trajectory, float, float]:
    """The motion's trajectory and the gyro's sampling window (t_lo, t_hi).

    The window runs from max(0.1 s, lead + readout + 50 ms) before the first frame, lead = the
    detector's history (`history_tau`·τ, or the photon exposure), to 50 ms after the last; the
    trajectory reaches |time offset| + 50 ms further either side (the gyro clock is shifted by it)."""
    if kind == "photon":
        lead = exposure_s or default_photon_exposure_s(calib.frame_rate_hz)
    else:
        lead = history_tau * calib.tau_s
    gyro_lo = t_frames[0] - max(0.1, lead + calib.readout_s + 0.05)
    gyro_hi = t_frames[-1] + 0.05
    off = abs(calib.time_offset_s)
    return mo.Trajectory(mot, t_frames[0], gyro_lo - off - 0.05, gyro_hi + off + 0.05), gyro_lo, gyro_hi


@contextmanager
def _progress_bar(n_frames: int):
    """A tqdm bar as the renderer's progress callable (None when n_frames is 0); closed on exit."""
    if not n_frames:
        yield None
        return
    from tqdm import tqdm
    bar = tqdm(total=n_frames, unit="frame", desc="thermod sim", leave=False)
    try:
        yield lambda k: bar.update(k - bar.n)
    finally:
        bar.close()


def _truth_extras(r: det.Rendered, gs, frame_R: np.ndarray, truth: bool) -> dict:
    """The truth datasets (module docstring); the float32 image stacks only when `truth`."""
    extras = {}
    if truth:
        extras["truth/frames"] = r.sharp
        extras["truth/blurry_noiseless"] = r.frames
        if r.sharp_rolling is not None:
            extras["truth/frames_rolling"] = r.sharp_rolling
    extras["truth/gyro_t_camera"] = gs.t_true
    extras["truth/gyro_omega_camera"] = gs.omega_true.astype(np.float32)
    extras["truth/frame_R"] = frame_R
    return extras


def _truth_attrs(truth_cal: Calibration, run: dict, fx: Mapping) -> dict:
    """The truth attributes: the true calibration, then how the recording was made (`run`), then
    one `effect_<name>` per effect."""
    attrs = {k: np.asarray(v, dtype=np.float64) if isinstance(v, (list, tuple, np.ndarray)) else v
             for k, v in {**truth_cal.camera_attrs(), **truth_cal.gyro_attrs()}.items()}
    attrs.update(run)
    for k, v in fx.items():
        attrs[f"effect_{k}"] = np.asarray(v, dtype=np.float64)
    return attrs


def truth_calibration(rec: Recording) -> Calibration:
    """The true calibration stored by `simulate` in a recording's truth attributes."""
    a = rec.extra_attrs.get("truth")
    if not a:
        raise ThermodError("recording has no truth attributes (not made by thermod sim)")
    return Calibration.from_attrs(a, a)


def _check_calibration(c: Calibration) -> None:
    checks = (("width", c.width >= 8), ("height", c.height >= 8), ("fx", c.fx > 0), ("fy", c.fy > 0),
              ("tau_s", c.tau_s >= 0), ("frame_rate_hz", c.frame_rate_hz > 0), ("rate_hz", c.rate_hz > 0),
              ("readout_s", c.readout_s >= 0))
    for name, ok in checks:
        v = getattr(c, name)
        if not (ok and math.isfinite(v)):
            raise ThermodError(f"calibration {name} = {v!r}: out of range for a simulation")


def _sphere_scene(scene, calib: Calibration, seed: int) -> det.SphereScene:
    if isinstance(scene, det.SphereScene):
        return scene
    H, W = int(calib.height), int(calib.width)
    procedural = isinstance(scene, str) and scene.split(":")[0] in ("bars", "points", "texture")
    shape = (2 * H, 2 * W) if procedural else (H, W)
    tex = scenes.load_scene(scene, shape, seed)
    return det.SphereScene(tex, calib.fx, calib.fy)


def _spec_str(scene) -> str:
    if isinstance(scene, str):
        return scene
    return f"<{type(scene).__name__}>"


def _jsonable(g: GyroErrorModel) -> dict:
    d = {}
    for k, v in g.__dict__.items():
        d[k] = None if v is None else (str(v) if isinstance(v, float) and not math.isfinite(v) else v)
    return d


# ------------------------------------------------------------------ gyro-side effects of issue 12
# clock_drift, gyro_lowpass, gyro_saturation: the truth calibration carries each (so that
# `Calibration.condition_gyro` with the true values inverts them) and the gyro error model renders
# the low-pass and the clipping; the clock drift is rendered through the truth calibration's clock.
MAX_CLOCK_DRIFT_PPM = 1e5


def _check_gyro_effects(fx: dict) -> None:
    if "clock_drift" in fx and not abs(fx["clock_drift"]) <= MAX_CLOCK_DRIFT_PPM:
        raise ThermodError(f"--effect clock_drift={fx['clock_drift']}: expected a drift within "
                           f"±{MAX_CLOCK_DRIFT_PPM:g} ppm")
    if "gyro_lowpass" in fx and fx["gyro_lowpass"] != 0 and not fx["gyro_lowpass"] >= 1.0:
        raise ThermodError(f"--effect gyro_lowpass={fx['gyro_lowpass']}: expected a cutoff ≥ 1 Hz "
                           "(0 = none)")
    if "gyro_saturation" in fx and not fx["gyro_saturation"] > 0:
        raise ThermodError(f"--effect gyro_saturation={fx['gyro_saturation']}: expected a full-scale range "
                           "> 0 rad/s")


def _true_gyro_effects(c: Calibration, fx: Mapping, t_anchor: float) -> Calibration:
    changes = {}
    if fx.get("clock_drift"):
        changes.update(clock_drift_ppm=float(fx["clock_drift"]),
                       clock_epoch_s=float(t_anchor) - c.time_offset_s)
    if fx.get("gyro_lowpass"):
        nyq = 0.5 * c.rate_hz
        if not fx["gyro_lowpass"] < nyq:
            raise ThermodError(f"--effect gyro_lowpass={fx['gyro_lowpass']}: expected a cutoff below the "
                               f"gyro's Nyquist rate {nyq:g} Hz")
        changes["gyro_lowpass_hz"] = float(fx["gyro_lowpass"])
    if "gyro_saturation" in fx:
        changes["gyro_range_rad_s"] = float(fx["gyro_saturation"])
    return c.replace(**changes) if changes else c


def _gyro_effect_changes(gyro: GyroErrorModel, fx: Mapping) -> dict:
    changes = {}
    if fx.get("gyro_lowpass"):
        changes["lowpass_hz"] = fx["gyro_lowpass"]
    if "gyro_saturation" in fx:
        changes["range_deg_s"] = min(gyro.range_deg_s, fx["gyro_saturation"] / DEG)
    return changes
