"""The model under test and one recording prepared for the fit: static reference, motion frames,
forward model, and the guards on every size derived from the file before it is allocated."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from thermod.calib.discrepancy.sensor import FFCEvent, Response
from thermod.calib.forward import ForwardModel, GridTooLarge, downsample
from thermod.errors import RecordingError
from thermod.io import recording as recording_io
from thermod.physics.calibration import Calibration

# Twice the largest full scale of common MEMS gyros (±2000 °/s): anything faster is not a rate in
# rad/s (raw counts stored as rates, or a wrong unit).
MAX_GYRO_RATE_RAD_S = math.radians(4000.0)
# Working resolution and forward-model memory: the warped views of every time step are held at once.
MIN_WORK_PX = 16
MAX_VIEWS_MB = 2048.0


@dataclass(frozen=True)
class Model:
    """The calibration under test plus the extra optical blur of motion frames (px, full resolution)
    and the detector-side effects (`sensor`: a non-linear response, flat-field correction events)."""

    calib: Calibration
    extra_psf_px: float = 0.0
    response: Response | None = None
    ffc: tuple[FFCEvent, ...] = ()

    def final_calibration(self) -> Calibration:
        """Calibration with the extra blur folded into Eq. 19's σ (static blur taken as nominal)."""
        if self.extra_psf_px <= 0:
            return self.calib
        sigma = math.hypot(self.calib.psf_sigma_px, self.extra_psf_px)
        return self.calib.with_psf_sigma_px(sigma)


@dataclass
class RecData:
    """One recording prepared for the fit (everything at the working resolution)."""

    name: str
    fm: ForwardModel
    measured: np.ndarray          # float32 [n, h, w] motion frames
    frame_t: np.ndarray           # their camera times (nominal model)
    static_mean: np.ndarray       # float32 [h, w] reference incl. FPN
    reference_full: np.ndarray    # float32 [H, W] static mean at full resolution
    noise_var: float              # temporal variance of one static frame (working res)
    n_static: int
    t_ref: float
    t_onset: float
    gyro_t: np.ndarray
    gyro_rate: np.ndarray
    static_gyro_mean: np.ndarray | None
    static_gyro_sem: np.ndarray | None    # standard error of that mean (rad/s)
    motion_rms_rad_s: np.ndarray  # per gyro axis, bias-removed
    fpn: np.ndarray | None = None
    mask: np.ndarray | None = None
    aux: dict = field(default_factory=dict)   # per-recording state of the detector-side effects (`sensor`)


def detect_static(gyro_t, gyro_rate, *, head_s: float = 0.05, min_rate: float = math.radians(0.5),
                  k_sigma: float = 8.0, smooth_s: float = 0.005):
    """Gyro-clock time at which the motion starts, and the static samples' mean raw rate.

    The rate during the first `head_s` sets the baseline (bias) and noise; the motion starts where the
    smoothed deviation from the baseline first exceeds max(k_sigma·noise, min_rate).
    Returns (t_onset or None if there is no motion, static mean rate or None if too short).
    """
    t = np.asarray(gyro_t, np.float64)
    r = np.asarray(gyro_rate, np.float64)
    if len(t) < 10:
        return None, None
    dt = float(np.median(np.diff(t)))
    n_head = min(len(t), max(5, int(head_s / dt)))
    base = np.median(r[:n_head], axis=0)
    dev = np.linalg.norm(r - base, axis=1)
    # white-noise σ from sample-to-sample differences (robust even if the head is already moving)
    noise = 1.4826 * float(np.median(np.abs(np.diff(r[:n_head], axis=0)))) / math.sqrt(2.0) * math.sqrt(3.0)
    thr = max(k_sigma * noise, min_rate)
    win = min(len(t), max(1, int(round(smooth_s / dt))))     # the file's clock sets it: bounded
    sm = np.convolve(dev, np.ones(win) / win, mode="same")
    above = np.flatnonzero(sm > thr)
    if len(above) == 0:
        return None, r.mean(axis=0)
    i0 = int(above[0])
    t_onset = float(t[i0] - smooth_s)
    static = t < t_onset - smooth_s
    mean = r[static].mean(axis=0) if static.sum() >= 5 else None
    return t_onset, mean


def _static_sem(gyro_t, gyro_rate, t_onset_gyro):
    r = np.asarray(gyro_rate, np.float64)[np.asarray(gyro_t) < t_onset_gyro - 0.005]
    if len(r) < 5:
        return None
    # white-noise σ from differences (immune to slow drift), /√n for the mean
    return np.std(np.diff(r, axis=0), axis=0) / math.sqrt(2.0) / math.sqrt(len(r))


