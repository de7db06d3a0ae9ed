"""A simulated flight as another tool would hand it over: an AGC'd 8-bit H.264 thermal video and a
flight-controller gyro log in a real format, with the truth that links them kept aside.

`simulate_flight(out_dir, ...)` renders a `thermod.sim.synth.simulate` recording and writes
``video.mp4`` (the raw counts through `thermod.io.video.PercentileAGC`, timestamps from 0 at the
first frame), the gyro log of a longer flight in which the video sits at a hidden place
(``log.gcsv``, ``log.csv`` Betaflight CSV, ``log.bin`` ArduPilot DataFlash, each read by
`thermod.io.flightlog.read_flight_log`) and ``truth.json``: what the sync must find.

The hidden truth: a multirotor-like motion in the FRD body frame seen through one of the 24
axis-aligned mounts (``mount_index``, ``camera_from_body``), and the log's clock placed so that

    t_log = t_video + log_offset_s            (calibration convention: time_offset_s = −log_offset_s)

The clocks and the motion in full: docs/design.md §3, "Simulated flights".
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from thermod.errors import ThermodError
from thermod.io import flightlog, video
from thermod.io.recording import Recording
from thermod.physics.calibration import Calibration
from thermod.physics.effects import ALIASES, GYRO_SIDE
from thermod.sim import motion as mo

LOG_FORMATS = {"gcsv": "log.gcsv", "betaflight-csv": "log.csv", "ardupilot": "log.bin"}
GYRO_SIDE_EFFECTS = GYRO_SIDE | set(ALIASES)      # an alias names a gyro-side effect too


class MountedMotion(mo.Motion):
    """A body-frame (FRD) motion seen by a camera mounted by `camera_from_body`: the camera-frame
    rate the simulator renders is camera_from_body · ω_body(t)."""

    def __init__(self, body: mo.Motion, camera_from_body: np.ndarray):
        self.body, self.camera_from_body = body, np.asarray(camera_from_body, dtype=np.float64)
        self.spec = f"mounted({body.spec})"

    def omega(self, t) -> np.ndarray:
        return self.body.omega(t) @ self.camera_from_body.T


@dataclass
class SimulatedFlight:
    """The written files and the truth (module docstring). `recording` is the simulated recording
    (uint16 counts on the simulator's own clock, frames at `recording.t`, with its truth extras:
    recording.t[k] − recording.t[0] = frame_t_video[k] − frame_t_video[0]); `frame_t_video` the
    video's frame times as `read_video` reads them; `agc_gain`/`agc_offset` each frame's stretch
    (8-bit = (counts − offset) · gain, also in truth.json), to put the truth in the video's scale."""

    video_path: Path
    log_paths: dict[str, Path]
    log_offset_s: float
    camera_from_body: np.ndarray
    mount_index: int
    log_start_s: float
    video_start_s: float
    log_seconds: float
    gyro_rate_hz: float
    frame_t_video: np.ndarray
    agc_gain: np.ndarray
    agc_offset: np.ndarray
    recording: Recording
    truth_path: Path
    body_t_log: np.ndarray = field(repr=False)          # the log's sample times (s, log clock)
    body_rate: np.ndarray = field(repr=False)           # the true FRD body rates there (rad/s, noise-free)
    gyro_bias_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))   # added to the log (FRD)

    @property
    def time_offset_s(self) -> float:
        """The offset in the calibration's convention (docs/design.md §2): t_cam = t_gyro + time_offset_s."""
        return -self.log_offset_s


