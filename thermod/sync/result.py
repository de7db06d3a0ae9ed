"""`synchronise`: picture motion, coarse and fine sync in one call, and what they found (`SyncResult`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from thermod.motion.picture import PictureMotion, check_motion, picture_motion
from thermod.physics.geometry import Intrinsics
from thermod.sync.coarse import MOUNTS, CoarseSync, coarse_sync, covered_part
from thermod.sync.errors import DurationMismatch, LogMismatch, SyncInputError
from thermod.sync.fine import FineSync, refine
from thermod.sync.gyro import _check_arrays


@dataclass
class SyncResult:
    """What `synchronise` found. Conventions as the calibration's (docs/design.md §2):
    ω_cam = R_cam_gyro (ω_gyro − bias), t_cam = t_gyro + time_offset_s.

    The mount's margin is given twice: the correlation of the best mount over the runner-up's
    (`CoarseSync.mount_margin`), and the ratio of the runner-up's fit cost to the chosen one's
    (`mount_cost_ratio`; inf when only one mount came close enough to be fitted)."""

    coarse: CoarseSync
    fine: FineSync
    motion: dict
    picture: PictureMotion
    seconds: dict = field(default_factory=dict)
    tau_s: float = 0.0              # as given (the sync does not fit it)
    readout_given_s: float = 0.0    # as given; the fitted value is `fine.readout_s`
    frames: tuple[int, int] | None = None   # the frames [i0, i1) the log covers, when not all of them

    @property
    def time_offset_s(self) -> float:
        return self.fine.time_offset_s

    @property
    def mount_index(self) -> int:
        return self.fine.mount_index

    @property
    def mount(self) -> np.ndarray:
        return MOUNTS[self.fine.mount_index]

    @property
    def R_cam_gyro(self) -> np.ndarray:
        return self.fine.R_cam_gyro

    @property
    def mount_cost_ratio(self) -> float:
        others = [c for i, c in self.fine.mount_costs.items() if i != self.fine.mount_index]
        return min(others) / self.fine.cost if others and self.fine.cost > 0 else math.inf

    def camera_clock(self, gyro_t) -> np.ndarray:
        """Gyro sample times moved onto the video clock by the offset (t + time_offset_s): a recording's
        `/gyro/t`, whose calibration then needs `time_offset_s` = 0 (`calibration_changes`; its range is
        ±1 s) and carries the drift about the video's middle (`clock_drift_ppm`, `clock_epoch_s`)."""
        return np.asarray(gyro_t, np.float64) + self.fine.time_offset_s

    def calibration_changes(self) -> dict:
        """Keyword arguments for `Calibration.replace`: the synced gyro chain, for gyro times already
        on the video clock (`camera_clock`)."""
        period = float(np.median(self.picture.t1 - self.picture.t0))
        return {"time_offset_s": 0.0,
                "R_cam_gyro": tuple(tuple(float(v) for v in row) for row in self.fine.R_cam_gyro),
                "bias_rad_s": tuple(float(v) for v in self.fine.bias_rad_s),
                "readout_s": min(float(self.fine.readout_s), 0.99 * period),
                "clock_drift_ppm": float(self.fine.clock_drift_ppm),
                "clock_epoch_s": float(self.fine.clock_epoch_video_s)}

    def to_dict(self) -> dict:
        c, f = self.coarse, self.fine
        ratio = self.mount_cost_ratio
        return {
            "time_offset_s": {"value": f.time_offset_s, "sigma": f.time_offset_sigma_s,
                              "lag_bound": f.lag_bound_s},
            "coarse_time_offset_s": c.time_offset_s,
            "mount": self.mount.astype(int).tolist(),
            "mount_index": f.mount_index,
            "frames_covered": list(self.frames) if self.frames is not None else None,
            "ncc": c.ncc, "ncc_second_mount": c.ncc_second_mount,
            "second_mount": MOUNTS[c.second_mount_index].astype(int).tolist(),
            "mount_margin_ncc": c.mount_margin,
            "mount_cost_ratio": ratio if math.isfinite(ratio) else None,
            "ncc_elsewhere": c.ncc_elsewhere,
            "misalignment_rad": {"value": f.misalignment_rad.tolist(),
                                 "sigma": f.misalignment_sigma_rad.tolist()},
            "R_cam_gyro": f.R_cam_gyro.tolist(),
            "gyro_bias_rad_s": {"value": f.bias_rad_s.tolist(), "sigma": f.bias_sigma_rad_s.tolist()},
            "clock_drift_ppm": {"value": f.clock_drift_ppm, "epoch_video_s": f.clock_epoch_video_s,
                                "sigma": (f.clock_drift_sigma_ppm if math.isfinite(f.clock_drift_sigma_ppm)
                                          else None)},
            "readout_s": {"value": f.readout_s,
                          "sigma": f.readout_sigma_s if math.isfinite(f.readout_sigma_s) else None},
            "tau_s": {"value": self.tau_s, "sigma": None, "note": "as given; see sync_discrepancy"},
            "residual_rms_rad_s": f.residual_rms_rad_s, "picture_rms_rad_s": f.picture_rms_rad_s,
            "intervals": f.n_intervals, "motion": self.motion, "grid_s": c.grid_s,
            "uncertainty": "sigma: delete-one-block jackknife over 8 contiguous stretches of the video; "
                           "lag_bound: the offset's systematic bound from the picture's apparent lag (tau/2)",
            "seconds": self.seconds,
        }