# ----------------------------------------------------------------------------------------- guards
def _check_inputs(rec: recording_io.Recording, calib: Calibration, name: str):
    """Everything `prepare` sizes from the file, checked before it is used (the calibration's own values
    are checked by `Calibration` itself)."""
    n, h, w = rec.frames.shape
    if (h, w) != (calib.height, calib.width):
        raise RecordingError(name, "camera/frames", f"frame size {w}×{h} does not match the model's "
                             f"width×height {calib.width}×{calib.height}")
    if n == 0:
        raise RecordingError(name, "camera/frames", "no frames: the workflow needs a static segment "
                             "followed by motion")
    rate = np.asarray(rec.gyro_rate)
    if rate.size:
        _, w_cam = calib.gyro_to_camera(rec.gyro_t, rate)
        peak = float(np.max(np.linalg.norm(w_cam, axis=1)))
        if not peak <= MAX_GYRO_RATE_RAD_S:
            raise RecordingError(name, "gyro/rate", f"peak calibrated rate {peak:.4g} rad/s "
                                 f"({math.degrees(peak):.4g} °/s) exceeds {MAX_GYRO_RATE_RAD_S:.0f} rad/s; "
                                 f"expected rad/s (dtype {rate.dtype}: raw counts, or a wrong "
                                 "scale/bias?)")


def _working_scale(calib: Calibration, work_width: int) -> float:
    scale = 1.0
    while calib.width * scale > 1.5 * work_width and scale > 1 / 16:
        scale /= 2.0
    return scale


def prepare(rec: recording_io.Recording, calib: Calibration, *, name: str = "<recording>",
            scale: float | None = None, work_width: int = 160,
            offset_margin_s: float = 0.03, max_step_px: float = 0.5, smooth_px: float = 0.0,
            max_views_mb: float = MAX_VIEWS_MB) -> RecData:
    """Split a recording into reference and motion frames and build its forward model.

    Raises RecordingError (naming `name`) when there is no static segment, no motion, no gyro
    coverage of the motion frames, or when a size derived from the file (the working image, the
    forward model's time steps) would be unreasonable. The calibration's own values were checked when
    it was built (by the --config loader or the recording reader, which name their source).
    """
    _check_inputs(rec, calib, name)
    if scale is None:
        scale = _working_scale(calib, work_width)
    work = calib.intrinsics.scaled(scale)
    if min(work.width, work.height) < MIN_WORK_PX:
        raise RecordingError(name, "camera/frames", f"{calib.width}×{calib.height} frames give a "
                             f"{work.width}×{work.height} working image; need ≥ {MIN_WORK_PX} px a side")
    seg = _segments(rec, calib, name, offset_margin_s)
    static, moving, t_onset, t_ref = seg.static, seg.moving, seg.t_onset, seg.t_ref
    n_static = int(static.sum())
    st = rec.frames[static].astype(np.float32)
    ref_full = st.mean(axis=0)
    frame_t = rec.t[moving]
    try:
        fm = ForwardModel(ref_full, frame_t, rec.gyro_t, rec.gyro_rate, calib, t_ref=t_ref, scale=scale,
                          max_step_px=max_step_px, max_views_mb=max_views_mb)
    except GridTooLarge as e:
        raise RecordingError(name, "camera/t, gyro/rate", f"{e}; shorten the motion segment, lower "
                             "--work-width, or check fx and tau_s") from None
    st_w = downsample(st, scale, smooth_px)
    static_mean = st_w.mean(axis=0)
    noise_var = float(np.mean((st_w - static_mean) ** 2) * n_static / max(n_static - 1, 1))
    fm.set_reference(static_mean, None, prescaled=True)
    measured = downsample(rec.frames[moving], scale, smooth_px)
    gm = rec.gyro_t + calib.time_offset_s > t_onset
    base = seg.static_rate if seg.static_rate is not None else np.zeros(3)
    motion_rms = np.sqrt(np.mean((rec.gyro_rate[gm] - base) ** 2, axis=0)) if gm.any() else np.zeros(3)
    return RecData(name, fm, measured, frame_t, static_mean, ref_full, noise_var, n_static, t_ref, t_onset,
                   rec.gyro_t, rec.gyro_rate, seg.static_rate,
                   _static_sem(rec.gyro_t, rec.gyro_rate, seg.t_onset_gyro), motion_rms)


@dataclass(frozen=True)
class _Segments:
    static: np.ndarray        # bool per frame: the reference frames
    moving: np.ndarray        # bool per frame: motion frames covered by gyro samples
    t_onset: float            # camera clock
    t_onset_gyro: float
    t_ref: float              # end of the reference (onset minus the time-offset margin)
    static_rate: np.ndarray | None


def _segments(rec, calib: Calibration, name: str, offset_margin_s: float) -> _Segments:
    t_on_g, static_rate = detect_static(rec.gyro_t, rec.gyro_rate)
    if t_on_g is None:
        raise RecordingError(name, "gyro/rate", "no motion found: the workflow needs a static segment "
                             "followed by motion")
    t_onset = t_on_g + calib.time_offset_s
    t_ref = t_onset - offset_margin_s
    static = rec.t <= t_ref
    n_static = int(static.sum())
    if n_static < 3:
        raise RecordingError(name, "camera/frames", f"only {n_static} frames before the motion starts at "
                             f"t={t_onset:.3f} s (minus a {offset_margin_s * 1e3:.0f} ms margin for the time "
                             "offset); need ≥ 3 static frames for a reference")
    gyro_end = rec.gyro_t[-1] + calib.time_offset_s - offset_margin_s
    moving = (rec.t > t_ref) & (rec.t <= gyro_end)
    if moving.sum() < 2:
        raise RecordingError(name, "camera/t", "fewer than 2 frames during the motion are covered by gyro "
                             "samples")
    return _Segments(static, moving, t_onset, t_on_g, t_ref, static_rate)
