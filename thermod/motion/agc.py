"""Undo a camera's automatic gain control (AGC) on a video whose camera rotation is known.

An AGC maps the detector's counts s to y_k = g_k s + o_k with a gain and level of its own in every
frame k. Where only frame-to-frame motion matters (the optical flow of `thermod.motion.picture`) each frame
is normalised on its own; the forward model of the discrepancy workflow, which predicts one frame from
others through the detector's thermal response (Eq. 10), needs the counts on one scale. Frame j seen
from frame k's pose (the rotation-only homography H = K Q_jk K⁻¹, Eq. 16, from the picture rotations)
shows the same scene, so over the pixels both see the pair's relative map is y_k ≈ a_jk y_j + c_jk.
It is fitted on the means of a grid of blocks (6 × 8, each ≥ ¾ seen by both): motion blur, which
differs from frame to frame, moves a block's mean far less than its pixels' spread; a = std(means_k)
/ std(means_j) (the symmetric, geometric-mean regression: misregistration in either frame does not
pull it towards 0) when the means correlate (≥ 0.9), c from the means. Pairs at several spacings
(1, 2, 4, 8 frames) are combined by least squares on log g_k − log g_j = log a_jk and
o_k − a_jk o_j = c_jk (frame 0: g = 1, o = 0), so one pair's error does not propagate down the whole
chain as it would frame by frame. What is left: a fast-turning frame's heavier blur still lowers its
large-scale contrast a little, which reads as a lower gain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from thermod.motion.picture import MotionError, PictureMotion
from thermod.physics.geometry import Intrinsics, so3_exp

MIN_OVERLAP = 0.3           # share of the frame two views must both see for a pair to count
MIN_BLOCKS = 8              # blocks both views see that a pair's regression needs
MIN_BLOCK_CORR = 0.9        # ... and the correlation of their means


@dataclass
class AgcFit:
    """y_k = gain[k] · s + offset[k], s on frame 0's scale; `pairs` the frame pairs used."""

    gain: np.ndarray
    offset: np.ndarray
    pairs: int

    def counts(self, frames) -> np.ndarray:
        """The frames on one scale (float32, frame 0's units)."""
        y = np.asarray(frames, np.float32)
        o, g = self.offset.astype(np.float32), self.gain.astype(np.float32)
        return (y - o[:, None, None]) / g[:, None, None]

    def to_uint16(self, frames, step_counts: float = 64.0) -> np.ndarray:
        """`counts` as uint16 for a format-v1 recording: one unit of frame 0 becomes `step_counts`
        counts (less if the range would not fit), the minimum 1000."""
        s = self.counts(frames)
        lo, hi = float(s.min()), float(s.max())
        k = min(step_counts, 60000.0 / max(hi - lo, 1e-6))
        return np.clip(np.round(1000.0 + (s - lo) * k), 0, 65535).astype(np.uint16)


def _block_means(x: np.ndarray, y: np.ndarray, valid: np.ndarray, blocks: tuple[int, int]):
    """Means of x and y over the blocks of a grid that are at least ¾ valid (the valid pixels only)."""
    h, w = valid.shape
    by, bx = blocks
    ys_, xs_ = np.linspace(0, h, by + 1).astype(int), np.linspace(0, w, bx + 1).astype(int)
    mx, my = [], []
    for r in range(by):
        for c in range(bx):
            v = valid[ys_[r]:ys_[r + 1], xs_[c]:xs_[c + 1]]
            if v.mean() < 0.75:
                continue
            mx.append(float(x[ys_[r]:ys_[r + 1], xs_[c]:xs_[c + 1]][v].mean()))
            my.append(float(y[ys_[r]:ys_[r + 1], xs_[c]:xs_[c + 1]][v].mean()))
    return np.array(mx), np.array(my)


