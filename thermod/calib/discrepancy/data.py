"""The model under test and one recording prepared for the fit: static reference, motion frames,
forward model, and the guards on every size derived from the file before it is allocated."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from thermod.calib.discrepancy.sensor import FFCEvent, Response
from thermod.calib.forward import ForwardModel, GridTooLarge
from thermod.errors import RecordingError
from thermod.io import recording as recording_io
from thermod.physics.calibration import Calibration

log = logging.getLogger("thermod.calib.discrepancy")

# Twice the largest full scale of common MEMS gyros (±2000 °/s): anything faster is not a rate in
# rad/s (raw counts stored as rates, or a wrong unit).
MAX_GYRO_RATE_RAD_S = math.radians(4000.0)
# Working resolution and forward-model memory: the warped views of every time step are held at once.
MIN_WORK_PX = 16
MIN_STATIC_FRAMES = 3         # fewer before the motion: no static reference, the motion-only one
MIN_COVERAGE = 2.5            # motion-only: canvas pixels seen by fewer frames are not part of the scene
MAX_VIEWS_MB = 2048.0         # beyond this the recording is refused (the views at the asked resolution)
# Every evaluation warps and filters all views, so their size sets the run time of the whole search: a
# grid above this is worked at half the resolution (at most `MAX_HALVINGS` times), then on the first
# motion frames only, each choice logged. `thermod sim`'s default recording needs 65 MB, tests ≤ 30 MB.
WORK_VIEWS_MB = 512.0
MAX_HALVINGS = 2
MAX_STATIC_FRAMES = 500       # the last ones before the motion make the reference


@dataclass(frozen=True)
class Model:
    """The calibration under test plus the extra optical blur of motion frames (px, full resolution)
    and the detector-side effects (`sensor`: a non-linear response, flat-field correction events)."""

    calib: Calibration
    extra_psf_px: float = 0.0
    response: Response | None = None
    ffc: tuple[FFCEvent, ...] = ()

    def final_calibration(self) -> Calibration:
        """Calibration with the extra blur folded into Eq. 19's σ (static blur taken as nominal) and one
        recording's per-run continuation gains folded into one (their median: what a live stream,
        whose windows see parts of runs, can apply)."""
        c = self.calib
        if c.gyro_clip_run_gains:
            c = c.replace(gyro_clip_gain=float(np.median(c.gyro_clip_run_gains)), gyro_clip_run_gains=())
        if self.extra_psf_px <= 0:
            return c
        return c.with_psf_sigma_px(math.hypot(c.psf_sigma_px, self.extra_psf_px))


@dataclass
class RecData:
    """One recording prepared for the fit (everything at the working resolution)."""

    name: str
    fm: ForwardModel
    measured: np.ndarray          # float32 [n, h, w] motion frames
    frame_t: np.ndarray           # their camera times (nominal model)
    static_mean: np.ndarray       # float32 [h, w] reference incl. FPN
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
    reference: str = "static"     # "static": mean of the static frames; "motion": estimated scene canvas
    scene: np.ndarray | None = None       # motion: float32 canvas (FPN-free sharp scene at t_ref's pose)
    origin: tuple = (0.0, 0.0)            # motion: canvas position of the reference view's pixel (0, 0)
    coverage: np.ndarray | None = None    # motion: frames' summed weight per canvas pixel
    noise_source: str = "static frames"   # how noise_var was measured
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
def _check_inputs(rec: recording_io.Recording, calib: Calibration, name: str, frames_scale: float = 1.0):
    """Everything `prepare` sizes from the file, checked before it is used (the calibration's own values
    are checked by `Calibration` itself)."""
    n, h, w = rec.frames.shape
    intr = calib.intrinsics.scaled(frames_scale)
    if (h, w) != (intr.height, intr.width):
        scaled = "" if frames_scale == 1.0 else f" (× {frames_scale:g}: {intr.width}×{intr.height})"
        raise RecordingError(name, "camera/frames", f"frame size {w}×{h} does not match the model's "
                             f"width×height {calib.width}×{calib.height}{scaled}")
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


def working_scale(calib: Calibration, work_width: int) -> float:
    """Working scale: halved until the width is within 1.5× `work_width` (at most 1/16)."""
    scale = 1.0
    while calib.width * scale > 1.5 * work_width and scale > 1 / 16:
        scale /= 2.0
    return scale


def working_frames(frames, index, size: tuple[int, int], smooth_px: float = 0.0) -> np.ndarray:
    """`frames[i]` for i in `index`, area-averaged to `size` (w, h) one frame at a time (float32
    [len(index), h, w]): what `downsample` gives, without a float copy of the whole stack."""
    import cv2

    out = np.empty((len(index), size[1], size[0]), np.float32)
    for j, i in enumerate(index):
        f = np.asarray(frames[int(i)], np.float32)
        g = f if f.shape == (size[1], size[0]) else cv2.resize(f, size, interpolation=cv2.INTER_AREA)
        if smooth_px > 0:
            g = cv2.GaussianBlur(g, (0, 0), smooth_px, borderType=cv2.BORDER_REPLICATE)
        out[j] = g
    return out


def _grid_refusal(name: str, calib: Calibration, e: GridTooLarge) -> RecordingError:
    """The view grid is beyond any budget: name what makes it fine (τ, the image speed, fx)."""
    if e.tau_limited:      # the steps are τ/3 long: the grid shrinks in proportion as τ grows
        need = max(calib.tau_s, 7.5e-5) * e.views_mb / MAX_VIEWS_MB   # (steps are ≥ 25 µs whatever τ)
        return RecordingError(name, "camera.attrs['tau_s']", f"{e}; expected τ ≥ about {need:.2g} s for "
                              "this length of motion (or a shorter recording)")
    return RecordingError(name, "camera/t, gyro/rate", f"{e}; shorten the motion segment, lower "
                          "--work-width, or check fx and tau_s")


def _bounded_grid(name: str, calib: Calibration, scale: float, n_frames: int, build, min_frames: int,
                  max_views_mb: float, work_views_mb: float):
    """`build(scale, n, budget_mb)` (a ForwardModel on the first n motion frames, GridTooLarge beyond the
    budget) within `work_views_mb`: at `scale` if it fits; else at up to `MAX_HALVINGS` halvings of it;
    else on the first motion frames only (≥ `min_frames`). A grid beyond `max_views_mb` at `scale` is
    refused. Returns (model, scale, frames kept); every reduction is logged."""
    try:
        fm = build(scale, n_frames, max_views_mb)
    except GridTooLarge as e:
        raise _grid_refusal(name, calib, e) from None
    views_mb = len(fm.t_views) * fm.h * fm.w * 2 * 4 / 1e6
    if views_mb <= work_views_mb:
        return fm, scale, n_frames
    s = scale
    for _ in range(MAX_HALVINGS):
        work = calib.intrinsics.scaled(s / 2)
        if min(work.width, work.height) < MIN_WORK_PX:
            break
        s /= 2
        try:
            fm = build(s, n_frames, work_views_mb)
        except GridTooLarge:
            continue
        log.warning("%s: the forward model's views need %.0f MB at %d×%d (budget %.0f MB): working at "
                    "%d×%d instead", name, views_mb, *_size(calib, scale), work_views_mb, fm.w, fm.h)
        return fm, s, n_frames
    lo, hi, best = min_frames, n_frames - 1, None      # the most leading motion frames that fit
    while lo <= hi:
        mid = (lo + hi) // 2
        try:
            best = (build(s, mid, work_views_mb), mid)
            lo = mid + 1
        except GridTooLarge:
            hi = mid - 1
    if best is None:
        raise RecordingError(name, "camera/t, gyro/rate", f"the forward model's views need {views_mb:.0f} MB "
                             f"and {min_frames} motion frames need more than {work_views_mb:.0f} MB even at "
                             f"{_size(calib, s)[0]}×{_size(calib, s)[1]}; expected slower motion (check the "
                             "gyro rates, fx and tau_s)")
    log.warning("%s: the forward model's views need %.0f MB for %d motion frames at %d×%d (budget %.0f MB): "
                "working on the first %d motion frames at %d×%d", name, views_mb, n_frames,
                *_size(calib, scale), work_views_mb, best[1], best[0].w, best[0].h)
    return best[0], s, best[1]


def _size(calib: Calibration, scale: float) -> tuple[int, int]:
    work = calib.intrinsics.scaled(scale)
    return work.width, work.height


def prepare(rec: recording_io.Recording, calib: Calibration, *, name: str = "<recording>",
            scale: float | None = None, work_width: int = 160,
            offset_margin_s: float = 0.03, max_step_px: float = 1.0, smooth_px: float = 0.0,
            max_views_mb: float = MAX_VIEWS_MB, work_views_mb: float = WORK_VIEWS_MB,
            frames_scale: float = 1.0) -> RecData:
    """Split a recording into reference and motion frames and build its forward model.

    `rec.frames` may be stored at `frames_scale` × the calibration's size (`thermod discrepancy` bins
    very large frames as it reads them); the working scale is at most that. The forward model's views
    are kept within `work_views_mb` (`_bounded_grid`: a coarser working image, then fewer motion frames).

    Raises RecordingError (naming `name`) when there is no static segment, no motion, no gyro
    coverage of the motion frames, or when a size derived from the file (the working image, the
    forward model's time steps) would be unreasonable. The calibration's own values were checked when
    it was built (by the --config loader or the recording reader, which name their source).
    """
    _check_inputs(rec, calib, name, frames_scale)
    if scale is None:
        scale = min(working_scale(calib, work_width), frames_scale)
    work = calib.intrinsics.scaled(scale)
    if min(work.width, work.height) < MIN_WORK_PX:
        raise RecordingError(name, "camera/frames", f"{calib.width}×{calib.height} frames give a "
                             f"{work.width}×{work.height} working image; need ≥ {MIN_WORK_PX} px a side")
    _check_offset(rec, calib, name)
    seg = _segments(rec, calib, name, offset_margin_s)
    if seg is None:
        return _prepare_motion(rec, calib, name, scale, offset_margin_s, max_step_px, smooth_px, max_views_mb,
                               work_views_mb)
    static, moving, t_onset, t_ref = seg.static, seg.moving, seg.t_onset, seg.t_ref
    static_idx = np.flatnonzero(static)[-MAX_STATIC_FRAMES:]
    n_static = len(static_idx)
    moving_idx = np.flatnonzero(moving)

    def build(s, n, budget):
        w, h = _size(calib, s)
        return ForwardModel(np.zeros((h, w), np.float32), rec.t[moving_idx[:n]], rec.gyro_t, rec.gyro_rate,
                            calib, t_ref=t_ref, scale=s, max_step_px=max_step_px, max_views_mb=budget,
                            prescaled=True)
    fm, scale, n_moving = _bounded_grid(name, calib, scale, len(moving_idx), build, 2, max_views_mb,
                                        work_views_mb)
    moving_idx = moving_idx[:n_moving]
    frame_t = rec.t[moving_idx]
    size = (fm.w, fm.h)
    st_w = working_frames(rec.frames, static_idx, size, smooth_px)
    static_mean = st_w.mean(axis=0)
    noise_var = max(float(np.mean((st_w - static_mean) ** 2) * n_static / max(n_static - 1, 1)),
                    quantisation_variance(scale))
    fm.set_reference(static_mean, None, prescaled=True)
    measured = working_frames(rec.frames, moving_idx, size, smooth_px)
    gm = rec.gyro_t + calib.time_offset_s > t_onset
    base = seg.static_rate if seg.static_rate is not None else np.zeros(3)
    motion_rms = np.sqrt(np.mean((rec.gyro_rate[gm] - base) ** 2, axis=0)) if gm.any() else np.zeros(3)
    return RecData(name, fm, measured, frame_t, static_mean, noise_var, n_static, t_ref,
                   t_onset, rec.gyro_t, rec.gyro_rate, seg.static_rate,
                   _static_sem(rec.gyro_t, rec.gyro_rate, seg.t_onset_gyro), motion_rms)


def _check_offset(rec, calib: Calibration, name: str) -> None:
    """A time offset that moves the gyro past the whole recording is not a clock offset: refused."""
    off = calib.time_offset_s
    span = float(rec.t[-1] - rec.t[0]) if len(rec.t) else 0.0
    if len(rec.gyro_t) and abs(off) > 0.5 * span:
        g0, g1 = float(rec.gyro_t[0]) + off, float(rec.gyro_t[-1]) + off
        raise RecordingError(name, "gyro.attrs['time_offset_s']", f"{off!r} s moves the gyro samples to "
                             f"camera times [{g0:.3f}, {g1:.3f}] s, against frames in [{rec.t[0]:.3f}, "
                             f"{rec.t[-1]:.3f}] s; expected an offset within ±{0.5 * span:.3g} s (half "
                             "the time the frames span)")


@dataclass(frozen=True)
class _Segments:
    static: np.ndarray        # bool per frame: the reference frames
    moving: np.ndarray        # bool per frame: motion frames covered by gyro samples
    t_onset: float            # camera clock
    t_onset_gyro: float
    t_ref: float              # end of the reference (onset minus the time-offset margin)
    static_rate: np.ndarray | None


def _segments(rec, calib: Calibration, name: str, offset_margin_s: float) -> _Segments | None:
    t_on_g, static_rate = detect_static(rec.gyro_t, rec.gyro_rate)
    if t_on_g is None:
        raise RecordingError(name, "gyro/rate", "no motion found: the workflow needs a static segment "
                             "followed by motion")
    t_onset = t_on_g + calib.time_offset_s
    t_ref = t_onset - offset_margin_s
    static = rec.t <= t_ref
    n_static = int(static.sum())
    if n_static < MIN_STATIC_FRAMES:
        return None            # no static lead-in: the motion-only reference (`_prepare_motion`)
    gyro_end = rec.gyro_t[-1] + calib.time_offset_s - offset_margin_s
    moving = (rec.t > t_ref) & (rec.t <= gyro_end)
    if moving.sum() < 2:
        raise RecordingError(name, "camera/t", "fewer than 2 frames during the motion are covered by gyro "
                             "samples")
    return _Segments(static, moving, t_onset, t_on_g, t_ref, static_rate)


def quantisation_variance(scale: float) -> float:
    """Least noise variance (counts², working resolution) a frame of integer counts can have: each
    full-resolution pixel's rounding error (uniform, variance 1/12) averaged over the 1/scale² pixels
    `downsample` puts into one working pixel. Noiseless renders (identical static frames, NETD 0) and
    flat scenes otherwise give a noise floor of 0, which no comparison of frames can reach."""
    return float(scale) ** 2 / 12.0


# ----------------------------------------------------------------------------------------- motion only
def noise_variance_spatial(frames: np.ndarray) -> float:
    """Temporal-noise variance of single frames from their spatial high frequencies (Immerkær 1996):
    the 3×3 operator [1 −2 1; −2 4 −2; 1 −2 1] cancels locally planar signal and has gain 36 on white
    noise; the median of its magnitude over the flattest half of the pixels (σ = √(π/2)·mean|L|/6 for
    Gaussian noise, here from the median) resists edges. Scene texture at the pixel scale still
    leaks in, so on textured scenes this is an upper bound (the report says which estimate it used)."""
    import cv2

    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    vals = []
    for f in np.asarray(frames, np.float32):
        L = np.abs(cv2.filter2D(f, -1, k, borderType=cv2.BORDER_REFLECT))[1:-1, 1:-1]
        gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)[1:-1, 1:-1]
        gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)[1:-1, 1:-1]
        g = np.hypot(gx, gy)
        flat = L[g <= np.median(g)]
        vals.append(np.median(flat))
    sigma = float(np.median(vals)) / 0.6745 / 6.0      # median |N(0, 36σ²)| = 0.6745·6σ
    return sigma * sigma


def _pixel_speed(calib: Calibration, gyro_t, gyro_rate, scale: float):
    """Camera-clock times and image speed (working px/s at the frame corners) of the gyro samples."""
    t_cam, w = calib.gyro_to_camera(gyro_t, gyro_rate)
    intr = calib.intrinsics.scaled(scale)
    r = math.hypot(intr.width, intr.height) / 2.0
    return t_cam, max(intr.fx, intr.fy) * np.hypot(w[:, 0], w[:, 1]) + r * np.abs(w[:, 2])


def _prepare_motion(rec, calib: Calibration, name: str, scale: float, offset_margin_s: float,
                    max_step_px: float, smooth_px: float, max_views_mb: float,
                    work_views_mb: float) -> RecData:
    """No static lead-in: every frame read ≥ 5τ after the gyro starts is predicted from a scene canvas
    estimated from the frames themselves (`problem.estimate_scene`), anchored at the pose of the frame
    whose preceding 5τ moved least (t_ref)."""
    tau = calib.tau_s
    period = 1.0 / calib.frame_rate_hz
    t_cam0 = float(rec.gyro_t[0]) + calib.time_offset_s + offset_margin_s
    gyro_end = float(rec.gyro_t[-1]) + calib.time_offset_s - offset_margin_s
    t_start = max(t_cam0, float(rec.t[0]) - period - 6.0 * tau)
    moving = (rec.t - period - 5.0 * tau > t_start) & (rec.t <= gyro_end)
    if moving.sum() < 3:
        raise RecordingError(name, "camera/t", "fewer than 3 frames are covered by gyro samples from 5τ "
                             "before their first row (no static segment either, so the reference must be "
                             "estimated from the moving frames)")
    idx = np.flatnonzero(moving)
    t_cam, speed = _pixel_speed(calib, rec.gyro_t, rec.gyro_rate, scale)
    # mean speed over each frame's last period + 5τ (prefix sums: the gyro may be long)
    csum = np.r_[0.0, np.cumsum(speed)]
    i0 = np.searchsorted(t_cam, rec.t[idx] - period - 5 * tau, side="left")
    i1 = np.searchsorted(t_cam, rec.t[idx], side="right")
    cnt = i1 - i0
    blur = np.where(cnt > 0, (csum[i1] - csum[i0]) / np.maximum(cnt, 1), np.inf)

    def build(s, n, budget):
        w, h = _size(calib, s)
        return ForwardModel(np.zeros((h, w), np.float32), rec.t[idx[:n]], rec.gyro_t, rec.gyro_rate, calib,
                            t_ref=float(rec.t[idx[int(np.argmin(blur[:n]))]]), t_start=t_start, scale=s,
                            max_step_px=max_step_px, max_views_mb=budget, prescaled=True)
    fm, scale, n = _bounded_grid(name, calib, scale, len(idx), build, 3, max_views_mb, work_views_mb)
    idx = idx[:n]
    k_ref = int(np.argmin(blur[:n]))
    frame_t = rec.t[idx]
    t_ref = float(frame_t[k_ref])
    measured = working_frames(rec.frames, idx, (fm.w, fm.h), smooth_px)
    origin, shape = _canvas(fm, calib)
    scene = np.zeros(shape, np.float32)
    ix, iy = int(round(origin[0])), int(round(origin[1]))
    scene[iy:iy + fm.h, ix:ix + fm.w] = measured[k_ref]
    fm.set_reference(scene, None, prescaled=True, origin=origin)
    noise_var = max(noise_variance_spatial(measured), quantisation_variance(scale))
    motion_rms = np.sqrt(np.mean((rec.gyro_rate - rec.gyro_rate.mean(axis=0)) ** 2, axis=0))
    d = RecData(name, fm, measured, frame_t, measured[k_ref].copy(), noise_var, n,
                t_ref, t_start, rec.gyro_t, rec.gyro_rate, None, None, motion_rms,
                reference="motion", scene=scene, origin=origin,
                noise_source="spatial high-pass of the motion frames")
    return d


def _canvas(fm: ForwardModel, calib: Calibration, pad: int = 4, max_factor: float = 3.0):
    """Canvas covering every view of the recording (frame corners mapped by H(s) into the reference
    camera), at most `max_factor` × the frame per side; returns (origin, shape)."""
    times = fm.t_views[:: max(1, len(fm.t_views) // 200)]
    Hs = fm.homographies(calib, times)
    w, h = fm.w, fm.h
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    p = Hs @ corners
    z = p[:, 2]
    ok = z > 1e-6
    xs = (p[:, 0] / np.where(ok, z, 1))[ok]
    ys = (p[:, 1] / np.where(ok, z, 1))[ok]
    ext_x = (max_factor - 1) / 2 * w
    ext_y = (max_factor - 1) / 2 * h
    x0 = max(float(np.floor(xs.min())) - pad, -ext_x) if xs.size else 0.0
    x1 = min(float(np.ceil(xs.max())) + pad, w - 1 + ext_x) if xs.size else w - 1
    y0 = max(float(np.floor(ys.min())) - pad, -ext_y) if ys.size else 0.0
    y1 = min(float(np.ceil(ys.max())) + pad, h - 1 + ext_y) if ys.size else h - 1
    x0, y0 = min(x0, 0.0), min(y0, 0.0)
    x1, y1 = max(x1, w - 1.0), max(y1, h - 1.0)
    origin = (-int(x0), -int(y0))
    shape = (int(y1 - int(y0)) + 1, int(x1 - int(x0)) + 1)
    return (float(origin[0]), float(origin[1])), shape
