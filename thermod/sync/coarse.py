"""Coarse sync: where in a whole log a video sits, and the camera's axis-aligned mount.

The picture rate φ_k/Δt_k (piecewise constant on the video clock) and the gyro's rate (box means over a
uniform grid of step h from its cumulative integral, filtered by the detector's exponential response τ,
Eq. 10; a picture row is read `readout_s`·½ before the frame time on average) are cross-correlated by
FFT over the whole log, for all nine axis pairs at once; each of the 24 axis-aligned mounts M (entries
in {−1, 0, 1}, det +1; `MOUNTS`) is a signed sum of those nine. The normalised correlation (Pearson,
the gyro's window mean removed at every lag, so a gyro bias does not count) picks the lag and the
mount; a parabola through the peak refines the lag below h. Conventions: ω_cam = M ω_gyro,
t_cam = t_gyro + time_offset_s. A log in which no place correlates significantly, or two places
equally, is refused (`LogMismatch`); so is a log shorter than the video (`DurationMismatch`), unless a
part of the video is covered (`covered_part`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from thermod.motion.picture import MIN_INTERVALS, PictureMotion
from thermod.sync.errors import DurationMismatch, LogMismatch, SyncError
from thermod.sync.gyro import _exp_filter, _gyro_grid, cumulative_rotation

MIN_NCC = 0.75                # the correlation peak a log must reach (null peaks of a 3 s video: ≤ 0.63)
MIN_RESIDUAL_RATIO = 3.0      # the best place elsewhere must leave ≥ this × the peak's residual (1 − ρ²)
MIN_LOG_MOTION_RATIO = 0.2     # the log's best stretch must turn ≥ this × the video's picture rotation (RMS)
MAX_GRID_S = 0.005            # coarse correlation grid step
MAX_GRID_SAMPLES = 1_000_000  # ... and its length over the whole log (a 1.4 h log at 5 ms)
MIN_PART_S = 3.0              # the shortest part of a video a log may cover alone (see `covered_part`)
MIN_PART_FRACTION = 0.3       # ... and of the video's length
PART_SHRINK = 0.8             # the part searched is shortened by this factor until one is found
PART_MARGIN_S = 0.1           # log kept beyond a covered part's frames (τ tails, the fine search)


def _axis_aligned_rotations() -> tuple[np.ndarray, ...]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs, strict=True)):
                M[row, col] = s
            if round(np.linalg.det(M)) == 1:
                out.append(M)
    return tuple(out)


#: The 24 proper rotations with entries in {−1, 0, 1}, the identity first.
MOUNTS: tuple[np.ndarray, ...] = _axis_aligned_rotations()


@dataclass
class CoarseSync:
    """The whole-log correlation: offset, mount and how clearly they won.

    `lags_s` are candidate time offsets (t_cam = t_gyro + offset); `ncc[i]` the normalised correlation
    of mount i at each (for the figure)."""

    time_offset_s: float
    mount_index: int
    ncc: float
    ncc_second_mount: float
    second_mount_index: int
    ncc_elsewhere: float
    grid_s: float
    lags_s: np.ndarray
    ncc_curves: np.ndarray

    @property
    def mount(self) -> np.ndarray:
        return MOUNTS[self.mount_index]

    @property
    def mount_margin(self) -> float:
        return self.ncc - self.ncc_second_mount

    @property
    def residual_ratio(self) -> float:
        """(1 − ρ²) of the best place more than a second from the peak over that of the peak."""
        if self.ncc_elsewhere <= -1.0:
            return math.inf
        return (1.0 - max(self.ncc_elsewhere, 0.0) ** 2) / max(1.0 - self.ncc**2, 1e-12)


def coarse_sync(pm: PictureMotion, gyro_t, gyro_rate, *, tau_s: float = 0.0, readout_s: float = 0.0,
                grid_s: float | None = None) -> CoarseSync:
    """Offset and mount by the best normalised cross-correlation over the whole log (stage 2)."""
    from scipy.signal import correlate

    valid = pm.valid
    period = float(np.median(pm.t1 - pm.t0))
    shift = 0.5 * readout_s
    v_lo, v_hi = pm.t0[0] - shift, pm.t1[-1] - shift
    video_s, log_s = v_hi - v_lo, float(gyro_t[-1] - gyro_t[0])
    # the grid is at most MAX_GRID_SAMPLES long, so a long log coarsens it rather than the memory growing
    h = max(float(grid_s) if grid_s else min(MAX_GRID_S, period / 2.0), log_s / MAX_GRID_SAMPLES)
    if video_s > log_s:
        raise DurationMismatch(f"the video lasts {video_s:.2f} s but the gyro log only {log_s:.2f} s: the "
                               "log cannot contain the video (a log of another flight, or cut short?)")
    nv = int(math.floor(video_s / h)) + 1
    u = v_lo + np.arange(nv) * h
    k = np.clip(np.searchsorted(pm.t1 - shift, u, side="right"), 0, len(pm.t0) - 1)
    p = pm.rate[k]
    w = valid[k].astype(np.float64)
    p = np.where(w[:, None] > 0, p, 0.0)
    W = w.sum()
    p = (p - (w[:, None] * p).sum(axis=0) / W) * w[:, None]

    nl = int(math.floor(log_s / h)) + 1
    G = cumulative_rotation(gyro_t, gyro_rate)
    box = max(1, int(round(period / h)))
    g = _gyro_grid(gyro_t, G, float(gyro_t[0]), h, nl)
    g = _exp_filter(g, h, tau_s)
    if box > 1:             # the picture sees the mean rate over one frame interval
        kern = np.ones(box) / box
        g = np.stack([np.convolve(g[:, a], kern, mode="same") for a in range(3)], axis=1)
    if nl < nv:
        raise DurationMismatch(f"the video lasts {video_s:.2f} s but the gyro log only {log_s:.2f} s")
    C = np.empty((3, 3, nl - nv + 1))
    for i in range(3):
        for j in range(3):
            C[i, j] = correlate(g[:, j], p[:, i], mode="valid", method="fft")
    gm = np.stack([correlate(g[:, j], w, mode="valid", method="fft") for j in range(3)], axis=1) / W
    e2 = correlate((g**2).sum(axis=1), w, mode="valid", method="fft")
    energy = np.maximum(e2 - W * (gm**2).sum(axis=1), 0.0)
    norm = math.sqrt(float((p**2).sum())) * np.sqrt(energy)
    floor = 1e-9 * (float(norm.max()) if norm.size else 0.0)
    if not floor > 0:
        raise LogMismatch("gyro log: the rates never change over the video's length (a log without gyro "
                          "data, or all zeros)")
    # the log's rotation over each stretch as long as the video, against the picture's: a log that
    # barely turns anywhere cannot hold this video, and the correlation alone would only say "no match"
    gyro_rms, picture_rms = math.sqrt(float(energy.max()) / W), math.sqrt(float((p**2).sum()) / W)
    if gyro_rms < MIN_LOG_MOTION_RATIO * picture_rms:
        raise LogMismatch(f"gyro log: it turns at most {math.degrees(gyro_rms):.2g} °/s RMS over any "
                          f"stretch as long as the video, which turns {math.degrees(picture_rms):.2g} °/s: "
                          "too little gyro motion to find the video in it (a log recorded at rest, or "
                          "another flight's?)")
    mounts = np.stack(MOUNTS)
    curves = (np.einsum("mij,ijl->ml", mounts, C) / np.maximum(norm, floor)).astype(np.float32)
    curves[:, norm < floor] = 0.0
    best_per_mount = curves.max(axis=1)
    order = np.argsort(best_per_mount)[::-1]
    mi, m2 = int(order[0]), int(order[1])
    li = int(np.argmax(curves[mi]))
    rho = float(curves[mi, li])
    # elsewhere: any mount, lags further than one second (and five frame periods) from the peak
    reach = int(math.ceil(max(1.0, 5 * period) / h))
    far = np.abs(np.arange(curves.shape[1]) - li) > reach
    rho_far = float(curves[:, far].max()) if far.any() else -1.0
    frac = 0.0
    if 0 < li < curves.shape[1] - 1:
        y0, y1, y2 = (float(v) for v in curves[mi, li - 1:li + 2])
        den = y0 - 2 * y1 + y2
        frac = float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) if den < 0 else 0.0
    lags = (v_lo - float(gyro_t[0])) - np.arange(curves.shape[1]) * h
    offset = (v_lo - float(gyro_t[0])) - (li + frac) * h
    cs = CoarseSync(offset, mi, rho, float(best_per_mount[m2]), m2, rho_far, h, lags, curves)
    _check_significance(cs)
    return cs


def _check_significance(cs: CoarseSync) -> None:
    if cs.ncc < MIN_NCC:
        raise LogMismatch(f"gyro log: the video's rotation correlates with the log at best {cs.ncc:.2f} "
                          f"(need ≥ {MIN_NCC}): the log does not contain this video (another flight, or "
                          "a gyro not on the camera's frame)")
    if cs.residual_ratio < MIN_RESIDUAL_RATIO:
        raise LogMismatch(f"gyro log: two places fit the video about equally (correlation {cs.ncc:.3f} and "
                          f"{cs.ncc_elsewhere:.3f} more than a second apart: the second leaves only "
                          f"{cs.residual_ratio:.1f}× the unexplained rotation of the first, need ≥ "
                          f"{MIN_RESIDUAL_RATIO:g}×): the motion repeats, or the log does not contain the "
                          "video")


def covered_part(pm: PictureMotion, gyro_t, gyro_rate, *, tau_s: float = 0.0,
                 readout_s: float = 0.0) -> tuple[int, int] | None:
    """The frames [i0, i1) of a video that a log covers when it does not cover all of them (a flight
    controller that logs only while armed, a video running from power-up), or None.

    Parts of the video, as long as the log allows and then `PART_SHRINK` times shorter down to
    `MIN_PART_S` and `MIN_PART_FRACTION` of the video, are placed in the log by `coarse_sync` (each
    with its own significance tests); the longest length at which one is found wins, the best
    correlation among its parts. The frames whose comet tails (8 τ) and read times lie in the log
    with `PART_MARGIN_S` to spare, around the placed part, are the covered ones."""
    n = len(pm.t0) + 1
    t = np.r_[pm.t0, pm.t1[-1]]
    period = float(np.median(pm.t1 - pm.t0))
    log_s = float(gyro_t[-1] - gyro_t[0])
    length = min(n, int(log_s / period))
    shortest = max(int(math.ceil(MIN_PART_S / period)), int(math.ceil(MIN_PART_FRACTION * n)),
                   MIN_INTERVALS + 1)
    while length >= shortest:
        step = max(1, length // 4)
        found = []
        for i0 in sorted({*range(0, n - length + 1, step), n - length}):
            try:
                cs = coarse_sync(pm.sliced(i0, i0 + length), gyro_t, gyro_rate, tau_s=tau_s,
                                 readout_s=readout_s)
            except SyncError:
                continue
            found.append((cs.ncc, cs.time_offset_s))
        if found:
            offset = max(found)[1]
            t_log = t - offset                      # t_cam = t_gyro + offset
            reach = 8.0 * tau_s + readout_s + PART_MARGIN_S
            inside = np.flatnonzero((t_log - reach >= gyro_t[0]) & (t_log + PART_MARGIN_S <= gyro_t[-1]))
            if len(inside) < shortest:
                return None
            return int(inside[0]), int(inside[-1]) + 1
        length = int(length * PART_SHRINK)
    return None