def fit_agc(frames, pm: PictureMotion, intrinsics: Intrinsics, *, spacings=(1, 2, 4, 8),
            blocks: tuple[int, int] = (6, 8), smooth_px: float = 0.0) -> AgcFit:
    """Per-frame gain and level of an AGC'd video (module docstring). `pm` gives the rotations between
    consecutive frames (`sync.picture_motion`), `intrinsics` those of `frames`."""
    import cv2
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import lsqr

    frames = np.asarray(frames)
    n = len(frames)
    if len(pm.t0) != n - 1:
        raise MotionError(f"AGC fit: {n} frames but picture motion for {len(pm.t0) + 1}")
    work = pm.work
    size = (work.width, work.height)
    small = []
    for f in frames:
        z = f.astype(np.float32)
        if (work.width, work.height) != (intrinsics.width, intrinsics.height):
            z = cv2.resize(z, size, interpolation=cv2.INTER_AREA)
        small.append(cv2.GaussianBlur(z, (0, 0), smooth_px) if smooth_px > 0 else z)
    K, K_inv = work.K, work.K_inv
    Qs = [so3_exp(r) if np.all(np.isfinite(r)) else None for r in pm.rotvec]
    ones = np.ones((work.height, work.width), np.float32)
    border = max(2, int(math.ceil(2 * smooth_px)))
    rows_l, rows_o = [], []
    for d in spacings:
        for j in range(0, n - d):
            k = j + d
            Q = np.eye(3)
            for i in range(j, k):
                if Qs[i] is None:
                    Q = None
                    break
                Q = Q @ Qs[i]
            if Q is None:
                continue
            H = K @ Q @ K_inv          # pixel of frame k → where frame j saw the same ray
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            x = cv2.warpPerspective(small[j], H, size, flags=flags)
            m = cv2.warpPerspective(ones, H, size, flags=flags, borderValue=0.0)
            m = cv2.erode((m > 0.999).astype(np.uint8), np.ones((2 * border + 1,) * 2, np.uint8)) > 0
            if m.mean() < MIN_OVERLAP:
                continue
            xs, ys = _block_means(x, small[k], m, blocks)
            if len(xs) < MIN_BLOCKS:
                continue
            sx, sy = float(xs.std()), float(ys.std())
            if not (sx > 0 and sy > 0) or np.corrcoef(xs, ys)[0, 1] < MIN_BLOCK_CORR:
                continue
            a = sy / sx
            rows_l.append((j, k, math.log(a)))
            rows_o.append((j, k, float(ys.mean()), float(xs.mean())))
    if not rows_l:
        raise MotionError("AGC fit: no two frames overlap enough (≥ 30 % of the frame) with a known rotation")
    m_rows = len(rows_l)
    r = np.repeat(np.arange(m_rows), 2)
    c = np.array([[k, j] for j, k, _ in rows_l]).ravel()
    v = np.tile([1.0, -1.0], m_rows)
    keep = c > 0                       # frame 0 is the reference: log g_0 = 0, o_0 = 0
    A = coo_matrix((v[keep], (r[keep], c[keep] - 1)), shape=(m_rows, n - 1)).tocsr()
    logg = np.r_[0.0, lsqr(A, np.array([x for _, _, x in rows_l]), atol=1e-12, btol=1e-12)[0]]
    g = np.exp(logg)
    # o_k − a_jk o_j = mean_k − a_jk mean_j, with a_jk = g_k / g_j from the fit
    a_fit = np.array([g[k] / g[j] for j, k, _ in rows_l])
    v = np.stack([np.ones(m_rows), -a_fit], axis=1).ravel()
    A = coo_matrix((v[keep], (r[keep], c[keep] - 1)), shape=(m_rows, n - 1)).tocsr()
    rhs = np.array([my - a * mx for (_, _, my, mx), a in zip(rows_o, a_fit, strict=True)])
    o = np.r_[0.0, lsqr(A, rhs, atol=1e-12, btol=1e-12)[0]]
    return AgcFit(g, o, m_rows)
