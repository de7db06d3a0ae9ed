"""A thermal video with no gyro log → a format-v1 recording whose gyro is the camera's rotation
estimated from the pictures (`thermod.motion.track`).

`import_video` reads the video (`thermod.io.video`: container timestamps, variable frame rate
included), estimates the rotation track and writes:

- ``/camera/frames``, ``/camera/t``: the video's frames as delivered (8-bit AGC'd frames widened to
  uint16) and times; the calibration is the camera file's, its frame rate the video's;
- ``/gyro/t``, ``/gyro/rate``: the track's camera-frame rate sampled at 1 kHz on the video clock
  (R_cam_gyro = I), with holes where the motion is unknown (cuts, frames too poor in texture), so
  `thermod deblur` passes the frames that reach into them through (``gyro_gap``);
- ``/motion``: attributes ``source = "video"``, the blur lag, the frames flagged and the overlay
  found (JSON); ``motion/sigma_rad_s`` [M] (each sample's 1σ, rad/s) and, when a static overlay was
  found, ``motion/overlay`` (uint8 [H, W]; kept out of the solve by `thermod.restore.overlay`);
- ``/import``: where it came from (file, codec, bit depth, luma range), ``motion_source = "video"``.

With ``fit_tau`` (or a camera file that gives no τ) the detector's τ is fitted to the frames' comet
tails along the track (`thermod.calib.tau_fit`), the track is estimated again with it, and
``/motion`` holds the fit (``tau_fit``, JSON); a stated τ more than 3σ from the fit is reported.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from thermod.calib.tau_fit import START_TAU_S, VIDEO_BAND, TauFit, fit_tau
from thermod.errors import ThermodError
from thermod.ingest.camera_video import put_frames_and_gyro, read_camera_video
from thermod.io import video
from thermod.io.json_safe import jsonable
from thermod.io.recording import OVERLAY_DATASET, Writer
from thermod.motion.track import DEFAULT_RATE_HZ, RotationTrack, TrackError, estimate_track, full_resolution
from thermod.physics.calibration import Calibration
from thermod.physics.kernels.grids import kernel_span_s

MOTION_GROUP = "motion"
SOURCE = "video"


class VideoImportError(ThermodError):
    """A video that cannot be made into a recording without a gyro: names the file and what was wrong."""


@dataclass
class ImportedVideo:
    """What `import_video` wrote and found."""

    path: Path
    calibration: Calibration
    track: RotationTrack
    n_frames: int
    n_gyro: int
    video_info: video.VideoInfo
    notes: list[str] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    tau_fit: TauFit | None = None

    def report(self) -> dict:
        """The import's report (strict JSON once through `jsonable`)."""
        return jsonable({"recording": str(self.path), "frames": self.n_frames, "gyro_samples": self.n_gyro,
                         "motion_source": SOURCE, "track": self.track.to_dict(),
                         "calibration": self.calibration.as_dict(), "notes": self.notes,
                         "seconds": self.seconds,
                         "tau_fit": None if self.tau_fit is None else self.tau_fit.to_dict()})


