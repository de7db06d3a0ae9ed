"""The fine stage of a sync that needs the pictures themselves: the motion-only discrepancy workflow
(`thermod.calib.discrepancy`) on a stretch of the synced video.

The rotation-level fit of `thermod.sync.fine` cannot tell the offset from the picture's lag (½ the
readout time plus up to τ); the discrepancy workflow's forward model renders each frame through the
detector's response and the rolling readout, so on a format-v1 recording made from the synced video it
refines the time offset, the misalignment and the gyro bias, and names the readout time and τ when the
motion excites them. `discrepancy_recording` makes that recording: the stretch of `window_s` whose
picture rotates most, the AGC undone (`thermod.motion.agc`: the forward model needs one count scale),
the log's samples around it and the sync's calibration. `refine_with_discrepancy` runs the workflow on
it with `DISCREPANCY_CANDIDATES`. The workflow's identifiability check (issue 34) gives each
parameter's σ and the pairs the motion cannot tell apart: an `ambiguous` effect is reported, not
applied (its parameters stay at the sync's values). Running it on several disjoint stretches
(`windows`) also gives their spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from thermod.io.recording import Recording
from thermod.motion.agc import fit_agc
from thermod.physics.calibration import Calibration
from thermod.physics.geometry import Intrinsics
from thermod.sync.errors import SyncError
from thermod.sync.result import SyncResult

#: The candidates that refine what the sync found (and what it cannot).
DISCREPANCY_CANDIDATES = ("time_offset", "misalignment", "gyro_bias", "rolling_readout", "time_constant")
GYRO_LEAD_S = 0.3           # log before the stretch's first frame (the workflow's 5τ history and margins)
GYRO_TAIL_S = 0.1


def stretches(result: SyncResult, window_s: float, count: int = 1) -> list[tuple[int, int]]:
    """`count` disjoint frame ranges [i0, i1) of `window_s` whose picture rotates most (Σ‖φ‖²),
    in time order."""
    pm = result.picture
    t = np.r_[pm.t0, pm.t1[-1]]
    n_win = int(np.searchsorted(t, t[0] + window_s))
    if n_win < 4 or n_win > len(t):
        raise SyncError(f"discrepancy stretch: {window_s} s is not within the video's {t[-1] - t[0]:.2f} s "
                        "(need ≥ 4 frames)")
    e = np.where(pm.valid, np.sum(np.nan_to_num(pm.rotvec) ** 2, axis=1), 0.0)
    c = np.r_[0.0, np.cumsum(e)]
    score = c[n_win - 1:] - c[:len(c) - n_win + 1]          # intervals i0 … i0 + n_win − 2
    chosen: list[tuple[int, int]] = []
    for i0 in np.argsort(score)[::-1]:
        i0 = int(i0)
        if all(i0 + n_win <= a or i0 >= b for a, b in chosen):
            chosen.append((i0, i0 + n_win))
        if len(chosen) == count:
            break
    return sorted(chosen)


def discrepancy_recording(frames, frame_t, gyro_t, gyro_rate, result: SyncResult, intrinsics: Intrinsics,
                          *, frames_range: tuple[int, int] | None = None, window_s: float = 1.0,
                          agc: bool = True) -> Recording:
    """A format-v1 recording of one stretch of the synced video (module docstring): frames [i0, i1)
    (default the stretch of `window_s` that rotates most), the AGC undone to uint16 counts (`agc`;
    False: the frames are counts on one scale already and are kept as they are), the gyro
    samples from `GYRO_LEAD_S` before to `GYRO_TAIL_S` after it moved onto the video clock
    (`SyncResult.camera_clock`), and the sync's calibration."""
    t = np.asarray(frame_t, np.float64)
    gt = np.asarray(gyro_t, np.float64)
    i0, i1 = frames_range if frames_range is not None else stretches(result, window_s)[0]
    frames = np.stack([np.asarray(frames[i]) for i in range(i0, i1)])      # the stretch only
    if agc:
        fit = fit_agc(frames, result.picture.sliced(i0, i1), intrinsics)
        counts = fit.to_uint16(frames)
    else:
        counts = frames
        if counts.dtype != np.uint16:
            counts = np.clip(np.round(counts), 0, 65535).astype(np.uint16)
    off = result.time_offset_s
    g0, g1 = np.searchsorted(gt, [t[i0] - off - GYRO_LEAD_S, t[i1 - 1] - off + GYRO_TAIL_S])
    if g1 - g0 < 8:
        raise SyncError(f"discrepancy stretch: the log has {g1 - g0} samples around frames {i0}–{i1 - 1}")
    period = float(np.median(np.diff(t)))
    rate_hz = 1.0 / float(np.median(np.diff(gt[g0:g1])))
    cal = Calibration(width=intrinsics.width, height=intrinsics.height, fx=intrinsics.fx, fy=intrinsics.fy,
                      cx=intrinsics.cx, cy=intrinsics.cy, tau_s=result.tau_s, frame_rate_hz=1.0 / period,
                      rate_hz=rate_hz, **result.calibration_changes())
    rec = Recording(counts, t[i0:i1].copy(), result.camera_clock(gt[g0:g1]),
                    np.asarray(gyro_rate, np.float64)[g0:g1].astype(np.float32), cal)
    rec.validate("<synced video>")
    return rec


