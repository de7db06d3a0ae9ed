"""Fine-time detector renderer: the simulator's truth.

The world is a scene texture on the sphere of view directions seen by a pinhole camera with
orientation R(t) (`thermod.sim.motion.Trajectory`): the sharp view at time t is
S_t(p) = scene(R(t) K⁻¹ p), so two views are related exactly by the rotation homography of Eq. 16.

Per frame interval a canvas is sampled once from the sphere and each fine step's view warped from
it (Eq. 16); the thermal state is advanced exactly for a piecewise-constant input (Eq. 10, exact
form), with steps short enough that the image moves ≤ `step_px` (0.5 px) anywhere in the frame
(Eq. 12); under rolling readout each row is captured at its own read time with the exact in-step
exponential; the optical PSF (Eq. 19) is applied to the integrated frame. With `parallax`
(`thermod.sim.parallax.NearGround`) each step's view adds the parallax shift. The integration
starts `history_tau` τ (≥ 5, default 8) before the first row, from a settled detector. The
photon-detector variant (Eq. 2) box-averages the views over each row's exposure window instead.
The steps in full: docs/design.md §1.2, "The simulator's truth renderer".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration
from thermod.physics.detector import default_photon_exposure_s, iir_alpha, row_read_time
from thermod.sim import movers as mv
from thermod.sim.motion import Trajectory
from thermod.sim.scenes import COUNTS_PER_K


@dataclass
class Rendered:
    frames: np.ndarray          # float32 [N, H, W]: detector output (blur, readout, PSF), noiseless
    sharp: np.ndarray           # float32 [N, H, W]: the sharp view at each frame time (no PSF)
    sharp_rolling: np.ndarray | None   # rolling readout only: each row's sharp view at its read time
    n_steps: int                # fine steps integrated
    max_step_px: float          # largest image motion of any step (px), ≤ step_px by construction


@njit(cache=True, nogil=True)
def _fold(x, n):
    """Coordinate into a mirror-tiled (reflect-101) axis of n samples."""
    if n == 1:
        return 0.0
    p = 2.0 * (n - 1)
    x = x - p * math.floor(x / p)
    return p - x if x > n - 1 else x


@njit(cache=True, nogil=True)
def _sphere_maps_rows(Ms, wc, fxs, fys, cxs, cys, ws, hs):
    """remap() coordinates into the scene texture for a canvas whose pixel (u, v) of row v looks
    along d = Ms[v] (u, v, 1) in world (Ms[v] = R(t_v) K_c⁻¹: one matrix per row for a rolling-readout
    view, the same one for a global view): azimuth/elevation at fxs, fys px/rad."""
    hc = Ms.shape[0]
    mx = np.empty((hc, wc), np.float32)
    my = np.empty((hc, wc), np.float32)
    for v in range(hc):
        M = Ms[v]
        for u in range(wc):
            dx = M[0, 0] * u + M[0, 1] * v + M[0, 2]
            dy = M[1, 0] * u + M[1, 1] * v + M[1, 2]
            dz = M[2, 0] * u + M[2, 1] * v + M[2, 2]
            az = math.atan2(dx, dz)
            el = math.atan2(dy, math.sqrt(dx * dx + dz * dz))
            mx[v, u] = _fold(cxs + fxs * az, ws)
            my[v, u] = _fold(cys + fys * el, hs)
    return mx, my


class SphereScene:
    """A texture (float32 counts) on the sphere: its centre looks along the world +z axis (the
    camera's optical axis at t_ref); `ifov_rad` per texture pixel (default: the camera's)."""

    def __init__(self, texture: np.ndarray, fx: float, fy: float | None = None):
        tex = np.asarray(texture, dtype=np.float32)
        if tex.ndim != 2 or min(tex.shape) < 2:
            raise ThermodError(f"scene: expected a 2-D texture, got shape {tex.shape}")
        self.texture = np.ascontiguousarray(tex)
        self.fx, self.fy = float(fx), float(fy if fy is not None else fx)
        self.cx, self.cy = (tex.shape[1] - 1) / 2.0, (tex.shape[0] - 1) / 2.0

    def view(self, R: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """The pinhole view (float32 [height, width]) at orientation R with intrinsics K."""
        Ms = np.repeat((R @ np.linalg.inv(K))[None], int(height), axis=0)  # one M for every row
        mx, my = _sphere_maps_rows(Ms, int(width), self.fx, self.fy, self.cx, self.cy,
                                   self.texture.shape[1], self.texture.shape[0])
        return cv2.remap(self.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)

    def rolling_view(self, Rs: np.ndarray, K: np.ndarray, width: int) -> np.ndarray:
        """A view whose row r is seen at orientation Rs[r] (rolling readout), float32 [len(Rs), width]."""
        Ms = np.ascontiguousarray(Rs @ np.linalg.inv(K))
        mx, my = _sphere_maps_rows(Ms, int(width), self.fx, self.fy, self.cx, self.cy,
                                   self.texture.shape[1], self.texture.shape[0])
        return cv2.remap(self.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def image_speed_bound(calib: Calibration, w_abs: np.ndarray, margin_px: float = 0.0) -> float:
    """Upper bound of the image speed (px/s) anywhere in the frame for rates |ω| = w_abs per axis:
    the rotational flow is f(1 + ρ²)|ω_xy| + fρ|ω_z| at normalised radius ρ (corner + margin)."""
    f = max(calib.fx, calib.fy)
    dx = max(calib.cx, calib.width - 1 - calib.cx) + margin_px
    dy = max(calib.cy, calib.height - 1 - calib.cy) + margin_px
    rho = math.hypot(dx / calib.fx, dy / calib.fy)
    return f * ((1 + rho * rho) * math.hypot(w_abs[0], w_abs[1]) + rho * abs(w_abs[2]))


def render(scene: SphereScene, traj: Trajectory, frame_times, calib: Calibration, *,
           kind: str = "thermal", exposure_s: float | None = None, psf_sigma_px: float | None = None,
           step_px: float = 0.5, history_tau: float = 8.0, progress=None, parallax=None,
           movers=()) -> Rendered:
    """Render blurry frames at `frame_times` (absolute s, on the trajectory's clock) with the
    detector of `calib` (τ, readout, intrinsics, PSF). See the module docstring.

    kind: "thermal" (microbolometer, Eq. 10/11) or "photon" (box average over `exposure_s`, Eq. 2;
    default exposure = one frame period, `default_photon_exposure_s`).
    psf_sigma_px: None → calib.psf_sigma_px (Eq. 19).
    progress: optional callable(n_frames_done) for a progress bar.
    parallax: optional `thermod.sim.parallax.NearGround` (module docstring).
    movers: `thermod.sim.movers.HotObject`s moving in the world, drawn into every fine step (the
    steps are short enough for them too) and into the sharp truth (not into `sharp_rolling`).
    """
    t_frames = np.asarray(frame_times, dtype=np.float64)
    _check_render_args(t_frames, calib, kind, step_px, history_tau)
    if kind == "photon":
        exposure_s = _photon_exposure(calib, exposure_s)
    t_begin = _integration_start(t_frames, traj, calib, kind, exposure_s, history_tau)
    sigma = _psf_sigma(calib, psf_sigma_px)

    cam = _Camera(calib)
    movers = [m.at(float(t_frames[0])) if m.t_ref is None else m for m in movers or ()]
    extra_px_s = mv.max_speed_px_s(movers)
    rows_t = row_read_time(t_frames[:, None], np.arange(cam.H)[None, :], float(calib.readout_s), cam.H)
    if kind == "thermal":
        if parallax is None:
            B0 = scene.view(traj.R(t_begin)[0], cam.K, cam.W, cam.H)
        else:
            B0 = _Segment.plan(scene, traj, cam, np.array([t_begin, t_begin]), parallax).view(cam, 0)
        B0 = mv.draw_all(movers, B0, traj.R(t_begin)[0], cam.K, t_begin)
        detector = _ThermalDetector(B0, rows_t, float(calib.tau_s))
    else:
        detector = _PhotonDetector(rows_t, exposure_s, cam.W)
    n = len(t_frames)
    sharp = np.empty((n, cam.H, cam.W), np.float32)
    sharp_rolling = np.empty((n, cam.H, cam.W), np.float32) if calib.readout_s > 0 else None
    n_steps, max_step = 0, 0.0

    edges = np.r_[t_begin, t_frames]
    for k in range(n):
        for a, b in _canvas_segments(cam, calib, traj, edges[k], edges[k + 1]):
            t_bounds = _fine_steps(calib, traj, a, b, step_px, extra_px_s)
            seg = _Segment.plan(scene, traj, cam, t_bounds, parallax)
            max_step = max(max_step, cam.step_motion_px(seg.Q))
            for j in range(len(t_bounds) - 1):
                view = seg.view(cam, j)
                if movers:
                    view = mv.draw_all(movers, view, seg.R_ref @ seg.Q[j], cam.K, float(seg.t_mid[j]))
                detector.step(view, t_bounds[j], t_bounds[j + 1])
            n_steps += len(t_bounds) - 1
        sharp[k] = seg.frame_view(cam)
        if movers:
            sharp[k] = mv.draw_all(movers, sharp[k], seg.R_ref, cam.K, seg.t_end)
        if sharp_rolling is not None:
            sharp_rolling[k] = scene.rolling_view(traj.R(rows_t[k]), cam.K, cam.W)
        if progress is not None:
            progress(k + 1)
    return Rendered(_apply_psf(detector.out, sigma), sharp, sharp_rolling, n_steps, max_step)


def _check_render_args(t_frames: np.ndarray, calib: Calibration, kind: str, step_px: float,
                       history_tau: float) -> None:
    """Reject frame times, detector kinds, step sizes and readouts the renderer cannot honour."""
    if len(t_frames) == 0:
        raise ThermodError("detector: no frame times to render")
    if np.any(np.diff(t_frames) <= 0):
        raise ThermodError("detector: frame times must be strictly increasing")
    if kind not in ("thermal", "photon"):
        raise ThermodError(f"detector: kind must be 'thermal' or 'photon', got {kind!r}")
    if not 0 < step_px <= 8:
        raise ThermodError(f"detector: step_px must be in (0, 8], got {step_px}")
    tau, ro = float(calib.tau_s), float(calib.readout_s)
    period = float(np.min(np.diff(t_frames))) if len(t_frames) > 1 else math.inf
    if ro < 0 or ro >= period:
        raise ThermodError(f"detector: readout_s = {ro} must be ≥ 0 and shorter than the frame period "
                           f"{period}")
    if kind == "thermal" and (tau < 0 or history_tau < 5):
        raise ThermodError(f"detector: need tau_s ≥ 0 and history_tau ≥ 5 (got {tau}, {history_tau})")


def _photon_exposure(calib: Calibration, exposure_s: float | None) -> float:
    """The photon detector's exposure (s): as given, else one frame period (Eq. 2)."""
    if exposure_s is None:
        exposure_s = default_photon_exposure_s(calib.frame_rate_hz)
    exposure_s = float(exposure_s)
    if not 0 < exposure_s:
        raise ThermodError(f"detector: exposure_s must be > 0, got {exposure_s}")
    return exposure_s


def _integration_start(t_frames: np.ndarray, traj: Trajectory, calib: Calibration, kind: str,
                       exposure_s: float | None, history_tau: float) -> float:
    """When integration starts: before the first row of the first frame by `history_tau`·τ (thermal:
    a settled detector) or by the exposure (photon); the trajectory must cover it."""
    ro = float(calib.readout_s)
    lead = exposure_s + ro if kind == "photon" else history_tau * float(calib.tau_s) + ro
    t_begin = t_frames[0] - lead - 1e-6
    if t_begin < traj.t_start or t_frames[-1] > traj.t_end:
        raise ThermodError(f"detector: trajectory covers [{traj.t_start}, {traj.t_end}] but rendering "
                           f"needs [{t_begin}, {t_frames[-1]}]")
    return t_begin


def _psf_sigma(calib: Calibration, psf_sigma_px: float | None) -> float:
    """The optical PSF σ in px (Eq. 19): as given, else the calibration's."""
    sigma = calib.psf_sigma_px if psf_sigma_px is None else float(psf_sigma_px)
    if sigma < 0:
        raise ThermodError(f"detector: PSF sigma must be ≥ 0 px, got {sigma}")
    return sigma


def _apply_psf(frames: np.ndarray, sigma: float) -> np.ndarray:
    """Blur every frame in place with the Gaussian optical PSF (Eq. 19); returns `frames`."""
    if sigma > 0:
        for k in range(len(frames)):
            frames[k] = gaussian_psf(frames[k], sigma)
    return frames


class _Camera:
    """The detector's pinhole geometry: K, K⁻¹, size and the image corners (homogeneous, [3, 4])."""

    def __init__(self, calib: Calibration):
        self.W, self.H = int(calib.width), int(calib.height)
        self.K = calib.K
        self.K_inv = np.linalg.inv(self.K)
        W, H = self.W, self.H
        self.corners = np.array([[0, 0, 1], [W - 1, 0, 1], [0, H - 1, 1], [W - 1, H - 1, 1]], float).T
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        self.rays = self.K_inv @ np.stack([u.ravel(), v.ravel(), np.ones(W * H)])    # K⁻¹ p, [3, W·H]

    def map_corners(self, Hs: np.ndarray) -> np.ndarray:
        """The image corners mapped by each homography of Hs [n, 3, 3] → pixels [n, 2, 4]."""
        p = np.einsum("nij,jc->nic", Hs, self.corners)
        return p[:, :2] / p[:, 2:3]

    def step_motion_px(self, Rs: np.ndarray) -> float:
        """Largest image motion (px, at the corners) between consecutive orientations Rs [n, 3, 3]
        (Eq. 16 with Q = R_{j}ᵀ R_{j+1}); 0 for a single orientation."""
        if len(Rs) < 2:
            return 0.0
        Hrel = self.K @ np.einsum("nji,njk->nik", Rs[:-1], Rs[1:]) @ self.K_inv
        d = self.map_corners(Hrel) - self.corners[None, :2]
        return float(np.hypot(*d.transpose(1, 0, 2)).max())


def _canvas_segments(cam: _Camera, calib: Calibration, traj: Trajectory, a0: float, b0: float):
    """Split the interval (a0, b0] into segments over which the image travels at most half the
    frame, so that one canvas holds every view of a segment; returns [(a, b), …]."""
    speed = image_speed_bound(calib, traj.max_rate(a0, b0))
    n_sub = max(1, int(math.ceil(speed * (b0 - a0) / (0.5 * min(cam.W, cam.H)))))
    sub = np.linspace(a0, b0, n_sub + 1)
    return list(zip(sub[:-1], sub[1:], strict=True))


def _fine_steps(calib: Calibration, traj: Trajectory, a: float, b: float, step_px: float,
                extra_px_s: float = 0.0) -> np.ndarray:
    """Step boundaries over (a, b] such that the image moves ≤ `step_px` per step anywhere in the
    frame (Eq. 12: h ≤ IFOV / ω), a mover's own image speed `extra_px_s` included."""
    speed = image_speed_bound(calib, traj.max_rate(a, b)) + extra_px_s
    n_steps = max(1, int(math.ceil(speed * (b - a) / step_px)))
    return np.linspace(a, b, n_steps + 1)


@dataclass
class _Segment:
    """One canvas and the rotations that warp it into each fine step's view.

    The canvas is the pinhole view at the segment end's orientation R_ref = R(b), with intrinsics
    K_c (K shifted by the canvas origin (x0, y0) in view pixels), large enough to hold every view;
    Q[j] = R_refᵀ R(t_j) at step j's mid time (Eq. 16); with `parallax`, the canvas has a margin for
    its shifts and each view adds them (module docstring)."""

    canvas: np.ndarray
    K_c: np.ndarray
    Q: np.ndarray
    x0: int
    y0: int
    R_ref: np.ndarray | None = None
    t_mid: np.ndarray | None = None
    t_end: float = 0.0
    parallax: object = None

    @classmethod
    def plan(cls, scene: SphereScene, traj: Trajectory, cam: _Camera, t_bounds: np.ndarray,
             parallax=None) -> _Segment:
        """Sample the canvas for the steps bounded by `t_bounds` (one cv2.remap from the sphere)."""
        t_mid = 0.5 * (t_bounds[:-1] + t_bounds[1:])
        R_ref = traj.R(t_bounds[-1])[0]
        Q = np.einsum("ji,njk->nik", R_ref, traj.R(t_mid))          # Q_j = R_refᵀ R(t_j)
        pc = cam.map_corners(cam.K @ Q @ cam.K_inv)                  # view corners in the reference view
        if np.any(~np.isfinite(pc)) or np.abs(pc).max() > 1e5:
            raise ThermodError("detector: a view turned more than 90° within one frame interval; "
                               "raise the frame rate or slow the motion")
        m = 0 if parallax is None else int(math.ceil(parallax.max_shift_px(
            max(cam.K[0, 0], cam.K[1, 1]) * 1.1, t_bounds[0], t_bounds[-1])))
        x0 = int(math.floor(min(pc[:, 0].min(), 0))) - 3 - m
        y0 = int(math.floor(min(pc[:, 1].min(), 0))) - 3 - m
        x1 = int(math.ceil(max(pc[:, 0].max(), cam.W - 1))) + 4 + m
        y1 = int(math.ceil(max(pc[:, 1].max(), cam.H - 1))) + 4 + m
        K_c = cam.K.copy()
        K_c[0, 2] -= x0
        K_c[1, 2] -= y0
        return cls(scene.view(R_ref, K_c, x1 - x0 + 1, y1 - y0 + 1), K_c, Q, x0, y0, R_ref, t_mid,
                   float(t_bounds[-1]), parallax)

    def view(self, cam: _Camera, j: int) -> np.ndarray:
        """The sharp view at step j's mid time: the canvas warped by K_c Q_j K⁻¹ (Eq. 16)."""
        if self.parallax is not None:
            return self._parallax_view(cam, self.Q[j], float(self.t_mid[j]))
        Hj = self.K_c @ self.Q[j] @ cam.K_inv
        return cv2.warpPerspective(self.canvas, Hj, (cam.W, cam.H),
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_REPLICATE)

    def frame_view(self, cam: _Camera) -> np.ndarray:
        """The sharp view at the segment's end (R_ref): the canvas cropped to the frame."""
        if self.parallax is not None:
            return self._parallax_view(cam, np.eye(3), self.t_end)
        return self.canvas[-self.y0:-self.y0 + cam.H, -self.x0:-self.x0 + cam.W]


    def _parallax_view(self, cam: _Camera, Q: np.ndarray, t: float) -> np.ndarray:
        """The view at orientation R_ref·Q and time t with the parallax shift: each pixel samples the
        canvas where its source ray (`NearGround.source_rays`) lands."""
        src = self.parallax.source_rays(self.R_ref @ Q @ cam.rays, t)
        h = self.K_c @ self.R_ref.T @ src
        mx = (h[0] / h[2]).reshape(cam.H, cam.W).astype(np.float32)
        my = (h[1] / h[2]).reshape(cam.H, cam.W).astype(np.float32)
        return cv2.remap(self.canvas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class _ThermalDetector:
    """Microbolometer state B advanced exactly for a piecewise-constant input (Eq. 10 with the
    exact α of Eq. 11), each frame's rows captured at their rolling-readout read times `rows_t`."""

    def __init__(self, B0: np.ndarray, rows_t: np.ndarray, tau: float):
        n, H = rows_t.shape
        self.B, self.rows_t, self.tau = B0, rows_t, tau
        self.out = np.zeros((n, H, B0.shape[1]), np.float32)
        self.next_k, self.next_r = 0, 0          # next (frame, row) to capture
        self._tmp = np.empty(B0.shape, np.float32)

    def step(self, S: np.ndarray, ta: float, tz: float) -> None:
        """Integrate the view S held over (ta, tz]."""
        self._capture_rows(S, ta, tz)
        np.subtract(S, self.B, out=self._tmp)
        self._tmp *= np.float32(iir_alpha(tz - ta, self.tau))
        self.B += self._tmp

    def _capture_rows(self, S: np.ndarray, ta: float, tz: float) -> None:
        """Read out the rows whose read time falls in (ta, tz], each with the exact in-step
        exponential approach B + α(t_r − ta)(S − B) — no rounding to the step grid."""
        n, H = self.rows_t.shape
        while self.next_k < n and self.rows_t[self.next_k][self.next_r] <= tz:
            k, r0 = self.next_k, self.next_r
            rt = self.rows_t[k]
            r1 = int(np.searchsorted(rt, tz, side="right"))
            g = iir_alpha(rt[r0:r1] - ta, self.tau).astype(np.float32)[:, None]
            self.out[k, r0:r1] = self.B[r0:r1] + g * (S[r0:r1] - self.B[r0:r1])
            self.next_r = r1
            if r1 >= H:
                self.next_k, self.next_r = k + 1, 0


class _PhotonDetector:
    """Photon detector (Eq. 2): each row box-averages the views over its exposure window."""

    def __init__(self, rows_t: np.ndarray, exposure_s: float, width: int):
        self.rows_t, self.exposure_s = rows_t, exposure_s
        self.out = np.zeros((*rows_t.shape, width), np.float32)

    def step(self, S: np.ndarray, ta: float, tz: float) -> None:
        """Add the view S held over (ta, tz] to every row whose exposure window [t_r − E, t_r]
        overlaps it, weighted by the overlap / E. Every frame whose rows can overlap is visited
        (an exposure longer than the frame period spans several frames)."""
        rows_t, exposure = self.rows_t, self.exposure_s
        k0 = int(np.searchsorted(rows_t[:, -1], ta, side="right"))           # last row read after ta
        k1 = int(np.searchsorted(rows_t[:, 0] - exposure, tz, side="left"))  # first window opens < tz
        for k in range(k0, k1):
            rt = rows_t[k]
            ov = np.minimum(tz, rt) - np.maximum(ta, rt - exposure)
            sel = np.flatnonzero(ov > 0)
            if sel.size:
                r0, r1 = sel[0], sel[-1] + 1
                self.out[k, r0:r1] += S[r0:r1] * (ov[r0:r1] / exposure).astype(np.float32)[:, None]


def render_time_compressed(scene: SphereScene, traj: Trajectory, frame_times, calib: Calibration, *,
                           compression: float = 20.0, slow_fps: float = 50.0,
                           psf_sigma_px: float | None = None, history_tau: float = 8.0,
                           progress=None) -> Rendered:
    """The paper's synthesis as a renderer: a slow camera (`slow_fps`, the motion slowed
    `compression`×) records sharp views; re-timed `compression`× faster they are views of the fast
    motion h = 1/(slow_fps·compression) apart, fed whole through Eq. 10 (B_j = (1−α)B_{j−1} + α S_j,
    exact α, S_j the view at the end of step j). No sub-step motion and no rolling readout: the
    result shows "stepping" when a step moves the image ≥ 1 px (Eq. 12), reported as max_step_px.
    """
    t_frames = np.asarray(frame_times, dtype=np.float64)
    n, H, W = len(t_frames), int(calib.height), int(calib.width)
    if not (compression > 0 and slow_fps > 0):
        raise ThermodError(f"time compression: compression and slow_fps must be > 0 "
                           f"(got {compression}, {slow_fps})")
    if calib.readout_s > 0:
        raise ThermodError("time compression: rolling readout is not supported (the paper's synthesis "
                           "integrates whole views); use the fine-time renderer")
    h = 1.0 / (slow_fps * compression)
    per = np.diff(t_frames) / h
    if n > 1 and np.abs(per - np.round(per)).max() > 1e-6:
        raise ThermodError(f"time compression: the frame period must be a whole number of re-timed views "
                           f"(period/h = {per[0]:.4f}; h = 1/(slow_fps·compression) = {h:.3g} s)")
    tau = float(calib.tau_s)
    n_hist = int(math.ceil(history_tau * tau / h))
    t_grid = t_frames[0] + h * np.arange(-n_hist, int(round((t_frames[-1] - t_frames[0]) / h)) + 1)
    if t_grid[0] < traj.t_start:
        raise ThermodError("time compression: trajectory does not cover the history")
    sigma = _psf_sigma(calib, psf_sigma_px)
    cam = _Camera(calib)
    alpha = np.float32(iir_alpha(h, tau))
    out = np.empty((n, H, W), np.float32)
    sharp = np.empty((n, H, W), np.float32)
    Rs = traj.R(t_grid)
    max_step = cam.step_motion_px(Rs)
    B = scene.view(Rs[0], cam.K, W, H)
    k = 0
    for j in range(1, len(t_grid)):
        S = scene.view(Rs[j], cam.K, W, H)
        B += alpha * (S - B)
        if k < n and abs(t_grid[j] - t_frames[k]) < 0.5 * h:
            out[k], sharp[k] = B, S
            k += 1
            if progress is not None:
                progress(k)
    return Rendered(_apply_psf(out, sigma), sharp, None, len(t_grid) - 1, max_step)


def gaussian_psf(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Isotropic Gaussian optical PSF (Eq. 19), ±4σ support, replicated border."""
    r = max(1, int(math.ceil(4 * sigma_px)))
    return cv2.GaussianBlur(img, (2 * r + 1, 2 * r + 1), sigma_px, borderType=cv2.BORDER_REPLICATE)


def time_compress(views: np.ndarray, h_slow: float, compression: float, tau: float,
                  every: int = 1, initial: np.ndarray | None = None) -> np.ndarray:
    """The paper's time-compression synthesis: a slow, sharp sequence (views `h_slow` s apart)
    re-timed `compression`× faster and fed through the thermal IIR (Eq. 10, exact α with
    h = h_slow / compression). Returns every `every`-th integrated frame (float32).
    The re-timed image motion per view must stay < 1 px (Eq. 12) — the caller checks that."""
    views = np.asarray(views, dtype=np.float32)
    if views.ndim != 3 or len(views) == 0:
        raise ThermodError(f"time_compress: expected views [T, H, W], got shape {views.shape}")
    if compression <= 0 or h_slow <= 0 or every < 1:
        raise ThermodError("time_compress: h_slow, compression must be > 0 and every ≥ 1")
    h = h_slow / compression
    alpha = np.float32(iir_alpha(h, tau))
    B = np.array(views[0] if initial is None else initial, np.float32)
    out = []
    for i in range(len(views)):
        B += alpha * (views[i] - B)
        if (i + 1) % every == 0:
            out.append(B.copy())
    return np.asarray(out, dtype=np.float32).reshape(-1, *views.shape[1:])


# ------------------------------------------------------------------ sensor (after the optics)

@dataclass(frozen=True)
class SensorEffects:
    """What the read-out electronics add to the noiseless integrated frame (all default off).

    netd_k: temporal noise (NETD, kelvin RMS); fpn_k: fixed-pattern offset (kelvin RMS; ⅔ of the
    variance per pixel, ⅓ per column); gain_nonuniformity: per-pixel gain RMS (fraction) about
    the reference level; nonlinearity: mild quadratic response y = m + d (1 + c d / 1000 counts),
    d = x − m (c = 0.05 → +5 % response 25 K above the reference); quantisation_bits: 16 → integer
    counts, 14 → multiples of 4 counts (the 16-bit stream of a 14-bit ADC). counts_per_k: responsivity.
    nuc: one flat-field correction (`FFCEvent`), applied by `apply_sensor` when frame times are given.
    """

    netd_k: float = 0.0
    fpn_k: float = 0.0
    gain_nonuniformity: float = 0.0
    nonlinearity: float = 0.0
    quantisation_bits: int = 16
    counts_per_k: float = COUNTS_PER_K
    nuc: FFCEvent | None = None

    def validate(self) -> None:
        for name in ("netd_k", "fpn_k", "gain_nonuniformity"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ThermodError(f"sensor effect {name}: expected a finite value ≥ 0, got {v!r}")
        if not np.isfinite(self.nonlinearity) or abs(self.nonlinearity) > 1:
            raise ThermodError("sensor effect detector_nonlinearity: expected |c| ≤ 1, "
                               f"got {self.nonlinearity!r}")
        if self.nuc is not None:
            self.nuc.validate()
        if int(self.quantisation_bits) != self.quantisation_bits or not 8 <= self.quantisation_bits <= 16:
            raise ThermodError(f"sensor effect quantisation_bits: expected an integer 8–16, "
                               f"got {self.quantisation_bits!r}")


def apply_sensor(frames: np.ndarray, fx: SensorEffects, rng: np.random.Generator,
                 ref_level: float, t_frames: np.ndarray | None = None,
                 nuc_rng: np.random.Generator | None = None) -> np.ndarray:
    """Noiseless float32 frames [N, H, W] → uint16 raw counts (nonlinearity, gain, FPN, NETD, ADC).

    With `fx.nuc` and `t_frames` (s since the first frame), a flat-field correction is applied as well
    (`FFCEvent`); its new residual pattern is drawn from `nuc_rng` (default a fixed stream) so the
    temporal noise is the same realisation as without it.
    """
    fx.validate()
    n, h, w = frames.shape
    cpk = fx.counts_per_k
    gain = (1.0 + fx.gain_nonuniformity * rng.standard_normal((h, w))).astype(np.float32)
    fpn = _fpn_pattern(fx, rng, h, w)
    lsb = float(2 ** (16 - int(fx.quantisation_bits)))
    out = np.empty(frames.shape, np.uint16)
    ref = np.float32(ref_level)
    if fx.nonlinearity:
        _check_monotonic(frames, fx.nonlinearity, ref_level)
    nuc = fx.nuc if t_frames is not None else None
    after = np.zeros(n, bool) if nuc is None else np.asarray(t_frames) >= nuc.t_end_s
    fpn_after = fpn
    if after.any():
        # the new NUC leaves a new residual pattern of the same RMS and a global offset step
        fpn_after = _fpn_pattern(fx, nuc_rng or np.random.default_rng(12), h, w) + np.float32(nuc.step_counts)
    for k in range(n):
        d = frames[k] - ref
        if fx.nonlinearity:
            d = d * (1 + np.float32(fx.nonlinearity / 1000.0) * d)
        y = ref + gain * d + (fpn_after if after[k] else fpn)
        if fx.netd_k:
            y = y + (fx.netd_k * cpk * rng.standard_normal((h, w))).astype(np.float32)
        y = np.round(y / lsb) * lsb
        out[k] = np.clip(y, 0, 65535 - (65535 % lsb)).astype(np.uint16)
    if nuc is not None:
        frozen = nuc.frozen(t_frames)
        if frozen.any():
            out[frozen] = out[nuc.last_live(t_frames)]
    return out


def _fpn_pattern(fx: SensorEffects, rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Fixed-pattern offset: ⅔ of the variance per pixel, ⅓ per column (counts)."""
    return (fx.fpn_k * fx.counts_per_k * (np.sqrt(2 / 3) * rng.standard_normal((h, w))
                                          + np.sqrt(1 / 3) * rng.standard_normal((1, w)))).astype(np.float32)


def _check_monotonic(frames: np.ndarray, c: float, ref_level: float) -> None:
    """The quadratic response y = m + d (1 + c d/1000) turns over at d = −500/c: the scene must stay
    on its rising side (a detector's response never decreases with the flux)."""
    d_turn = -500.0 / c
    d = (float(frames.min()) if c > 0 else float(frames.max())) - ref_level
    if (c > 0 and d <= d_turn) or (c < 0 and d >= d_turn):
        raise ThermodError(f"--effect detector_nonlinearity={c:g}: the response turns over {abs(d_turn):.0f} "
                           f"counts {'below' if c > 0 else 'above'} the scene's median level and the scene "
                           f"reaches {abs(d):.0f}; use |c| < {500.0 / abs(d):.3g} for this scene")


@dataclass(frozen=True)
class FFCEvent:
    """A flat-field correction (shutter / NUC) at `t_start_s` (s since the first frame) lasting
    `duration_s`: frames read inside [t_start, t_start + duration) repeat the last frame read before
    it (the camera freezes its output, as Boson/Tau cores do, cf. `thermod.sim.emu_camera.FFCSchedule`);
    frames read after it carry the new NUC: a global offset `step_counts` and a new residual FPN.
    The detector's recovery from the shutter is taken to be over by the end of the frozen stretch."""

    t_start_s: float
    duration_s: float
    step_counts: float = 20.0

    @property
    def t_end_s(self) -> float:
        return self.t_start_s + self.duration_s

    def validate(self) -> None:
        if not (math.isfinite(self.t_start_s) and self.t_start_s > 0):
            raise ThermodError(f"--effect ffc_event: T_START={self.t_start_s!r} s must be > 0 (after the "
                               "first frame, whose image the frozen frames repeat)")
        if not (math.isfinite(self.duration_s) and 0 < self.duration_s <= 10):
            raise ThermodError(f"--effect ffc_event: DURATION={self.duration_s!r} s must be in (0, 10]")
        if not (math.isfinite(self.step_counts) and abs(self.step_counts) <= 1000):
            raise ThermodError(f"--effect ffc_event: STEP_COUNTS={self.step_counts!r} must be within ±1000")

    def frozen(self, t_frames) -> np.ndarray:
        t = np.asarray(t_frames, float)
        return (t >= self.t_start_s) & (t < self.t_end_s)

    def last_live(self, t_frames) -> int:
        """Index of the last frame read before the event (the one the frozen frames repeat)."""
        return int(np.searchsorted(np.asarray(t_frames, float), self.t_start_s, side="left")) - 1