def import_video(video_path: str | os.PathLike, out: str | os.PathLike, camera: Calibration, *,
                 fps: float | None = None, max_bytes: int = video.DEFAULT_MAX_BYTES, start_s: float = 0.0,
                 duration_s: float | None = None, rate_hz: float = DEFAULT_RATE_HZ,
                 report_dir: str | os.PathLike | None = None, fit_time_constant: bool = False,
                 tau_stated: bool = True, say: Callable[[str], None] | None = None) -> ImportedVideo:
    """Read a video, estimate its rotation track and write the recording (module docstring). `camera`
    gives the intrinsics, τ and readout (`thermod.io.camera_file`); `tau_stated` False: its τ is not
    known and is fitted (as with `fit_time_constant`). With `report_dir`, writes ``track.json`` and
    ``track.png`` (the estimated rate per axis, flagged frames marked). Raises a ThermodError naming
    the file and what was wrong; nothing is written then."""
    say = say or (lambda _msg: None)
    t_start = time.perf_counter()
    cv = read_camera_video(video_path, camera, VideoImportError,
                           "estimating the motion from the pictures needs a video of several frames",
                           fps=fps, max_bytes=max_bytes, start_s=start_s, duration_s=duration_s)
    vf, period, notes, info = cv.frames, cv.period_s, cv.notes, cv.frames.info
    calib = cv.camera.with_camera_gyro(rate_hz)
    say(f"video: {len(vf.t)} frames of {info.width}×{info.height} ({info.bit_depth}-bit {info.codec}), "
        f"{vf.t[-1] - vf.t[0]:.1f} s at {1.0 / period:.3g} fps; no gyro: the motion comes from the pictures")
    t_read = time.perf_counter()
    if not tau_stated:
        calib = calib.replace(tau_s=START_TAU_S)
    track = _track(vf, calib, video_path)
    margin = calib.gyro_condition_margin_s + 4.0 / rate_hz
    tau_fit = None
    if fit_time_constant or not tau_stated:
        calib, track, tau_fit = _fit_tau(vf, calib, track, video_path, rate_hz, margin, tau_stated, notes,
                                         say)
    t_track = time.perf_counter()
    gt, gr, gs = _track_gyro(track, calib, rate_hz, margin, video_path)
    flagged = track.flagged()
    for what, frames in flagged.items():
        if frames:
            label = "after a time gap (frames lost or the clock jumped)" if what == "gap" else what
            notes.append(f"{len(frames)} frame(s) {label}: {frames[:10]}{' …' if len(frames) > 10 else ''}"
                         + (" (shows the previous view; the motion is interpolated across it)"
                            if what == "duplicate" else " (the motion into it is unknown: passed through)"))
    if track.overlay is not None:
        notes.append(f"a static overlay covers {track.overlay.mean():.1%} of the frame (found by itself; not "
                     "tracked)")
    path = _write(out, vf, gt, gr, gs, calib, track, tau_fit, {
        "video": str(video_path), "video_codec": info.codec, "video_bit_depth": info.bit_depth,
        "video_luma_only": info.luma_only, "video_full_range": info.full_range, "motion_source": SOURCE,
        "agc": "per-frame AGC left in the frames" if info.bit_depth == 8 else "none assumed (16-bit)"})
    t_write = time.perf_counter()
    seconds = {"read_video": t_read - t_start, "track": t_track - t_read, "write": t_write - t_track}
    imported = ImportedVideo(path, calib, track, len(vf.t), len(gt), info, notes, seconds, tau_fit)
    if report_dir is not None:
        rd = Path(report_dir)
        rd.mkdir(parents=True, exist_ok=True)
        (rd / "track.json").write_text(json.dumps(imported.report(), indent=2, allow_nan=False) + "\n")
        plot_track(track, gt, gr, rd / "track.png")
    return imported


def _track(vf: video.VideoFrames, calib: Calibration, video_path) -> RotationTrack:
    try:
        return estimate_track(vf.frames, vf.t, calib.intrinsics, tau_s=calib.tau_s, readout_s=calib.readout_s,
                              name=str(video_path))
    except TrackError as e:
        raise VideoImportError(str(e)) from None


def _track_gyro(track: RotationTrack, calib: Calibration, rate_hz: float, margin: float, video_path,
                smooth: bool = False):
    """The track sampled as a gyro: the kernel window before the first frame, and past each stretch's
    last knot the lag plus what a frame's kernel reads beyond its read time
    (thermod.restore.policy.gyro_span)."""
    gt, gr, gs = track.gyro(rate_hz, lead_s=kernel_span_s(calib) + margin, tail_s=track.lag_s + margin,
                            smooth=smooth)
    if len(gt) < 2:
        raise VideoImportError(f"{video_path}: no stretch of frames with a known motion")
    return gt, gr, gs