def simulate_flight(out_dir: str | os.PathLike, *, seconds: float = 3.0, log_seconds: float = 20.0,
                    width: int = 160, height: int = 120, fps: float = 30.0, hfov_deg: float = 50.0,
                    tau_s: float = 0.008, gyro_rate_hz: float = 1000.0, gyro_noise_deg_s: float = 0.1,
                    body_rms_deg_s: tuple = (30.0, 25.0, 12.0), scene: str = "texture",
                    mount: int | np.ndarray | None = None, video_start_s: float | None = None,
                    log_start_s: float = 37.25, formats: tuple = ("gcsv", "betaflight-csv"),
                    crf: int = 18, seed: int = 0, agc: video.PercentileAGC | None = None,
                    effects: dict | None = None, gyro_bias_rad_s=(0.0, 0.0, 0.0),
                    body: mo.Motion | None = None) -> SimulatedFlight:
    """Simulate and write a flight (module docstring). `mount` is an index into the 24 axis-aligned
    rotations or a 3×3 rotation (default: drawn from `seed`); `video_start_s` the video's start in
    the log (default: drawn from `seed`, ≥ 1 s from either end); `formats` any of `LOG_FORMATS`.
    `effects` are `thermod.sim.synth` effects of the camera side (rolling_readout, time_constant,
    netd, …; the log is written here, so gyro-side effects are refused); `gyro_bias_rad_s` (FRD,
    rad/s) is added to every logged sample. `body` replaces the procedural body motion (e.g. a real
    log's, `thermod.sim.motion.gyro_log`; its time 0 is the first frame)."""
    from thermod.sim.synth import simulate

    out = Path(out_dir)
    if not out.is_dir():
        raise ThermodError(f"simulate_flight: directory {out} does not exist")
    unknown = set(formats) - set(LOG_FORMATS)
    if unknown or not formats:
        raise ThermodError(f"simulate_flight: formats {sorted(unknown) or '()'}: expected some of "
                           f"{sorted(LOG_FORMATS)}")
    if not (0 < seconds and seconds + 2.0 <= log_seconds <= 3600):
        raise ThermodError(f"simulate_flight: expected a log ≥ 2 s longer than the video and ≤ 1 h, got "
                           f"video {seconds} s, log {log_seconds} s")
    gyro_side = sorted(set(effects or {}) & GYRO_SIDE_EFFECTS)
    if gyro_side:
        raise ThermodError(f"simulate_flight: effects {gyro_side} act on the simulator's own gyro, not on "
                           "the written log; give the log's bias as gyro_bias_rad_s")
    bias = np.broadcast_to(np.asarray(gyro_bias_rad_s, dtype=np.float64), (3,))
    if not np.all(np.isfinite(bias)):
        raise ThermodError(f"simulate_flight: gyro_bias_rad_s {gyro_bias_rad_s!r}: expected finite rad/s")
    rng = np.random.default_rng([seed, 24])
    rotations = flightlog.axis_aligned_rotations()
    camera_from_body, mount_index = _mount(mount, rotations, rng)
    if video_start_s is None:
        video_start_s = float(rng.uniform(1.0, log_seconds - seconds - 1.0))
    if not 0 <= video_start_s <= log_seconds - seconds:
        raise ThermodError(f"simulate_flight: video_start_s {video_start_s}: the video must lie inside the "
                           f"{log_seconds} s log")

    body = body if body is not None else mo.flight(tuple(body_rms_deg_s), seed=seed)
    f = 1.0 / math.radians(hfov_deg / width)
    calib = Calibration().replace(width=int(width), height=int(height), fx=f, fy=f, cx=(width - 1) / 2,
                                  cy=(height - 1) / 2, frame_rate_hz=float(fps), tau_s=float(tau_s),
                                  rate_hz=float(gyro_rate_hz))
    # motion time 0 = the first frame = log time log_start_s + video_start_s
    rec = simulate(scene, MountedMotion(body, camera_from_body), seconds, calib, effects=effects, seed=seed,
                   truth=True)

    agc = agc or video.PercentileAGC()
    frames8, gains, offsets = [], [], []
    for frame, t in zip(rec.frames, rec.t, strict=True):
        y, g, o = agc.apply(frame, float(t))
        frames8.append(y)
        gains.append(g)
        offsets.append(o)
    video_path = video.write_video(out / "video.mp4", np.stack(frames8), rec.t - rec.t[0], crf=crf)
    t_read = np.array([t for t, _ in video.iter_video(video_path)])
    if len(t_read) != rec.n_frames:
        raise ThermodError(f"{video_path}: wrote {rec.n_frames} frames, read back {len(t_read)}")
    # the container may shift all times by a constant (an edit list): the truth follows what is read
    log_offset = log_start_s + video_start_s - float(t_read[0])

    t_log = log_start_s + np.arange(int(round(log_seconds * gyro_rate_hz))) / gyro_rate_hz
    w_body = body.omega(t_log - (log_start_s + video_start_s))
    noise = np.random.default_rng([seed, 25]).standard_normal(w_body.shape)
    noisy = w_body + bias + math.radians(gyro_noise_deg_s) * noise
    log_paths = {}
    for fmt in formats:
        path = out / LOG_FORMATS[fmt]
        if fmt == "gcsv":
            flightlog.write_gcsv(path, t_log, noisy, note="thermod simulated flight")
        elif fmt == "betaflight-csv":
            flightlog.write_betaflight_csv(path, t_log, noisy)
        else:
            flightlog.write_ardupilot_bin(path, t_log, noisy)
        log_paths[fmt] = path

    result = SimulatedFlight(video_path, log_paths, log_offset, camera_from_body, mount_index,
                             float(log_start_s), float(video_start_s), float(log_seconds),
                             float(gyro_rate_hz),
                             t_read, np.asarray(gains), np.asarray(offsets), rec, out / "truth.json",
                             t_log, w_body, bias.copy())
    _write_truth(result)
    return result


def _mount(mount, rotations: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    if mount is None:
        i = int(rng.integers(len(rotations)))
        return rotations[i].copy(), i
    if isinstance(mount, (int, np.integer)):
        if not 0 <= mount < len(rotations):
            raise ThermodError(f"simulate_flight: mount index {mount}: expected 0–{len(rotations) - 1}")
        return rotations[int(mount)].copy(), int(mount)
    m = np.asarray(mount, dtype=np.float64)
    if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-9) or np.linalg.det(m) < 0:
        raise ThermodError("simulate_flight: mount must be a 3×3 proper rotation or an index 0–23")
    d = np.abs(rotations - m).sum(axis=(1, 2))
    return m, int(np.argmin(d)) if d.min() < 1e-9 else -1


def _write_truth(sim: SimulatedFlight) -> None:
    truth = {
        "log_offset_s": sim.log_offset_s,
        "time_offset_s": sim.time_offset_s,
        "convention": "t_log = t_video + log_offset_s; omega_camera = camera_from_body @ omega_body (FRD)",
        "camera_from_body": sim.camera_from_body.tolist(),
        "mount_index": sim.mount_index,
        "log_start_s": sim.log_start_s,
        "video_start_s": sim.video_start_s,
        "log_seconds": sim.log_seconds,
        "gyro_rate_hz": sim.gyro_rate_hz,
        "gyro_bias_rad_s": sim.gyro_bias_rad_s.tolist(),
        "effects": {k: (list(v) if isinstance(v, tuple) else v)
                    for k, v in json.loads(sim.recording.extra_attrs["truth"]["effects_json"]).items()},
        "video": sim.video_path.name,
        "logs": {k: v.name for k, v in sim.log_paths.items()},
        "frames": int(len(sim.frame_t_video)),
        "agc_gain": sim.agc_gain.tolist(),
        "agc_offset": sim.agc_offset.tolist(),
        "calibration": {k: (list(v) if isinstance(v, tuple) else v)
                        for k, v in sim.recording.calibration.camera_attrs().items()},
    }
    sim.truth_path.write_text(json.dumps(truth, indent=2, default=float) + "\n")
