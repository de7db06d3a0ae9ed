"""A thermal video read for an ingest, checked against the camera that shot it (`read_camera_video`):
its size must be the camera's, it needs two frames or more, and its own frame rate (the median frame
interval of its container timestamps) replaces the camera file's, with a note when they differ by more
than `FRAME_RATE_TOLERANCE`, and the readout is held within one frame period. A frame much closer to
the one before than the median interval (`MIN_INTERVAL_SHARE`), or a median rate over a camera's, is
refused: a time that repeats or goes back, moved one tick on by the muxer (MP4 and NUT do). Of a
file's several video streams the one of the camera's size is read (else the one a player would
play), with a note; the reader's notes (a cut, a rotation) are passed on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from thermod.io import video
from thermod.physics.calibration import RANGES, Calibration

FRAME_RATE_TOLERANCE = 0.05   # the video's rate may differ this much from the camera file's before a note
MIN_INTERVAL_SHARE = 0.1      # a frame interval under this × the median is a timestamp, not a frame period


@dataclass
class CameraVideo:
    """The frames, the camera at the video's own rate, and what differed from its description."""

    frames: video.VideoFrames
    camera: Calibration
    period_s: float
    notes: list[str]


def read_camera_video(video_path, camera: Calibration, error: type[Exception], needs: str, *,
                      fps: float | None = None, max_bytes: int = video.DEFAULT_MAX_BYTES,
                      start_s: float = 0.0, duration_s: float | None = None) -> CameraVideo:
    """Read `video_path` for `camera`; every refusal is an `error` naming the file (`needs` says what the
    ingest needs the frames for, e.g. "a sync needs a video of several seconds")."""
    # of several video streams, the camera's size tells the thermal one
    probed = video.probe_video(video_path, fps)
    fits = [i for i, w, h in probed.video_streams if (w, h) == (camera.width, camera.height)]
    chosen = probed.stream_index if probed.kind == "video" else None
    try:
        vf = video.read_video(video_path, fps=fps, max_bytes=max_bytes, start_s=start_s,
                              duration_s=duration_s,
                              stream=fits[0] if fits and chosen not in fits else None)
    except video.VideoTooLarge as e:
        raise error(f"{e}: import a part of it with --start S --duration D (seconds of video)") from None
    info = vf.info
    if (info.width, info.height) != (camera.width, camera.height):
        raise error(f"{video_path}: {info.width}×{info.height} px, but the camera description is for "
                    f"{camera.width}×{camera.height} px")
    if len(vf.t) < 2:
        raise error(f"{video_path}: {len(vf.t)} frame(s); {needs}")
    period = _frame_period(video_path, vf.t, error)
    rate = 1.0 / period
    notes = list(vf.notes)
    if len(info.video_streams) > 1:
        notes.append(f"the file holds {len(info.video_streams)} video streams ("
                     + ", ".join(f"#{i} {w}×{h}" for i, w, h in info.video_streams)
                     + f"): #{info.stream_index} is read")
    if abs(rate - camera.frame_rate_hz) > FRAME_RATE_TOLERANCE * camera.frame_rate_hz:
        notes.append(f"the video runs at {rate:.3g} fps, the camera description says "
                     f"{camera.frame_rate_hz:.3g}: the video's rate is used")
    camera = camera.replace(frame_rate_hz=rate, readout_s=min(camera.readout_s, 0.99 * period))
    return CameraVideo(vf, camera, period, notes)


def _frame_period(video_path, t: np.ndarray, error: type[Exception]) -> float:
    """The median frame interval (s), once every interval is a plausible frame period (module
    docstring)."""
    dt = np.diff(t)
    period = float(np.median(dt))
    top = RANGES["frame_rate_hz"][1]
    if not period >= 1.0 / top:
        raise error(f"{video_path}: the frames are {period * 1e3:.3g} ms apart at the median "
                    f"({1.0 / period:.6g} fps, over the {top:g} fps of a camera): timestamps that repeat, "
                    "moved one tick apart by the muxer? expected one frame per frame interval")
    short = np.flatnonzero(dt < MIN_INTERVAL_SHARE * period)
    if len(short):
        k = int(short[0]) + 1
        raise error(f"{video_path}: frame {k} at {t[k]:.6f} s comes {dt[k - 1] * 1e3:.3g} ms after frame "
                    f"{k - 1}, under {MIN_INTERVAL_SHARE:g} of the median frame interval "
                    f"({period * 1e3:.3g} ms); {len(short)} such frame(s): a repeated or backward timestamp "
                    "that the muxer moved one tick on? expected one frame per frame interval")
    return period


def put_frames_and_gyro(w, vf: video.VideoFrames, gyro_t, gyro_rate, calib: Calibration) -> None:
    """Write the video's frames (widened to uint16) and the gyro into a recording `Writer` `w`."""
    w.reserve("camera/frames", len(vf.t), (calib.height, calib.width), np.uint16)
    for frame, t in zip(vf.frames, vf.t, strict=True):
        w.append_frame(frame.astype(np.uint16, copy=False), float(t))
    w.put("gyro/t", np.asarray(gyro_t, np.float64))
    w.put("gyro/rate", np.asarray(gyro_rate, np.float32))
