"""A flight from other tools — a thermal video and a flight-controller log — → a synced format-v1
recording that `thermod deblur` and `thermod discrepancy` take.

`import_flight` reads the video (`thermod.io.video`: container timestamps, variable frame rate
included) and the log (`thermod.io.flightlog`), finds where the video sits in the log and how the
camera is mounted from the pictures alone (`thermod.sync`), optionally refines offset, mount,
gyro bias, readout and τ with the motion-only discrepancy workflow on the stretch that turns most
(`thermod.sync.discrepancy`; when it names the readout or τ but not the offset, the sync's fine
stage is run again with them, as the offset it found absorbed their lag), and writes the recording:

- ``/camera/frames``: the video's frames as delivered (8-bit AGC'd frames widened to uint16, values
  0–255, so a deblurred frame maps back to the same 8-bit scale); ``/camera/t`` the video's times;
- ``/gyro/t``: the log's samples around the video, moved onto the video clock (t_log + offset, so the
  calibration's ``time_offset_s`` is 0: a log offset is often minutes, beyond its ±1 s range);
  ``/gyro/rate`` the raw rates in the flight controller's frame; the calibration carries the mount
  (``R_cam_gyro``), bias and readout the sync found, the camera's intrinsics, frame rate and τ;
- ``/import`` attributes: where it came from (files, formats, the video's bit depth and AGC, the log's
  offset to the video) and the sync's result as JSON, with uncertainties.

Per-frame AGC is left in the frames: a blur kernel sums to one, so a frame's own gain and offset
commute with its deblurring; the sync normalises each frame before tracking, and the discrepancy
stage undoes the AGC (`thermod.motion.agc`) because its forward model needs one count scale.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from thermod.errors import ThermodError
from thermod.ingest.camera_video import put_frames_and_gyro, read_camera_video
from thermod.io import flightlog, video
from thermod.io.json_safe import jsonable
from thermod.io.recording import Writer
from thermod.motion.picture import MotionError
from thermod.physics.calibration import Calibration
from thermod.physics.kernels.grids import kernel_span_s
from thermod.sync.errors import DurationMismatch, LogMismatch, SyncError
from thermod.sync.fine import refine as refine_fine
from thermod.sync.plots import plot_sync
from thermod.sync.result import SyncResult, synchronise

GYRO_MARGIN_S = 1.0          # log kept before the first and after the last frame (≫ the 5τ window)
MIN_LOG_RATE_HZ = 100.0      # below it a log's samples are too sparse for a blur kernel of a few ms
# how each family's log reaches MIN_LOG_RATE_HZ (ArduPilot's IMU message is 25 Hz unless asked)
RATE_ADVICE = {"ardupilot": "ArduPilot logs IMU at 25 Hz by default; set LOG_BITMASK's IMU_FAST bit (bit 18) "
                            "to log it at the loop rate",
               "betaflight": "raise the blackbox logging rate"}
# when neither the whole video nor a part of it was found in the log, the user may know where it is
PART_HINT = (". If the video runs before or after the log (a flight controller often logs only while "
             "armed), import the part of it the log covers with --start S --duration D")


class FlightImportError(ThermodError):
    """A video and a log that cannot be made into one recording: names both and what was wrong."""


@dataclass
class ImportedFlight:
    """What `import_flight` wrote and found."""

    path: Path
    calibration: Calibration
    sync: SyncResult
    refinement: dict | None
    n_frames: int
    n_gyro: int
    video_info: video.VideoInfo
    log_format: str
    log_offset_s: float               # t_log = t_video + log_offset_s
    notes: list[str] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)

    def report(self) -> dict:
        """The import's report (strict JSON once through `jsonable`)."""
        c = self.calibration
        return jsonable({
            "recording": str(self.path), "frames": self.n_frames, "gyro_samples": self.n_gyro,
            "video": {"path": self.video_info.path, "size": [self.video_info.width, self.video_info.height],
                      "bit_depth": self.video_info.bit_depth, "codec": self.video_info.codec},
            "log": {"format": self.log_format},
            "log_offset_s": self.log_offset_s,
            "sync": self.sync.to_dict(),
            "refinement": self.refinement,
            "calibration": c.as_dict(),
            "notes": self.notes, "seconds": self.seconds,
        })