@dataclass
class DiscrepancyRefinement:
    """The workflow's values on each stretch, their mean and (with ≥ 2 stretches) standard error."""

    per_stretch: list[dict]
    named: list[list[str]]
    unexplained: list[bool]
    ambiguous: list[list[dict]] = field(default_factory=list)   # per stretch: the ambiguous entries
    identifiability: list[dict] = field(default_factory=list)   # per stretch: σ, ρ, each effect's test

    def summary(self) -> dict:
        out = {}
        for key in self.per_stretch[0]:
            v = np.array([d[key] for d in self.per_stretch], float)
            n = len(v)
            out[key] = {"value": v.mean(axis=0).tolist(),
                        "sigma": (v.std(axis=0, ddof=1) / math.sqrt(n)).tolist() if n > 1 else None}
        return out

    def to_dict(self) -> dict:
        return {"stretches": self.per_stretch, "named": self.named, "unexplained": self.unexplained,
                "ambiguous": self.ambiguous, "identifiability": self.identifiability,
                "summary": self.summary(),
                "uncertainty": "standard error of the mean over disjoint stretches (None for one)"}


def refine_with_discrepancy(frames, frame_t, gyro_t, gyro_rate, result: SyncResult, intrinsics: Intrinsics,
                            *, windows: int = 1, window_s: float = 1.0, candidates=DISCREPANCY_CANDIDATES,
                            work_width: int = 160, max_steps: int = 4, agc: bool = True,
                            progress=None) -> DiscrepancyRefinement:
    """Run the motion-only discrepancy workflow on `windows` disjoint stretches (module docstring)."""
    from thermod.calib.discrepancy import Model, analyse, prepare

    per, named, unexpl, ambiguous, ident = [], [], [], [], []
    for i0, i1 in stretches(result, window_s, windows):
        rec = discrepancy_recording(frames, frame_t, gyro_t, gyro_rate, result, intrinsics,
                                    frames_range=(i0, i1), agc=agc)
        data = prepare(rec, rec.calibration, name=f"synced video frames {i0}–{i1 - 1}", work_width=work_width)
        ana = analyse([data], Model(rec.calibration), candidates=candidates, max_steps=max_steps,
                      progress=progress)
        c = ana.calibration()        # an ambiguous effect's parameters left at the sync's values
        per.append({"time_offset_s": result.time_offset_s + c.time_offset_s,
                    "R_cam_gyro": np.asarray(c.R_cam_gyro_matrix).tolist(),
                    "gyro_bias_rad_s": list(c.bias_rad_s), "readout_s": c.readout_s, "tau_s": c.tau_s})
        named.append(ana.named)
        unexpl.append(bool(ana.unexplained))
        ambiguous.append(list(ana.ambiguous))
        ident.append(dict(ana.identifiability))
    return DiscrepancyRefinement(per, named, unexpl, ambiguous, ident)
