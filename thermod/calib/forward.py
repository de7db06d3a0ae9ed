"""Fast forward model: predict blurry microbolometer frames from a static reference view and raw gyro.

The physics is the simulator's, written for speed instead of fidelity to a high-resolution scene:

* the view at time s is the reference warped by the rotation-only homography (Eq. 16)
  ``H(s) = K Q(s) K⁻¹`` with ``Q(s) = R(t_ref)ᵀ R(s)`` integrated from the calibrated gyro with the
  piecewise-linear rate semantics of `thermod.physics.geometry.integrate_rotations`;
* the detector is the first-order thermal low-pass (Eq. 10/11), run as an exact IIR over sub-pixel
  time steps (Eq. 12: the image moves < `max_step_px` per step), so each frame is the exponential
  average of the views over its past (≥ 5τ of weight, Eq. 18);
* rolling readout: row r of a frame read at t_k is sampled at ``t_k − T_ro·(1 − (r+1)/H)``;
* optical PSF: an optional *extra* Gaussian (Eq. 19) on top of whatever blur the reference has.

The reference is a measured static frame, so it already carries the detector's own optical PSF
(and the same FPN as every frame): the prediction therefore needs no PSF of its own, and
`extra_psf_px` is the blur that motion frames show *beyond* the static ones (0 for a correct model).

Work happens at a reduced resolution (`scale`, intrinsics scaled with `Intrinsics.scaled`), on a
fixed time grid that does not depend on the candidate parameters, so that the warped views can be
cached while only τ, the readout time or the extra PSF change.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from thermod.physics.calibration import GYRO_EFFECT_KEYS, Calibration
from thermod.physics.detector import iir_alpha, row_read_time
from thermod.physics.geometry import integrate_rotations

__all__ = ["ForwardModel", "GridTooLarge", "downsample", "orientations", "predict_frames"]


class GridTooLarge(ValueError):
    """The fixed time grid would need more memory for its warped views than allowed."""


def downsample(frames: np.ndarray, scale: float, smooth_px: float = 0.0) -> np.ndarray:
    """Area-average frames [.., H, W] to `scale` × their size (float32), matching `Intrinsics.scaled`.

    `smooth_px` > 0 adds a Gaussian low-pass (σ in output pixels) that removes the aliased
    frequencies, so that warping the small image and shrinking a warped big one agree.
    """
    frames = np.asarray(frames, dtype=np.float32)
    one = frames.ndim == 2
    stack = frames[None] if one else frames
    h, w = stack.shape[-2:]
    size = (int(round(w * scale)), int(round(h * scale)))
    out = []
    for f in stack:
        g = f.copy() if scale == 1.0 else cv2.resize(f, size, interpolation=cv2.INTER_AREA)
        if smooth_px > 0:
            g = cv2.GaussianBlur(g, (0, 0), smooth_px, borderType=cv2.BORDER_REPLICATE)
        out.append(g)
    out = np.stack(out)
    return out[0] if one else out


def orientations(t_query: np.ndarray, t_cam: np.ndarray, omega_cam: np.ndarray, t_ref: float) -> np.ndarray:
    """Q(t) = R(t_ref)ᵀ R(t) at arbitrary times, same semantics as `geometry.integrate_rotations`.

    The rate is piecewise linear between gyro samples and held constant outside them; query times
    and t_ref are merged into the sample times, and `integrate_rotations` integrates the lot.
    """
    t_query = np.asarray(t_query, dtype=np.float64)
    lo = min(t_query.min(), t_ref)
    hi = max(t_query.max(), t_ref)
    keep = (t_cam > lo) & (t_cam < hi)
    tt, inv = np.unique(np.concatenate([t_query, [t_ref], t_cam[keep]]), return_inverse=True)
    if len(t_cam) == 1:
        ww = np.repeat(omega_cam[:1], len(tt), axis=0)
    else:
        ww = np.stack([np.interp(tt, t_cam, omega_cam[:, a]) for a in range(3)], axis=1)
    return integrate_rotations(tt, ww, t_ref)[inv[: len(t_query)]]


class ForwardModel:
    """Predicts one recording's motion frames for any calibration, caching what does not change.

    Parameters
    ----------
    reference : float32 [H, W]
        Sharp (static) view at full resolution, in counts, with FPN already removed if known.
    frame_t : float64 [n]
        Camera times of the frames to predict (when their last row was read), all > `t_ref`.
    gyro_t, gyro_rate : raw gyro samples (gyro clock, gyro frame, rad/s).
    calib : Calibration
        Nominal model; it fixes the image size, intrinsics and the step size of the time grid.
    t_ref : float
        A camera time at which the camera was at the reference pose (end of the static segment);
        the detector is taken as settled on the reference there.
    scale : float
        Working resolution relative to the recording (e.g. 0.5 or 0.25).
    fpn : float32 [H, W] or None
        Fixed-pattern noise, added back after the motion (it stays put on the sensor).
    max_step_px : float
        Largest image motion per time step (Eq. 12), at the working resolution.
    max_rate_factor : float
        Head-room on the gyro rate when choosing the step, so candidate scales stay sub-pixel.
    cache_mb : float
        Memory allowed for cached warped views (skipped when larger).
    max_views_mb : float
        Memory the warped views of one prediction may take at all; GridTooLarge beyond it (checked
        before anything is allocated: the step count follows from the gyro rate, fx and τ).
    interpolation : "cubic" (default: least resampling blur) or "linear" (≈ 2× faster warps).
    """

    def __init__(self, reference, frame_t, gyro_t, gyro_rate, calib: Calibration, *, t_ref: float,
                 scale: float = 1.0, fpn=None, max_step_px: float = 0.5, max_rate_factor: float = 1.3,
                 tau_min_s: float | None = None, cache_mb: float = 400.0, interpolation: str = "cubic",
                 max_views_mb: float = 4096.0):
        self.calib0 = calib
        self.scale = float(scale)
        self.intr = calib.intrinsics.scaled(self.scale)
        self.h, self.w = self.intr.height, self.intr.width
        ref = downsample(reference, self.scale)
        self.fpn = None if fpn is None else downsample(fpn, self.scale)
        self.reference = ref if self.fpn is None else ref - self.fpn
        self.frame_t = np.asarray(frame_t, dtype=np.float64)
        self.gyro_t = np.asarray(gyro_t, dtype=np.float64)
        self.gyro_rate = np.asarray(gyro_rate, dtype=np.float64)
        self.t_ref = float(t_ref)
        if len(self.frame_t) and self.frame_t.min() <= self.t_ref:
            raise ValueError("every frame to predict must be read after t_ref")
        # Fixed time grid: from t_ref (detector settled on the reference) to the last frame.
        speed = self._max_pixel_speed(calib) * max_rate_factor
        tau_min = tau_min_s if tau_min_s is not None else calib.tau_s / 3.0
        h_max = max(tau_min, 1e-4) / 4.0   # α ≤ 0.22: rows read between grid points interpolate well
        self.dt = min(h_max, max_step_px / speed) if speed > 0 else h_max
        t_end = float(self.frame_t.max()) if len(self.frame_t) else self.t_ref
        n_float = max(1.0, math.ceil((t_end - self.t_ref) / self.dt))
        views_mb = n_float * self.h * self.w * 2 * 4 / 1e6
        if not views_mb <= max_views_mb:
            raise GridTooLarge(f"the forward model needs {n_float:.3g} time steps ({views_mb / 1e3:.3g} GB "
                               f"of warped views, limit {max_views_mb / 1e3:.3g} GB) for "
                               f"{t_end - self.t_ref:.3g} s of motion at up to {speed:.3g} px/s "
                               f"(working fx {self.intr.fx:.4g}, τ {calib.tau_s:.3g} s)")
        n = int(n_float)
        self.dt = (t_end - self.t_ref) / n if t_end > self.t_ref else self.dt
        self.t_grid = self.t_ref + self.dt * np.arange(n + 1)
        self.t_mid = 0.5 * (self.t_grid[1:] + self.t_grid[:-1])
        if interpolation not in ("linear", "cubic"):
            raise ValueError(f"interpolation must be 'linear' or 'cubic', got {interpolation!r}")
        self._interp = cv2.INTER_LINEAR if interpolation == "linear" else cv2.INTER_CUBIC
        self._cache_key = None
        self._views = None
        self._cache_ok = n * self.h * self.w * 2 * 4 / 1e6 <= cache_mb
        yy, xx = np.mgrid[0:self.h, 0:self.w]
        self._pix = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], axis=0)

    def set_reference(self, reference, fpn=None, *, prescaled: bool = False) -> None:
        """Replace the reference (and FPN) keeping the time grid; drops the cached views."""
        ref = np.asarray(reference, np.float32) if prescaled else downsample(reference, self.scale)
        if fpn is not None:
            fpn = np.asarray(fpn, np.float32) if prescaled else downsample(fpn, self.scale)
        self.fpn = fpn
        self.reference = ref if fpn is None else ref - fpn
        self._views, self._cache_key = None, None

    # ------------------------------------------------------------------ geometry
    def _max_pixel_speed(self, calib: Calibration) -> float:
        _, w = calib.gyro_to_camera(self.gyro_t, self.gyro_rate)
        if len(w) == 0:
            return 0.0
        f = max(self.intr.fx, self.intr.fy)
        r = math.hypot(self.w, self.h) / 2.0   # roll moves the corners by |ω_z|·r
        speed = f * np.hypot(w[:, 0], w[:, 1]) + r * np.abs(w[:, 2])
        return float(np.max(speed))

    def homographies(self, calib: Calibration, times: np.ndarray) -> np.ndarray:
        """H(s) = K Q(s) K⁻¹ (Eq. 16) at the working resolution for camera times `times`."""
        t_cam, w_cam = calib.gyro_to_camera(self.gyro_t, self.gyro_rate)
        Q = orientations(times, t_cam, w_cam, self.t_ref)
        K = self.intr.K
        return K[None] @ Q @ np.linalg.inv(K)[None]

    def _gyro_key(self, calib: Calibration):
        return (calib.time_offset_s, tuple(calib.bias_rad_s), tuple(np.ravel(calib.gyro_to_camera_matrix)),
                tuple(getattr(calib, k) for k in GYRO_EFFECT_KEYS))

    def views(self, calib: Calibration) -> np.ndarray:
        """Warped reference and validity mask at the grid mid-points: float32 [n_steps, h, w, 2]."""
        key = self._gyro_key(calib)
        if self._views is not None and key == self._cache_key:
            return self._views
        Hs = self.homographies(calib, self.t_mid)
        src = np.dstack([self.reference, np.ones_like(self.reference)])
        out = np.empty((len(Hs), self.h, self.w, 2), np.float32)
        flags = self._interp | cv2.WARP_INVERSE_MAP
        for j, H in enumerate(Hs):
            cv2.warpPerspective(src, H, (self.w, self.h), dst=out[j], flags=flags,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if self._cache_ok:
            self._views, self._cache_key = out, key
        return out

    def row_times(self, calib: Calibration) -> np.ndarray:
        """Read time of every working row of every frame: [n_frames, h]."""
        y_full = (np.arange(self.h) + 0.5) / self.scale - 0.5
        return row_read_time(self.frame_t[:, None], y_full[None, :], calib.readout_s, calib.height)

    # ------------------------------------------------------------------ detector
    def predict(self, calib: Calibration, extra_psf_px: float = 0.0, valid_min: float = 0.99):
        """Predicted frames (float32 [n, h, w], counts, FPN included) and their valid mask (bool).

        Eq. 10/11: B_j = B_{j−1} + α (V_j − B_{j−1}), α = 1 − exp(−Δt/τ), over the fine grid;
        each frame row is the state at its read time (linear between grid points). A pixel is
        valid when ≥ `valid_min` of its exponential weight came from inside the reference.
        """
        V = self.views(calib)
        n, h, w = len(self.frame_t), self.h, self.w
        out = np.empty((n, h, w), np.float32)
        valid = np.empty((n, h, w), bool)
        if n == 0:
            return out, valid
        rt = np.clip(self.row_times(calib), self.t_grid[0], self.t_grid[-1])
        # j such that t_grid[j-1] < t ≤ t_grid[j]; rows read at t_ref take j = 0.
        jj = np.clip(np.searchsorted(self.t_grid, rt, side="left"), 0, len(self.t_grid) - 1)
        frac = np.where(jj > 0, (rt - self.t_grid[np.maximum(jj - 1, 0)]) / self.dt, 1.0).astype(np.float32)
        order = np.argsort(jj, axis=None, kind="stable")
        jflat = jj.ravel()[order]
        bounds = np.searchsorted(jflat, np.arange(len(self.t_grid) + 1))
        alpha = np.float32(iir_alpha(self.dt, calib.tau_s))
        B = np.dstack([self.reference, np.ones_like(self.reference)])
        prev = B.copy()
        out2 = np.empty((n, h, w, 2), np.float32)
        fr, rr = np.unravel_index(order, jj.shape)
        ff = frac.ravel()[order]
        for j in range(len(self.t_grid)):
            if j > 0:
                prev[...] = B
                B += alpha * (V[j - 1] - B)
            a, b = bounds[j], bounds[j + 1]
            if a == b:
                continue
            fk, rk, t = fr[a:b], rr[a:b], ff[a:b, None, None]
            out2[fk, rk] = prev[rk] + t * (B[rk] - prev[rk])
        m = out2[..., 1]
        valid[...] = m >= valid_min
        # Normalised by the in-bounds weight, so pixels near the edge stay in range (they are invalid).
        out[...] = self.reference[None]
        np.divide(out2[..., 0], m, out=out, where=m > 0.5)
        if extra_psf_px > 0:
            s = float(extra_psf_px) * self.scale
            g = cv2.getGaussianKernel(2 * int(math.ceil(4 * s)) + 1, s, cv2.CV_32F)   # ±4σ, sums to 1
            for k in range(n):
                out[k] = cv2.sepFilter2D(out[k], -1, g, g, borderType=cv2.BORDER_REPLICATE)
        if self.fpn is not None:
            out += self.fpn[None]
        return out, valid


def predict_frames(reference, frame_t, gyro_t, gyro_rate, calib: Calibration, *, t_ref: float,
                   scale: float = 1.0, extra_psf_px: float = 0.0, fpn=None, max_step_px: float = 0.5):
    """One-shot `ForwardModel(...).predict(calib, extra_psf_px)`: (frames float32 [n,h,w], valid bool)."""
    fm = ForwardModel(reference, frame_t, gyro_t, gyro_rate, calib, t_ref=t_ref, scale=scale, fpn=fpn,
                      max_step_px=max_step_px, cache_mb=0)
    return fm.predict(calib, extra_psf_px)
