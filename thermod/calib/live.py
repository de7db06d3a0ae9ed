"""Live calibration estimates from the stream: gyro bias, time offset and τ from frame-to-frame registration.

Consecutive frames are registered at low resolution in a few patches by phase correlation, with each
frame's comet tail (the exponential kernel of Eq. 10) taken out of the cross-power phase, so the
measured shift is that of the instants the patch rows were read. Between two such instants the
camera turns by θ = ∫ ω_cam dt with ω_cam(t) = M (ω_gyro(g(t)) − b), g the gyro clock (time offset
o, clock drift), and the content moves by the homography of Q = exp(−θ) (Eq. 16). A rolling window
of pairs is fitted for (b, o): a coarse lag search, then Gauss–Newton with robust reweighting; σ
from a delete-one-block jackknife.

τ from the comet tails' shape: the linear part of a tail's phase (its centroid lag vτ) is
degenerate with the shift, hence with the offset; its curvature is not. On patch pairs whose tails
differ by at least `TAU_MIN_LEVER_PX`, the whitened cross-power is compared with the model of each τ
on a log scan of 0.5–2× the τ in force and the coherence maximised over the shift
(`Registrar.tau_coherence`); τ maximises the coherence summed over `TAU_WINDOW_S`, σ from a
jackknife over `TAU_BLOCKS` blocks. Too few such pairs, a maximum at the scan's edge or σ above a
quarter of τ: `tau_s` is None and ``notes`` says why. The offset is estimated at the τ in force.
The derivation: docs/design.md §6, "The live calibration monitor".
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from thermod.physics.calibration import Calibration
from thermod.physics.geometry import so3_exp_many

N_PARAMS = 4            # bias x, y, z (gyro frame, rad/s), time offset (s)
MIN_PAIRS = 20
MODEL_DELAY_ERROR = 0.05  # of τ: the floor of the offset's σ (see `LiveEstimator.fit`)
AMBIGUOUS_CORRELATION = 0.95   # |ρ(bias axis, offset)| above this: the window cannot tell them apart
LAG_SCAN_S, LAG_STEP_S = 0.06, 0.004   # the coarse offset search around the offset in force
MIN_RESPONSE = 0.05     # phase-correlation peaks weaker than this are no match (blank sky, a cut)
PATCH_FRACTION = 0.6    # of a grid cell: a shift of up to ~20 % of a cell still overlaps well
TAU_BAND_MAX = 0.3      # cycles per working px: the τ coherence's band (aliasing above)
TAU_SCAN = np.exp(np.linspace(math.log(0.5), math.log(2.0), 13))   # τ candidates / τ in force, 12 % steps
NEWTON = 2              # Newton steps on the shift per τ (`_profiled_coherence`)
TAIL_SPAN = 8.0         # of τ_max: how far back the tails are followed (e^−8 of the weight left out)
TAU_MODEL_ERROR = 0.05  # of τ: the floor of τ's σ (see `LiveEstimator.fit_tau`)
TAU_WIDTH = 160         # px: τ is measured at this working width (its cost does not grow with the frame)
TAU_WINDOW_S = 12.0     # s: the window of τ measurements (at least the motion's window)
MAX_WINDOW_S = 60.0     # s: the longest a stretched window grows (`LiveEstimator.stretch`)
TAU_REF = 6             # TAU_SCAN[TAU_REF] = 1: the τ in force
TAU_MIN_LEVER_PX = 0.5  # working px: a patch pair whose tails differ less shows nothing of τ
TAU_BLOCKS = 16         # τ's jackknife blocks: σ from g blocks has g − 1 degrees of freedom
MIN_TAU_PATCHES = 24    # patch pairs in a window needed for a τ estimate
TAU_MAX_REL_SIGMA = 0.25


@dataclass
class Pair:
    """The displacements measured between two consecutive frames, at the patch centres (full-res px)."""

    t_a: float
    t_b: float
    centres: np.ndarray          # [P, 2] (x, y) full-resolution pixel coordinates in frame a
    shift: np.ndarray            # [P, 2] content at centre p of a is at p + shift in b
    weight: np.ndarray           # [P] phase-correlation response (0 = unusable)
    taus: np.ndarray | None = None      # [T] the τ scan (s) of `tau_coherence`
    tau_coherence: np.ndarray | None = None   # [P, T] `Registrar.tau_coherence` (NaN: not measured)


@dataclass
class Estimate:
    """One fit on a window: values, 1-σ uncertainties, and how well the model explains the window."""

    bias_rad_s: np.ndarray
    bias_sigma: np.ndarray
    time_offset_s: float
    time_offset_sigma: float
    t: float                      # centre of the window (camera time)
    n_pairs: int
    residual_px: float            # robust RMS displacement mismatch at the estimate
    residual_applied_px: float    # the same with the calibration in force
    tau_s: float | None = None
    tau_sigma: float | None = None
    n_tau: int = 0                # patch pairs whose tails changed enough to show τ
    bias_offset_correlation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # each bias axis with o
    ambiguous: bool = False       # a bias axis and the offset cannot be told apart in this window
    # the bias σ of the fit alone (the jackknife), without the offset's model delay error it inherits:
    # what a change applied with its offset is judged by (`thermod.runtime.monitor`)
    bias_sigma_stat: np.ndarray | None = None
    notes: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"gyro_bias_rad_s": [float(x) for x in self.bias_rad_s],
                "gyro_bias_rad_s_sigma": [float(x) for x in self.bias_sigma],
                "time_offset_s": float(self.time_offset_s),
                "time_offset_s_sigma": float(self.time_offset_sigma),
                "tau_s": _opt(self.tau_s), "tau_s_sigma": _opt(self.tau_sigma),
                "n_tau_patches": int(self.n_tau),
                "t": float(self.t), "n_pairs": int(self.n_pairs),
                "residual_px": float(self.residual_px),
                "residual_applied_px": float(self.residual_applied_px),
                "bias_offset_correlation": [round(float(c), 3) for c in self.bias_offset_correlation],
                "ambiguous": bool(self.ambiguous),
                "notes": list(self.notes)}


def _opt(x: float | None) -> float | None:
    return None if x is None else float(x)


# ------------------------------------------------------------------------------- registration
class Registrar:
    """Registers two frames in a 2 × 2 grid of patches at a working width of `width` px (area
    downsampling), each patch of frame b taken where the gyro predicts its content went (so fast motion
    stays within the patch); phase correlation gives the remainder to sub-pixel precision."""

    def __init__(self, calib: Calibration, width: int = 160, grid: tuple[int, int] = (2, 2),
                 tau_band_max: float = TAU_BAND_MAX):
        self.full = (calib.width, calib.height)
        self.factor = max(1.0, calib.width / float(width))
        self.w = int(round(calib.width / self.factor))
        self.h = int(round(calib.height / self.factor))
        gy, gx = grid
        self.pw = _even(PATCH_FRACTION * self.w / gx)
        self.ph = _even(PATCH_FRACTION * self.h / gy)
        cx = (np.arange(gx) + 0.5) * self.w / gx
        cy = (np.arange(gy) + 0.5) * self.h / gy
        self.centres_lr = np.array([(x, y) for y in cy for x in cx])
        self.window = cv2.createHanningWindow((self.pw, self.ph), cv2.CV_32F)
        self.fy = np.fft.fftfreq(self.ph)[:, None]        # cycles/px of the rfft2 bins
        self.fx = np.fft.rfftfreq(self.pw)[None, :]
        sx, sy = calib.width / self.w, calib.height / self.h
        self.scale = np.array([sx, sy])
        # τ: full fft2 grid of a periodic Hann window, whose transform has 3 taps per axis (½, −¼, −¼),
        # so the window spreads each frequency's cross-power over its neighbours by (1, 4, 1)/6 per axis
        n_y, n_x = np.arange(self.ph), np.arange(self.pw)
        self.hann = np.outer(0.5 - 0.5 * np.cos(2 * np.pi * n_y / self.ph),
                             0.5 - 0.5 * np.cos(2 * np.pi * n_x / self.pw)).astype(np.float32)
        gy, gx = np.meshgrid(np.fft.fftfreq(self.ph), np.fft.fftfreq(self.pw), indexing="ij")
        rad = np.hypot(gx, gy)
        # half of the band: the other half holds the conjugates (real frames, real kernels)
        upper = (gx > 0) | ((gx == 0) & (gy > 0))
        band = (rad > 0) & (rad <= tau_band_max) & upper
        # every neighbour a window tap reaches from the band, folded into the upper half plane: the
        # frequencies the tails are needed at
        iy, ix = np.nonzero(band)
        need = {}
        taps = []
        for ky in (-1, 0, 1):
            for kx in (-1, 0, 1):
                qy, qx = (iy - ky) % self.ph, (ix - kx) % self.pw           # f − k
                mirror = ~upper[qy, qx]
                qy, qx = np.where(mirror, -qy % self.ph, qy), np.where(mirror, -qx % self.pw, qx)
                keys = qy * self.pw + qx
                idx = np.array([need.setdefault(int(q), len(need)) for q in keys])
                taps.append(((1 + 3 * (ky == 0)) * (1 + 3 * (kx == 0)) / 36.0, kx / self.pw, ky / self.ph,
                             idx, mirror))
        # tap k of band frequency f reads the cross-power at f − k (conjugated where it was mirrored)
        self.taps = taps
        ext_flat = np.array(sorted(need, key=need.get))
        self.ext_in_grid = ext_flat
        self.ext_f_full = np.c_[gx.ravel()[ext_flat], gy.ravel()[ext_flat]] / self.scale[None, :]
        self.band_in_grid = np.flatnonzero(band)
        self.band_iy, self.band_ix = np.nonzero(band)                  # gx ≥ 0: rfft2 rows, columns
        self.band_f = np.c_[gx[band], gy[band]]                        # cycles / working px
        # full-res coordinates of the low-res pixel centres (area downsampling)
        self.centres = (self.centres_lr + 0.5) * self.scale - 0.5

    def downsample(self, image: np.ndarray) -> np.ndarray:
        return cv2.resize(np.asarray(image, np.float32), (self.w, self.h), interpolation=cv2.INTER_AREA)

    def measure(self, a: np.ndarray, b: np.ndarray, predicted: np.ndarray | None = None,
                vel_a: np.ndarray | None = None, vel_b: np.ndarray | None = None, tau_s: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray]:
        """(shift [P, 2] full-res px, response [P]) between downsampled frames a and b. `predicted`
        [P, 2] (full-res px) places b's patches; `vel_a`, `vel_b` [P, 2] (full-res px/s, the content's
        image velocity over each frame's thermal window) take out each frame's comet-tail phase, so the
        shift is that of the frames' read instants (`deblurred_phase`)."""
        n = len(self.centres_lr)
        pred = np.zeros((n, 2)) if predicted is None else predicted / self.scale
        va = np.zeros((n, 2)) if vel_a is None else vel_a / self.scale
        vb = np.zeros((n, 2)) if vel_b is None else vel_b / self.scale
        shifts = np.zeros((n, 2))
        resp = np.zeros(n)
        for i in range(n):
            c = self.centres_lr[i]
            pa = self._patch(a, c)
            if pa is None:
                continue
            r = np.round(pred[i])
            pb = self._patch(b, c + r)
            if pb is None:                       # the predicted place is off the frame: nothing to compare
                continue
            s, q = self._correlate(pa, pb, va[i] * tau_s, vb[i] * tau_s)
            shifts[i] = r + s
            resp[i] = q
        return shifts * self.scale, resp

    def _correlate(self, pa, pb, tail_a, tail_b):
        """Phase correlation with each frame's exponential comet tail (length v·τ, px) removed from the
        cross-power phase: K(f) = 1/(1 − i2πf·vτ) (the content trails along −v), so what remains is the
        shift of the read instants, whatever the blur."""
        A = np.fft.rfft2(pa * self.window)
        B = np.fft.rfft2(pb * self.window)
        X = np.conj(A) * B
        X /= np.abs(X) + 1e-12 * (np.abs(X).max() + 1e-30)
        phi_a = np.arctan(2 * np.pi * (self.fx * tail_a[0] + self.fy * tail_a[1]))
        phi_b = np.arctan(2 * np.pi * (self.fx * tail_b[0] + self.fy * tail_b[1]))
        X *= np.exp(-1j * (phi_b - phi_a))
        r = np.fft.irfft2(X, s=pa.shape)
        iy, ix = np.unravel_index(int(np.argmax(r)), r.shape)
        peak = float(r[iy, ix])
        h, w = r.shape

        def sub(m1, m0, p1):
            den = m1 - 2 * m0 + p1
            return 0.0 if den >= 0 else 0.5 * (m1 - p1) / den

        dx = ix + sub(r[iy, (ix - 1) % w], peak, r[iy, (ix + 1) % w])
        dy = iy + sub(r[(iy - 1) % h, ix], peak, r[(iy + 1) % h, ix])
        dx = dx - w if dx > w / 2 else dx
        dy = dy - h if dy > h / 2 else dy
        return np.array([dx, dy]), peak

    def tau_patches(self, vel_a: np.ndarray, vel_b: np.ndarray, tau_s: float) -> np.ndarray:
        """[P] bool: the patches whose two comet tails (velocities [P, 2] full-res px/s over τ) differ by
        at least `TAU_MIN_LEVER_PX` working px, the pairs worth a τ measurement."""
        return np.linalg.norm((vel_b - vel_a) * tau_s / self.scale, axis=1) >= TAU_MIN_LEVER_PX

    def tau_coherence(self, a: np.ndarray, b: np.ndarray, predicted: np.ndarray, shift: np.ndarray,
                      resp: np.ndarray, tail_a: TailSpectra, tail_b: TailSpectra, patches: np.ndarray
                      ) -> np.ndarray:
        """[P, T] how well each τ of the scan explains patch p's cross-power phase (NaN: not measured).

        The model cross-power at τ is e^{−i2πf·d} Σ_k c_k e^{i2πk·d} (P·U)(f − k): the tails' unit
        transfer ratio U = e^{i(arg K_b − arg K_a)} weighted by the measured cross-power magnitude P and
        spread over the neighbours k the periodic Hann window reaches (c_k = (1, 4, 1)/6 per axis).
        With the shift profiled out (Newton on d from the whole-pixel peak of each τ's correlation; the
        window taps' phases at the registration's shift moved by the tails' centroids), the coherence
        Re Σ_f X_f conj(M_f)/|M_f| of the whitened cross-power X is largest at the true τ whatever
        noise leaves the phases alone: the linear part of the tail phase (the centroid lag, degenerate
        with the shift and so with the time offset) drops out and what remains is its curvature, the
        tail's shape."""
        n_t = tail_a.phase.shape[1]
        out = np.full((len(self.centres_lr), n_t), np.nan)
        pred = predicted / self.scale
        for i in np.flatnonzero(patches & (resp >= MIN_RESPONSE)):
            c = self.centres_lr[i]
            pa = self._patch(a, c)
            r = np.round(pred[i])
            pb = self._patch(b, c + r)
            if pa is None or pb is None:
                continue
            A = np.fft.fft2(pa * self.hann).ravel()
            B = np.fft.fft2(pb * self.hann).ravel()
            C = np.conj(A) * B
            power = np.abs(C)
            X = C[self.band_in_grid] / (power[self.band_in_grid] + 1e-12 * (power.max() + 1e-30))
            lever = (tail_b.centroid[i] - tail_a.centroid[i]) / self.scale     # [T, 2] working px
            d = shift[i] / self.scale - r + lever - lever[tail_a.ref]
            # the model's cross-power e^{−i2πf·d} Σ_k c_k e^{i2πk·d} (P U)(f − k): the scene's power P
            # (the measured |C|) times the unit ratio U of the two tails' transfers, spread by the window
            PU = power[self.ext_in_grid] * np.exp(1j * (tail_b.phase[i] - tail_a.phase[i]))   # [T, E]
            M = 0
            for c_k, fx_k, fy_k, idx, mirrored in self.taps:
                PU_k = np.where(mirrored, np.conj(PU[:, idx]), PU[:, idx])
                M = M + (c_k * np.exp(2j * np.pi * (d[:, 0] * fx_k + d[:, 1] * fy_k)))[:, None] * PU_k
            Z = X[None, :] * np.conj(M) / (np.abs(M) + 1e-30)
            out[i] = _profiled_coherence(Z, self.band_f, self._peak_shift(Z)) / len(self.band_f)
        return out

    def _peak_shift(self, Z: np.ndarray) -> np.ndarray:
        """[T, 2] the whole-pixel d maximising Re Σ_f Z[t, f] e^{i2πf·d} (an inverse FFT of the band,
        which lies in the rfft half plane): where Newton starts, within half a pixel of the peak."""
        grid = np.zeros((len(Z), self.ph, self.pw // 2 + 1), np.complex128)
        grid[:, self.band_iy, self.band_ix] = Z
        r = np.fft.irfft2(grid, s=(self.ph, self.pw)).reshape(len(Z), -1)
        iy, ix = np.unravel_index(np.argmax(r, axis=1), (self.ph, self.pw))
        return np.c_[(ix + self.pw // 2) % self.pw - self.pw // 2,
                     (iy + self.ph // 2) % self.ph - self.ph // 2].astype(float)

    def _patch(self, img: np.ndarray, c: np.ndarray) -> np.ndarray | None:
        x0 = int(round(c[0] - self.pw / 2))
        y0 = int(round(c[1] - self.ph / 2))
        if x0 < 0 or y0 < 0 or x0 + self.pw > self.w or y0 + self.ph > self.h:
            return None
        p = img[y0:y0 + self.ph, x0:x0 + self.pw]
        return np.ascontiguousarray(p - p.mean(), np.float32)


def _profiled_coherence(Z: np.ndarray, f: np.ndarray, d: np.ndarray) -> np.ndarray:
    """max over d of Re Σ_f Z[t, f] e^{i2πf·d}, by Newton from d [T, 2] (working px), per row t."""
    w = 2 * np.pi * f                                                # [F, 2]
    ww = np.c_[w[:, 0] ** 2, w[:, 0] * w[:, 1], w[:, 1] ** 2]         # [F, 3]
    d = np.array(d, float)
    for _ in range(NEWTON):
        Y = Z * np.exp(1j * (d @ w.T))                               # [T, F]
        g = -(Y.imag @ w)                                            # [T, 2]: ∂Q/∂d
        hxx, hxy, hyy = (-(Y.real @ ww)).T                           # ∂²Q/∂d²
        det = hxx * hyy - hxy ** 2
        ok = (hxx < 0) & (det > 0)
        det = np.where(ok, det, 1.0)
        step = np.where(ok[:, None], -np.c_[hyy * g[:, 0] - hxy * g[:, 1],
                                            hxx * g[:, 1] - hxy * g[:, 0]] / det[:, None], 0.0)
        d += np.clip(step, -0.5, 0.5)
    return (Z * np.exp(1j * (d @ w.T))).real.sum(axis=1)


def _even(x: float) -> int:
    return max(8, int(x) // 2 * 2)


# ------------------------------------------------------------------------------- the model
class GyroIntegral:
    """The cumulative integral of the conditioned raw gyro (gyro frame, bias kept) on the gyro clock;
    the rotation between two camera times for any (bias, offset) is two interpolations of it."""

    def __init__(self, calib: Calibration, t_gyro: np.ndarray, rate_gyro: np.ndarray):
        t, r = calib.condition_gyro(t_gyro, rate_gyro, whole_series=False)
        self.t = t
        steps = 0.5 * (r[1:] + r[:-1]) * np.diff(t)[:, None]
        self.c = np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
        self.M = calib.gyro_to_camera_matrix
        self.eps = calib.clock_drift_ppm * 1e-6
        self.epoch = calib.clock_epoch_s

    def covers(self, t0: float, t1: float, offset: float) -> bool:
        g0, g1 = self.gyro_time(np.array([t0, t1]), offset)
        return len(self.t) > 1 and self.t[0] <= g0 and g1 <= self.t[-1]

    def gyro_time(self, t_cam: np.ndarray, offset: float) -> np.ndarray:
        return (t_cam - offset + self.eps * self.epoch) / (1.0 + self.eps)

    def rotation(self, s_a: np.ndarray, s_b: np.ndarray, bias: np.ndarray, offset: float) -> np.ndarray:
        """θ [n, 3] (camera frame, rad) turned between camera times s_a and s_b."""
        ga, gb = self.gyro_time(s_a, offset), self.gyro_time(s_b, offset)
        d = np.stack([np.interp(gb, self.t, self.c[:, k]) - np.interp(ga, self.t, self.c[:, k])
                      for k in range(3)], axis=-1)
        d = d - np.asarray(bias)[None, :] * (gb - ga)[:, None]
        return d @ self.M.T


def row_times(calib: Calibration, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Camera time at which row `rows` of a frame whose last row is read at t is read."""
    h = max(calib.height - 1, 1)
    return t - calib.readout_s * (h - rows) / h


def displacements(K: np.ndarray, K_inv: np.ndarray, theta: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[n, 2] displacement π(K exp(−θ) K⁻¹ p) − p of each centre p [n, 2] under rotation θ [n, 3]."""
    Q = so3_exp_many(-theta)
    H = K[None] @ Q @ K_inv[None]
    ph = np.einsum("nij,nj->ni", H, np.c_[centres, np.ones(len(centres))])
    return ph[:, :2] / ph[:, 2:3] - centres


def tail_velocity(calib: Calibration, integral: GyroIntegral, t: np.ndarray, centres: np.ndarray,
                  bias: np.ndarray, offset: float) -> np.ndarray:
    """[n, 2] mean image velocity (full-res px/s) of the content at each centre over the thermal window's
    centroid span (t − τ, t]: the comet tail's length and direction over τ."""
    tau = calib.tau_s
    return predict(calib, integral, t - tau, t, centres, bias, offset) / tau


@dataclass
class TailSpectra:
    """One frame's comet tails at the patch centres over a τ scan: the phase [P, T, F] of each tail's
    transfer function at the frequencies asked for (`Registrar.ext_f_full`) and its centroid [P, T, 2]
    (full-res px, the lag of the blurred content behind the read instant); `ref` is the index of the
    τ in force."""

    taus: np.ndarray
    phase: np.ndarray
    centroid: np.ndarray
    ref: int


def tail_spectra(calib: Calibration, integral: GyroIntegral, t: float, centres: np.ndarray, bias: np.ndarray,
                 offset: float, taus: np.ndarray, freqs: np.ndarray, ref: int) -> TailSpectra:
    """The exponential kernel of Eq. 10 along the path the gyro gives, for each τ of `taus`: the content
    seen s before the read instant t sits D(s) from where it is at t (`predict` from t − s to t), so
    K(f; τ) = ∫ (1/τ) e^{−s/τ} e^{i2πf·D(s)} ds (for a steady velocity v, 1/(1 − i2πf·vτ)). The path is
    cut into segments (`_tail_edges`), each a straight smear (sinc) carrying its exact share of the
    exponential weight at its exponential centroid; `freqs` [F, 2] in cycles per full-res px."""
    taus = np.asarray(taus, float)
    edges = _tail_edges(float(taus.min()), float(taus.max()))
    n = len(edges)
    p = len(centres)
    cen = np.repeat(centres, n, axis=0)
    tb = np.full(p * n, float(t))
    D = predict(calib, integral, tb - np.tile(edges, p), tb, cen, bias, offset).reshape(p, n, 2)
    mid = 0.5 * (D[:, 1:] + D[:, :-1])                                          # [P, n−1, 2]
    step = D[:, 1:] - D[:, :-1]
    fx, fy = freqs[:, 0], freqs[:, 1]
    # products and sums spelled out: no BLAS call, whose threads only spin at these sizes
    fd = (step[..., :1] * fx + step[..., 1:] * fy).astype(np.float32)          # [P, n−1, F]
    E = np.exp(np.float32(2 * np.pi) * 1j * (mid[..., :1] * fx + mid[..., 1:] * fy).astype(np.float32))
    E *= np.sinc(fd)
    m = np.exp(-edges[None, :-1] / taus[:, None]) - np.exp(-edges[None, 1:] / taus[:, None])
    m /= m.sum(axis=1, keepdims=True)                                          # [T, n−1]
    # each segment's weight sits at its exponential centroid, a fraction u of the way along it (not at
    # its middle): to first order in (u − ½)·step
    h = np.diff(edges)[None, :]
    u = (taus[:, None] - h / np.expm1(h / taus[:, None])) / h - 0.5           # [T, n−1]
    G = E * (np.float32(2 * np.pi) * fd)
    mr, mi = m.astype(np.float32), (m * u).astype(np.float32)
    K = np.zeros((p, len(taus), E.shape[2]), np.complex64)
    for j in range(E.shape[1]):
        K += mr[None, :, j, None] * E[:, None, j] + 1j * mi[None, :, j, None] * G[:, None, j]
    centroid = np.einsum("tn,pnk->ptk", m, mid) + np.einsum("tn,pnk->ptk", m * u, step)
    return TailSpectra(taus=taus, phase=np.angle(K), centroid=centroid, ref=ref)


def _tail_edges(tau_min: float, tau_max: float) -> np.ndarray:
    """Segment edges (s before the read instant): τ_min/2 long near it, then a quarter of the time
    already covered, at most τ_max/2, out to `TAIL_SPAN` τ_max."""
    edges = [0.0]
    while edges[-1] < TAIL_SPAN * tau_max:
        edges.append(edges[-1] + min(max(0.5 * tau_min, 0.25 * edges[-1]), 0.5 * tau_max))
    return np.array(edges)


def predict(calib: Calibration, integral: GyroIntegral, t_a: np.ndarray, t_b: np.ndarray,
            centres: np.ndarray, bias: np.ndarray, offset: float) -> np.ndarray:
    """Predicted displacement [n, 2] of each (t_a, t_b, centre) row."""
    s_a = row_times(calib, t_a, centres[:, 1])
    s_b = row_times(calib, t_b, centres[:, 1])
    theta = integral.rotation(s_a, s_b, bias, offset)
    K = calib.K
    return displacements(K, np.linalg.inv(K), theta, centres)


# ------------------------------------------------------------------------------- the fit
class LiveEstimator:
    """A rolling window of `Pair` s and the (bias, offset) fit on it; the pairs τ was measured on are
    kept over a longer window (`tau_window_s`: τ drifts slowly, and each measurement is costly)."""

    def __init__(self, window_s: float = 4.0, blocks: int = 8, tau_window_s: float | None = None):
        self.window_s = float(window_s)
        self.tau_window_s = max(self.window_s, TAU_WINDOW_S if tau_window_s is None else float(tau_window_s))
        self._windows = (self.window_s, self.tau_window_s)
        self.keep, self.max_window_s = 0, MAX_WINDOW_S
        self.tau_keep, self.max_tau_window_s = 0, MAX_WINDOW_S
        self.blocks = int(blocks)
        self.pairs: deque[Pair] = deque()
        self.tau_pairs: deque[Pair] = deque()
        self._tau_kept = 0            # patch pairs with a τ measurement in `tau_pairs`

    def add(self, pair: Pair) -> None:
        self.pairs.append(pair)
        if pair.tau_coherence is not None:
            self.tau_pairs.append(pair)
            self._tau_kept += _tau_measured(pair)
        self._trim(pair.t_b)

    def stretch(self, factor: float, keep: int = 0, max_window_s: float = MAX_WINDOW_S,
                tau_keep: int = 0, max_tau_window_s: float = MAX_WINDOW_S) -> None:
        """Keep `factor` × the windows it was made with (at most `max_window_s`), and at least `keep`
        pairs within that: pairs taken `factor` times more sparsely then still fill a fit. The τ window
        keeps at least `tau_keep` measured patch pairs, up to `max_tau_window_s` (its measurements need
        no gyro history). Pairs beyond a shortened window go now."""
        cap = max(float(max_window_s), self._windows[0])
        self.window_s, self.tau_window_s = (min(w * float(factor), max(cap, w)) for w in self._windows)
        self.keep, self.max_window_s, self.tau_keep = int(keep), cap, int(tau_keep)
        self.max_tau_window_s = float(max_tau_window_s)
        if self.pairs:
            self._trim(self.pairs[-1].t_b)

    def _trim(self, newest_t: float) -> None:
        while self.pairs and newest_t - self.pairs[0].t_a > self.window_s and \
                (len(self.pairs) > self.keep or newest_t - self.pairs[0].t_a > self.max_window_s):
            self.pairs.popleft()
        while self.tau_pairs and newest_t - self.tau_pairs[0].t_a > self.tau_window_s and \
                (self._tau_kept - _tau_measured(self.tau_pairs[0]) >= self.tau_keep
                 or newest_t - self.tau_pairs[0].t_a > max(self.max_tau_window_s, self.tau_window_s)):
            self._tau_kept -= _tau_measured(self.tau_pairs.popleft())

    def span(self) -> tuple[float, float] | None:
        return (self.pairs[0].t_a, self.pairs[-1].t_b) if self.pairs else None

    def _rows(self):
        t_a, t_b, cen, sh, w, blk = [], [], [], [], [], []
        n = len(self.pairs)
        for i, p in enumerate(self.pairs):
            ok = p.weight >= MIN_RESPONSE
            k = int(ok.sum())
            t_a += [p.t_a] * k
            t_b += [p.t_b] * k
            cen.append(p.centres[ok])
            sh.append(p.shift[ok])
            w.append(p.weight[ok])
            blk += [i * self.blocks // max(n, 1)] * k
        if not cen:
            return None
        return (np.array(t_a), np.array(t_b), np.vstack(cen), np.vstack(sh), np.concatenate(w),
                np.array(blk))

    def fit(self, calib: Calibration, integral: GyroIntegral, iterations: int = 6) -> Estimate | None:
        """Gauss–Newton for (bias, offset) from the calibration in force, robustly reweighted; None when
        the window has too few usable pairs or the gyro does not cover it."""
        if len(self.pairs) < MIN_PAIRS:
            return None
        rows = self._rows()
        if rows is None:
            return None
        t_a, t_b, cen, meas, w0, blk = rows
        if len(t_a) < MIN_PAIRS:
            return None
        reach = calib.tau_s + calib.readout_s + 0.05
        x = np.r_[np.asarray(calib.bias_rad_s, float), calib.time_offset_s]
        if not integral.covers(float(t_a.min()) - reach, float(t_b.max()), x[3]):
            return None

        def residual(p):
            return (meas - predict(calib, integral, t_a, t_b, cen, p[:3], p[3])).ravel()

        r_applied = residual(x)
        # the lag that best explains the image motion, on a coarse grid: Gauss–Newton then starts
        # within its reach however far the offset in force is off (the cost is smooth over a few ms)
        lags = x[3] + np.arange(-LAG_SCAN_S, LAG_SCAN_S + 1e-9, LAG_STEP_S)
        costs = [_robust_rms(residual(np.r_[x[:3], lag])) for lag in lags]
        if np.min(costs) < _robust_rms(r_applied):
            x[3] = float(lags[int(np.argmin(costs))])
        steps = np.array([1e-3, 1e-3, 1e-3, 1e-4])
        r = residual(x)
        J = None
        for _ in range(iterations):
            J = np.stack([(residual(x + np.eye(N_PARAMS)[k] * steps[k]) - r) / steps[k]
                          for k in range(N_PARAMS)], axis=1)
            w = np.repeat(w0, 2) * _huber(r)
            A = J * w[:, None]
            # Levenberg damping keeps unobservable directions (no roll, no acceleration) where they are
            N = J.T @ A
            dx = -np.linalg.solve(N + 1e-9 * np.trace(N) * np.eye(N_PARAMS), A.T @ r)
            x_new = x + dx
            x_new[3] = float(np.clip(x_new[3], -0.5, 0.5))
            r_new = residual(x_new)
            if np.sum(w * r_new ** 2) > np.sum(w * r ** 2):
                break
            x, r = x_new, r_new
            if np.all(np.abs(dx) < steps * 1e-2):
                break
        cov = self._jackknife(J, r, w, np.repeat(blk, 2))
        sigma = np.sqrt(np.diag(cov))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.nan_to_num(cov[:3, 3] / (sigma[:3] * sigma[3]))
        # the comet tail's phase is taken out at one velocity per frame (first order in the change of
        # velocity over τ): a delay error the jackknife cannot see, bounded at 5 % of τ. The bias
        # follows the offset along the normal equations' coupling (the bias that best explains the
        # window with the offset held δ off), so it shares that error.
        delay = MODEL_DELAY_ERROR * calib.tau_s
        N = J.T @ (J * w[:, None])
        try:
            drag = -np.linalg.solve(N[:3, :3] + 1e-9 * np.trace(N) * np.eye(3), N[:3, 3])
        except np.linalg.LinAlgError:
            drag = np.full(3, np.inf)
        stat = sigma[:3].copy()
        sigma[3] = math.hypot(sigma[3], delay)
        sigma[:3] = np.hypot(sigma[:3], drag * delay)
        tau, tau_sigma, n_tau, note = self.fit_tau(calib)
        notes = [note] if note else []
        confounded = [ax for ax, c in zip("xyz", corr, strict=True) if abs(c) > AMBIGUOUS_CORRELATION]
        if confounded:
            notes.append(f"ambiguous: gyro_bias[{','.join(confounded)}] | time_offset (correlation "
                         f"{', '.join(f'{c:+.2f}' for c in corr)}): this window's motion does not tell a "
                         "bias from a delay; a rate that changes within the window separates them")
        return Estimate(bias_rad_s=x[:3], bias_sigma=sigma[:3], time_offset_s=float(x[3]),
                        time_offset_sigma=float(sigma[3]), t=0.5 * (float(t_a.min()) + float(t_b.max())),
                        n_pairs=len(self.pairs), residual_px=_robust_rms(r),
                        residual_applied_px=_robust_rms(r_applied), tau_s=tau, tau_sigma=tau_sigma,
                        n_tau=n_tau, bias_offset_correlation=corr, ambiguous=bool(confounded),
                        bias_sigma_stat=stat,
                        notes=notes)

    def _tau_rows(self, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """([n, T] coherence curves, [n] jackknife block) of the τ window's patch pairs measured on the
        scan `taus` (pairs registered before the τ in force changed are left out)."""
        pairs = [p for p in self.tau_pairs if p.taus is not None and len(p.taus) == len(taus) and
                 np.allclose(p.taus, taus, rtol=1e-9, atol=0.0)]
        q, blk = [], []
        n = len(pairs)
        for i, p in enumerate(pairs):
            ok = _tau_rows_measured(p)
            q.append(p.tau_coherence[ok])
            blk += [i * TAU_BLOCKS // max(n, 1)] * int(ok.sum())
        if not q:
            return np.zeros((0, len(taus))), np.zeros(0, int)
        return np.vstack(q), np.array(blk, int)

    def fit_tau(self, calib: Calibration) -> tuple[float | None, float | None, int, str | None]:
        """(τ, σ, patch pairs used, note): `tau_peak` on the τ window's patch pairs, over the scan
        around the τ in force. None, with the reason in the note, when too few patch pairs saw their
        comet tail change (slow or steady motion, or no CPU to spare), when the peak lies at the
        scan's edge, or when σ exceeds `TAU_MAX_REL_SIGMA` of τ."""
        taus = calib.tau_s * TAU_SCAN
        q, blk = self._tau_rows(taus)
        tau, sigma, problem = tau_peak(q, blk, taus)
        if problem is not None:
            held = self.tau_pairs[-1].t_b - self.tau_pairs[0].t_a if self.tau_pairs else 0.0
            where = (f" in the last {max(self.tau_window_s, held):.0f} s (or the monitor had no CPU to spare "
                     "for it)" if len(q) < MIN_TAU_PATCHES else "")
            return None, None, len(q), f"tau_s: not estimated: {problem}{where}"
        return tau, sigma, len(q), None

    def tau_misfit(self, calib: Calibration, tau: float) -> float:
        """1 − the window's mean tail-phase coherence at τ (interpolated in log τ on the scan around the
        τ in force): the prediction residual of the comet tails a change of τ must lower."""
        taus = calib.tau_s * TAU_SCAN
        q, _ = self._tau_rows(taus)
        if not len(q) or not taus[0] <= tau <= taus[-1]:
            return math.nan
        return float(1.0 - np.interp(math.log(tau), np.log(taus), q.mean(axis=0)))

    def residual(self, calib: Calibration, integral: GyroIntegral, bias, offset: float) -> float:
        """Robust RMS (px) of the window's displacement mismatch under (bias, offset): the prediction
        residual a change must lower before it is applied."""
        rows = self._rows()
        if rows is None:
            return math.nan
        t_a, t_b, cen, meas, _, _ = rows
        return _robust_rms((meas - predict(calib, integral, t_a, t_b, cen, np.asarray(bias, float),
                                           float(offset))).ravel())

    def _jackknife(self, J: np.ndarray, r: np.ndarray, w: np.ndarray, blk: np.ndarray) -> np.ndarray:
        """The parameters' covariance [4, 4] from a delete-one-block jackknife of the linearised step at
        the solution (infinite when there are too few blocks)."""
        g = int(blk.max()) + 1 if len(blk) else 0
        unknown = np.diag(np.full(N_PARAMS, np.inf))
        if g < 3:
            return unknown
        est = []
        for k in range(g):
            m = blk != k
            A = J[m] * w[m, None]
            N = J[m].T @ A
            try:
                est.append(-np.linalg.solve(N + 1e-9 * np.trace(N) * np.eye(N_PARAMS), A.T @ r[m]))
            except np.linalg.LinAlgError:
                return unknown
        est = np.array(est)
        d = est - est.mean(axis=0)
        return (g - 1) / g * d.T @ d


def _tau_rows_measured(pair: Pair) -> np.ndarray:
    """[P] bool: the patch pairs of `pair` whose τ coherence was measured (`Registrar.tau_coherence`)."""
    return np.all(np.isfinite(pair.tau_coherence), axis=1)


def _tau_measured(pair: Pair) -> int:
    return int(_tau_rows_measured(pair).sum())


def tau_peak(q: np.ndarray, blk: np.ndarray, taus: np.ndarray
             ) -> tuple[float | None, float | None, str | None]:
    """(τ, σ, None) from patch-pair coherence curves `q` [n, T] over the scan `taus` [T], or
    (None, None, the problem): τ maximises the summed coherence (parabolic peak in log τ), σ from a
    delete-one-block jackknife over the blocks `blk` [n] with a `TAU_MODEL_ERROR` floor. Needs
    `MIN_TAU_PATCHES` rows, a peak inside the scan and σ below `TAU_MAX_REL_SIGMA` of τ."""
    n = len(q)
    if n < MIN_TAU_PATCHES:
        return None, None, (f"{n} patch pairs saw their comet tails change by {TAU_MIN_LEVER_PX} working "
                            f"px or more (needs {MIN_TAU_PATCHES}): the motion is too slow or too steady to "
                            "show tau")
    tau = _scan_peak(q.sum(axis=0), taus)
    if tau is None:
        return None, None, (f"the best fit lies at the edge of the scan ({1e3 * taus[0]:.2f}–"
                            f"{1e3 * taus[-1]:.2f} ms)")
    g = int(blk.max()) + 1
    est = [_scan_peak(q[blk != k].sum(axis=0), taus) for k in range(g)] if g >= 3 else [None]
    if any(e is None for e in est):
        return None, None, "the blocks disagree beyond the scan"
    sigma = float(_jackknife_sigma(np.array(est)))
    # one tail per patch (the centre's: under roll the tails vary across a patch) and the spread of the
    # cross-power modelled for a scene of independent frequencies: model errors the jackknife cannot
    # see, bounded here at 5 % of τ
    sigma = math.hypot(sigma, TAU_MODEL_ERROR * tau)
    if not sigma < TAU_MAX_REL_SIGMA * tau:
        return None, None, (f"too uncertain (sigma {1e3 * sigma:.2f} ms of {1e3 * tau:.2f} ms) with this "
                            "motion")
    return tau, sigma, None


def _jackknife_sigma(est: np.ndarray) -> np.ndarray:
    """1-σ from the g delete-one-block estimates `est` [g, …]: √((g − 1)/g · Σ (est − mean)²)."""
    g = len(est)
    return np.sqrt((g - 1) / g * np.sum((est - est.mean(axis=0)) ** 2, axis=0))


def _scan_peak(score: np.ndarray, taus: np.ndarray) -> float | None:
    """The maximum of `score` over the log-spaced scan `taus`, refined by a parabola in log τ; None at
    the scan's edge (the maximum may lie beyond it)."""
    i = int(np.argmax(score))
    if i == 0 or i == len(score) - 1:
        return None
    y0, y1, y2 = score[i - 1], score[i], score[i + 1]
    den = y0 - 2 * y1 + y2
    off = 0.5 * (y0 - y2) / den if den < 0 else 0.0
    step = math.log(taus[i + 1] / taus[i])
    return float(math.exp(math.log(taus[i]) + float(np.clip(off, -0.5, 0.5)) * step))


def _huber(r: np.ndarray) -> np.ndarray:
    s = 1.4826 * np.median(np.abs(r)) + 1e-9
    a = np.abs(r) / (2.0 * s)
    return np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))


def _robust_rms(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r))) if len(r) else math.nan