def synchronise(frames, frame_t, gyro_t, gyro_rate, intrinsics: Intrinsics, *, tau_s: float = 0.0,
                readout_s: float = 0.0, work_width: int = 160, smooth_px: float = 1.5,
                progress=None) -> SyncResult:
    """Find where a video sits in a gyro log and how the camera is mounted (module docstring).

    frames [N, H, W] grey (8- or 16-bit, AGC allowed); frame_t [N] s on the video clock (a frame's
    time: its last row read); gyro_t [M] s on the log clock; gyro_rate [M, 3] rad/s in the flight
    controller's frame; `intrinsics` of the frames; `tau_s` and `readout_s` as far as known (0: none).
    `frames` may also be any sequence of [H, W] frames with len() and indexing (a lazy reader: one
    frame is read at a time). Raises `TooLittleMotion` or a `SyncError` subclass naming what was wrong."""
    lazy = hasattr(frames, "__len__") and hasattr(frames, "__getitem__")
    if not isinstance(frames, np.ndarray) and not lazy:
        frames = np.asarray(frames)
    n = len(frames)
    shape = (n, *np.shape(frames[0])) if n else np.shape(frames)
    if len(shape) != 3 or shape[1] < 16 or shape[2] < 16:
        raise SyncInputError(f"frames: expected [N, H, W] grey frames of ≥ 16×16 px, got shape {shape}")
    if (shape[2], shape[1]) != (intrinsics.width, intrinsics.height):
        raise SyncInputError(f"frames: {shape[2]}×{shape[1]} px but the intrinsics describe "
                             f"{intrinsics.width}×{intrinsics.height}")
    if not (0 <= tau_s <= 1 and 0 <= readout_s <= 1):
        raise SyncInputError(f"tau_s {tau_s!r}, readout_s {readout_s!r}: expected 0–1 s")
    t, gt, gr = _check_arrays(frame_t, gyro_t, gyro_rate, len(frames))
    clock = time.perf_counter
    t0 = clock()
    pm = picture_motion(frames, t, intrinsics, work_width=work_width, smooth_px=smooth_px, progress=progress)
    t1 = clock()
    stats = check_motion(pm)
    part = None
    try:
        coarse = coarse_sync(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
    except (DurationMismatch, LogMismatch):
        part = covered_part(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
        if part is None:
            raise
        pm = pm.sliced(*part)
        coarse = coarse_sync(pm, gt, gr, tau_s=tau_s, readout_s=readout_s)
    t2 = clock()
    fine = refine(pm, gt, gr, coarse, tau_s=tau_s, readout_s=readout_s)
    t3 = clock()
    return SyncResult(coarse, fine, stats, pm, {"picture": t1 - t0, "coarse": t2 - t1, "fine": t3 - t2},
                      tau_s, readout_s, part)