def import_flight(video_path: str | os.PathLike, log_path: str | os.PathLike, out: str | os.PathLike,
                  camera: Calibration, *, fps: float | None = None, log_index: int | None = None,
                  refine: bool = False, refine_windows: int = 1, report_dir: str | os.PathLike | None = None,
                  max_bytes: int = video.DEFAULT_MAX_BYTES, start_s: float = 0.0,
                  duration_s: float | None = None,
                  say: Callable[[str], None] | None = None) -> ImportedFlight:
    """Read, sync, refine and write one flight (module docstring). `camera` gives the intrinsics, τ
    and readout as far as known (`thermod.io.camera_file`); `fps` is needed only for a TIFF sequence.
    `start_s` and `duration_s` import a part of the video (seconds after its first frame): a long
    flight whose frames would not fit in `max_bytes`.
    With `report_dir`, writes ``sync.json`` and ``sync.png`` (gyro vs picture rotation before and
    after the sync) there. Raises a ThermodError naming the file and what was wrong; nothing is
    written then."""
    say = say or (lambda _msg: None)
    t_start = time.perf_counter()
    cv = read_camera_video(video_path, camera, FlightImportError, "a sync needs a video of several seconds",
                           fps=fps, max_bytes=max_bytes, start_s=start_s, duration_s=duration_s)
    vf, camera, period, notes = cv.frames, cv.camera, cv.period_s, cv.notes
    info, rate, readout = vf.info, 1.0 / period, camera.readout_s
    t_read = time.perf_counter()
    say(f"video: {len(vf.t)} frames of {info.width}×{info.height} ({info.bit_depth}-bit {info.codec}), "
        f"{vf.t[-1] - vf.t[0]:.1f} s at {rate:.3g} fps")

    log = flightlog.read_flight_log(log_path, log_index)
    say(f"log: {log.source_format}, {len(log)} gyro samples at {log.rate_hz:.0f} Hz over "
        f"{log.duration_s:.1f} s" + (f" (log {log.log_index + 1} of {log.n_logs})" if log.n_logs > 1 else ""))
    if log.rate_hz < MIN_LOG_RATE_HZ:
        advice = RATE_ADVICE.get(log.source_format, "raise the flight controller's logging rate")
        raise FlightImportError(f"{log_path}: gyro logged at {log.rate_hz:.3g} Hz; a flight import needs "
                                f"≥ {MIN_LOG_RATE_HZ:g} Hz ({advice})")
    t_log = time.perf_counter()

    intr = camera.intrinsics
    try:
        result = synchronise(vf.frames, vf.t, log.t, log.rate, intr, tau_s=camera.tau_s, readout_s=readout)
    except (SyncError, MotionError) as e:      # the sync works on arrays: say which files
        hint = PART_HINT if isinstance(e, (LogMismatch, DurationMismatch)) else ""
        raise FlightImportError(f"{video_path} with {log_path}: {e}{hint}") from None
    t_sync = time.perf_counter()
    if result.frames is not None:       # the log covers a part of the video: the rest is left out
        i0, i1 = result.frames
        notes.append(f"the log covers frames {i0}–{i1 - 1} of {len(vf.t)} ({vf.t[i0] - vf.t[0]:.2f}–"
                     f"{vf.t[i1 - 1] - vf.t[0]:.2f} s of the video); the others were left out")
        vf = dataclasses.replace(vf, frames=vf.frames[i0:i1], t=vf.t[i0:i1])
    d = result.to_dict()
    say(f"sync: video at log time {vf.t[0] - result.time_offset_s:.3f} s "
        f"(offset {result.time_offset_s:+.4f} ± {d['time_offset_s']['sigma'] * 1e3:.2f} ms), mount "
        f"{d['mount']}, correlation {d['ncc']:.3f}")

    changes = result.calibration_changes()
    refinement = None
    offset = result.time_offset_s
    if refine:
        from thermod.sync.discrepancy import refine_with_discrepancy

        ref = refine_with_discrepancy(vf.frames, vf.t, log.t, log.rate, result, intr, windows=refine_windows,
                                      agc=info.bit_depth == 8)
        refinement = ref.to_dict()
        s = ref.summary()
        offset = float(s["time_offset_s"]["value"])
        changes.update(R_cam_gyro=tuple(tuple(float(v) for v in row) for row in s["R_cam_gyro"]["value"]),
                       bias_rad_s=tuple(float(v) for v in s["gyro_bias_rad_s"]["value"]),
                       readout_s=min(float(s["readout_s"]["value"]), 0.99 * period),
                       tau_s=float(s["tau_s"]["value"]))
        named = set(sum(ref.named, []))
        if "time_offset" not in named and {"rolling_readout", "time_constant"} & named:
            # the sync's offset absorbed the picture's lag for the readout and τ it was given (½ readout
            # + τ); with the refined ones its fine stage places the video again (offset, and the mount's
            # misalignment and the bias unless the workflow named them)
            fine = refine_fine(result.picture, log.t, log.rate, result.coarse, tau_s=changes["tau_s"],
                               readout_s=changes["readout_s"], mounts=(result.mount_index,))
            offset = fine.time_offset_s
            if "misalignment" not in named:
                changes["R_cam_gyro"] = tuple(tuple(float(v) for v in row) for row in fine.R_cam_gyro)
            if "gyro_bias" not in named:
                changes["bias_rad_s"] = tuple(float(v) for v in fine.bias_rad_s)
            refinement["fine_sync_again"] = {"time_offset_s": {"value": fine.time_offset_s,
                                                               "sigma": fine.time_offset_sigma_s},
                                             "R_cam_gyro": fine.R_cam_gyro.tolist(),
                                             "gyro_bias_rad_s": fine.bias_rad_s.tolist()}
        unsure = sorted({a["label"] for stretch in ref.ambiguous for a in stretch})
        unsure += sorted({f"{u['effect']} {u['param']} not resolved" for stretch in ref.identifiability
                          for u in stretch.get("unresolved", [])})
        say(f"refined on {refine_windows} stretch(es): named {', '.join(sum(ref.named, [])) or 'nothing'}"
            + (f" ({'; '.join(unsure)}: not applied)" if unsure else "") + "; "
            f"offset {offset:+.4f} s, readout {changes['readout_s'] * 1e3:.2f} ms, "
            f"τ {changes['tau_s'] * 1e3:.2f} ms")
    t_refine = time.perf_counter()

    calib = camera.replace(rate_hz=log.rate_hz, **changes)
    gt = log.t + offset                          # onto the video clock
    g0, g1 = np.searchsorted(gt, [vf.t[0] - GYRO_MARGIN_S - kernel_span_s(camera), vf.t[-1] + GYRO_MARGIN_S])
    path = _write(out, vf, gt[g0:g1], log.rate[g0:g1], calib, {
        "video": str(video_path), "video_codec": info.codec, "video_bit_depth": info.bit_depth,
        "video_luma_only": info.luma_only,
        "video_full_range": info.full_range, "log": str(log_path), "log_format": log.source_format,
        "log_frame": log.frame, "log_offset_s": -offset, "log_index": log.log_index,
        "agc": "per-frame AGC left in the frames" if info.bit_depth == 8 else "none assumed (16-bit)",
    }, result, refinement)
    t_write = time.perf_counter()
    seconds = {"read_video": t_read - t_start, "read_log": t_log - t_read, "sync": t_sync - t_log,
               "refine": t_refine - t_sync, "write": t_write - t_refine}
    imported = ImportedFlight(path, calib, result, refinement, len(vf.t), int(g1 - g0), info,
                              log.source_format, -offset, notes, seconds)
    if report_dir is not None:
        rd = Path(report_dir)
        rd.mkdir(parents=True, exist_ok=True)
        (rd / "sync.json").write_text(json.dumps(imported.report(), indent=2, allow_nan=False) + "\n")
        plot_sync(result, log.t, log.rate, rd / "sync.png")
    return imported


def _write(out, vf: video.VideoFrames, gyro_t, gyro_rate, calib: Calibration, attrs: dict,
           result: SyncResult, refinement: dict | None) -> Path:
    if len(gyro_t) < 2:
        raise FlightImportError(f"{attrs['log']}: no gyro samples around the video after the sync")
    w = Writer(out)
    try:
        put_frames_and_gyro(w, vf, gyro_t, gyro_rate, calib)
        w.set_attrs("import", {**attrs, "sync": json.dumps(jsonable(result.to_dict()), allow_nan=False),
                               "refinement": json.dumps(jsonable(refinement), allow_nan=False)})
        return w.commit(calib)
    except BaseException:
        w.abort()
        raise
