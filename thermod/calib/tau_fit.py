"""τ from the pictures: the detector's thermal time constant fitted to the comet tails of a recording.

The live monitor's τ estimator (`thermod.calib.live`) run over a whole recording: each pair of
consecutive frames is registered in 2 × 2 patches with each frame's comet tail (Eq. 10 along the
path the recording's gyro gives) taken out, and on the patches whose two tails differ enough the
whitened cross-power is scored against the tails of each τ on a log scan of 0.5–2× a centre τ
(`Registrar.tau_coherence`). τ maximises the summed score; σ from a delete-one-block jackknife, with
a 5 % model floor. The tail's curvature, not its centroid, carries τ, so a time offset or a track's
lag error does not move it. A peak at the scan's edge moves the centre there and scans again; the
last scan is centred on the estimate. The gyro may be the track estimated from the video itself
(`thermod.motion.track`): pairs whose tails reach into a hole of the gyro are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.calib import live
from thermod.physics.calibration import Calibration
from thermod.physics.kernels.grids import has_hole

# cycles per full-resolution px: the highest frequency scored on compressed video. H.264's residual
# coding keeps less of the change of a comet tail between frames the higher the frequency, which pulls
# τ low: on a crf-18 clip at 320 px, −5…−7 % at 0.075, −9…−11 % at 0.1 and −13…−15 % at 0.15 (the
# same frames uncompressed: within 2 % at every band)
VIDEO_BAND = 0.075
START_TAU_S = 0.010       # a scan's centre when nothing is known: typical uncooled cores are 7–14 ms
MAX_SCANS = 4             # scans before giving up on a peak that keeps to the edge


@dataclass(frozen=True)
class TauFit:
    """The fitted τ (s) and its 1σ, or None with the reason in `note`; `patches`: patch pairs used."""

    tau_s: float | None
    sigma_s: float | None
    patches: int
    scans_ms: tuple[tuple[float, float], ...]     # (lowest, highest) τ of each scan, ms
    note: str | None = None

    def disagrees_with(self, tau_s: float, n_sigma: float = 3.0) -> bool:
        """Whether a stated τ lies more than `n_sigma` σ from the fit."""
        return self.tau_s is not None and abs(tau_s - self.tau_s) > n_sigma * self.sigma_s

    def to_dict(self) -> dict:
        return {"tau_s": self.tau_s, "sigma_s": self.sigma_s, "patch_pairs": self.patches,
                "scans_ms": [list(s) for s in self.scans_ms], "note": self.note}


def fit_tau(frames, frame_t: np.ndarray, gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration,
            *, start_tau_s: float | None = None, pairs: np.ndarray | None = None,
            width: int = live.TAU_WIDTH, band: float | None = None) -> TauFit:
    """Fit τ to the comet tails of `frames` [N, H, W] read at `frame_t` [N] (camera clock), with the
    raw gyro (`gyro_t`, `gyro_rate`) and the rest of `calib`. `start_tau_s`: the first scan's centre
    (default `calib.tau_s`; `START_TAU_S` when nothing is known). `pairs` [N − 1] bool: the frame
    pairs (k − 1, k) that may be used (default all). `band`: the highest frequency scored, cycles per
    full-resolution px (default the live monitor's `TAU_BAND_MAX` per working px; `VIDEO_BAND` for
    compressed video)."""
    frame_t = np.asarray(frame_t, np.float64)
    n = len(frame_t)
    if n < 2:
        return TauFit(None, None, 0, (), "tau_s: not estimated: fewer than two frames")
    usable = np.ones(n - 1, bool) if pairs is None else np.asarray(pairs, bool)
    centre = float(start_tau_s if start_tau_s is not None else calib.tau_s)
    gyro_t = np.asarray(gyro_t, np.float64)
    scans: list[tuple[float, float]] = []
    tau = sigma = problem = None
    used = 0
    for _ in range(MAX_SCANS):
        q, blk, used = _scan(frames, frame_t, gyro_t, gyro_rate, calib.replace(tau_s=centre), usable, width,
                             band)
        taus = centre * live.TAU_SCAN
        scans.append((round(float(1e3 * taus[0]), 3), round(float(1e3 * taus[-1]), 3)))
        tau, sigma, problem = live.tau_peak(q, blk, taus)
        if tau is not None:
            if abs(math.log(tau / centre)) < 0.1:
                break                                   # centred within a step of the scan: done
            centre = tau                                # once more, centred on the estimate
            continue
        score = q.sum(axis=0)
        edge = int(np.argmax(score)) if len(q) >= live.MIN_TAU_PATCHES else -1
        if edge not in (0, len(taus) - 1):
            break                                       # too few pairs, or blocks that disagree
        centre = float(taus[edge])                      # the peak lies beyond this edge: follow it
    note = None if problem is None else f"tau_s: not estimated: {problem}"
    return TauFit(tau, sigma, used, tuple(scans), note)


def _covered(gyro_t: np.ndarray, rate_hz: float, t0: float, t1: float) -> bool:
    """Whether the samples reach over [t0, t1] with no hole inside (`has_hole`)."""
    if len(gyro_t) < 2 or t0 < gyro_t[0] or t1 > gyro_t[-1]:
        return False
    i0, i1 = np.searchsorted(gyro_t, [t0, t1])
    return not has_hole(gyro_t[max(i0 - 1, 0):i1 + 1], rate_hz)


def _scan(frames, frame_t, gyro_t, gyro_rate, calib: Calibration, usable, width, band):
    """([n, T] coherence per patch pair over the scan around calib.tau_s, [n] jackknife block, pairs)."""
    per_working_px = max(1.0, calib.width / float(width))          # full-res px per working px
    reg = live.Registrar(calib, width=width, tau_band_max=live.TAU_BAND_MAX if band is None else
                         min(live.TAU_BAND_MAX, band * per_working_px))
    integ = live.GyroIntegral(calib, gyro_t, gyro_rate)
    taus = calib.tau_s * live.TAU_SCAN
    reach = live.TAIL_SPAN * taus[-1] + calib.readout_s
    bias, offset = np.asarray(calib.bias_rad_s, float), calib.time_offset_s
    P = len(reg.centres)
    rows, order = [], []
    tails: dict[int, live.TailSpectra] = {}
    small: dict[int, np.ndarray] = {}       # the downsampled frames of the current pair
    for k in range(1, len(frame_t)):
        if not usable[k - 1]:
            continue
        g0 = float(calib.camera_time_to_gyro(frame_t[k - 1] - reach))
        g1 = float(calib.camera_time_to_gyro(frame_t[k]))
        if not _covered(gyro_t, calib.rate_hz, g0, g1):
            continue
        ta, tb = np.full(P, frame_t[k - 1]), np.full(P, frame_t[k])
        pred = live.predict(calib, integ, ta, tb, reg.centres, bias, offset)
        va = live.tail_velocity(calib, integ, ta, reg.centres, bias, offset)
        vb = live.tail_velocity(calib, integ, tb, reg.centres, bias, offset)
        patches = reg.tau_patches(va, vb, calib.tau_s)
        if not patches.any():
            continue
        # only the pair's two frames are kept (a skipped pair leaves nothing behind)
        small = {j: small[j] if j in small else reg.downsample(frames[j]) for j in (k - 1, k)}
        a, b = small[k - 1], small[k]
        shift, resp = reg.measure(a, b, pred, va, vb, calib.tau_s)
        patches &= resp >= live.MIN_RESPONSE
        if not patches.any():
            continue
        tails = {j: tails[j] if j in tails else
                 live.tail_spectra(calib, integ, float(frame_t[j]), reg.centres, bias, offset, taus,
                                   reg.ext_f_full, live.TAU_REF)
                 for j in (k - 1, k)}
        c = reg.tau_coherence(a, b, pred, shift, resp, tails[k - 1], tails[k], patches)
        ok = np.all(np.isfinite(c), axis=1)
        rows.append(c[ok])
        order += [k] * int(ok.sum())
    if not rows:
        return np.zeros((0, len(taus))), np.zeros(0, int), 0
    q = np.vstack(rows)
    rank = np.searchsorted(np.unique(order), order)
    blk = rank * live.TAU_BLOCKS // max(int(rank.max()) + 1, 1)
    return q, blk, len(rows)


__all__ = ["START_TAU_S", "VIDEO_BAND", "TauFit", "fit_tau"]