def _fit_tau(vf, calib: Calibration, track: RotationTrack, video_path, rate_hz, margin, tau_stated: bool,
             notes: list[str], say) -> tuple[Calibration, RotationTrack, TauFit]:
    """τ fitted to the frames along the track's smoothed rate (`RotationTrack.gyro(smooth=True)`: the
    rate's noise biases the fit), then the track again with the fitted τ (its lag is τ's) and τ
    fitted once more along it: a start far from τ (a wrong camera file) misplaces the first track
    and shortens the first fit (benchmarks/results/video_tau.md). A camera file's τ is kept, with a
    note, when the pictures do not show τ; with no τ stated that is a VideoImportError."""

    def fitted(calib, track):
        gt, gr, _ = _track_gyro(track, calib, rate_hz, margin, video_path, smooth=True)
        return fit_tau(vf.frames, vf.t, gt, gr, calib, start_tau_s=calib.tau_s, pairs=track.status == "ok",
                       band=VIDEO_BAND)

    fit = fitted(calib, track)
    if fit.tau_s is not None:
        first = calib.replace(tau_s=float(fit.tau_s))
        again = fitted(first, _track(vf, first, video_path))
        if again.tau_s is not None:      # its scans follow the first fit's in the report
            fit = replace(again, scans_ms=fit.scans_ms + again.scans_ms)
    if fit.tau_s is None:
        if not tau_stated:
            raise VideoImportError(f"{video_path}: the camera file gives no tau_s and the pictures do not "
                                   f"show it ({fit.note}); give the detector's time constant (tau_s, or "
                                   "--tau)")
        notes.append(f"{fit.note}; the camera file's tau_s {1e3 * calib.tau_s:.2f} ms is kept")
        return calib, track, fit
    text = (f"tau fitted from the pictures: {1e3 * fit.tau_s:.2f} ± {1e3 * fit.sigma_s:.2f} ms "
            f"({fit.patches} frame pairs)")
    if tau_stated:
        text += (f"; the camera file says {1e3 * calib.tau_s:.2f} ms, " +
                 (f"{abs(calib.tau_s - fit.tau_s) / fit.sigma_s:.1f}σ away: it disagrees with the pictures"
                  if fit.disagrees_with(calib.tau_s) else "within 3σ"))
    notes.append(text)
    say(text)
    calib = calib.replace(tau_s=float(fit.tau_s))
    return calib, _track(vf, calib, video_path), fit


def _write(out, vf: video.VideoFrames, gyro_t, gyro_rate, sigma, calib: Calibration, track: RotationTrack,
           tau_fit: TauFit | None, attrs: dict) -> Path:
    w = Writer(out)
    try:
        put_frames_and_gyro(w, vf, gyro_t, gyro_rate, calib)
        w.put(f"{MOTION_GROUP}/sigma_rad_s", np.asarray(sigma, np.float32))
        if track.overlay is not None:     # kept out of the solve by `thermod deblur` (restore.overlay)
            w.put(OVERLAY_DATASET, full_resolution(track.overlay, calib.width, calib.height))
        m = motion_attrs(track)
        if tau_fit is not None:
            m["tau_fit"] = json.dumps(jsonable(tau_fit.to_dict()), allow_nan=False)
        w.set_attrs(MOTION_GROUP, m)
        w.set_attrs("import", attrs)
        return w.commit(calib)
    except BaseException:
        w.abort()
        raise


def motion_attrs(track: RotationTrack) -> dict:
    """The /motion attributes: where the gyro came from and what the track flagged."""
    return {"source": SOURCE, "lag_s": float(track.lag_s),
            "note": "gyro estimated from the pictures (thermod.motion.track): camera-frame rate, 1σ per "
                    "sample in motion/sigma_rad_s; no samples where the motion is unknown",
            "track": json.dumps(jsonable(track.to_dict()), allow_nan=False)}


def plot_track(track: RotationTrack, gyro_t, gyro_rate, path, truth: tuple | None = None) -> None:
    """PNG: the estimated camera-frame rate per axis (the sampled spline, and each interval's mean
    rate at its middle), flagged frames marked; with `truth` = (t, rate), the true rate beside."""
    import math

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    deg = 180.0 / math.pi
    fig, axes = plt.subplots(3, 1, figsize=(11, 7), sharex=True, constrained_layout=True)
    tm = 0.5 * (track.frame_t[1:] + track.frame_t[:-1]) - track.lag_s
    mean = track.rate_at_frames()
    for a, (ax, name) in enumerate(zip(axes, ("x (right)", "y (down)", "z (forward)"), strict=True)):
        if truth is not None:
            ax.plot(truth[0], truth[1][:, a] * deg, lw=1.0, color="k", alpha=0.6, label="true gyro")
        ax.plot(gyro_t, gyro_rate[:, a] * deg, ".", ms=1, color="C0", label="from the video (1 kHz)")
        ax.plot(tm, mean[:, a] * deg, "o", ms=3, color="C1", label="interval mean")
        for what, color in (("duplicate", "C2"), ("cut", "C3"), ("untracked", "C4"), ("gap", "C5")):
            for i, k in enumerate(track.flagged()[what]):
                ax.axvline(track.frame_t[k], color=color, lw=0.8, ls="--", label=what if i == 0 and a == 0
                           else None)
        ax.set_ylabel(f"ω {name} (°/s)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("video time (s)")
    fig.savefig(path, dpi=90)
    plt.close(fig)
