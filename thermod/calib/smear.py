"""Which detector explains a recording's smear: no blur, a box (photon) or an exponential (microbolometer).

Each smeared frame k is compared with frame k − 1 warped into its pixels by the recording's motion
(Eq. 16 per row, `thermod.physics.deconv.temporal`). Under a blur model with kernels K_k, K_{k−1}
(none; a box over one frame period, Eq. 17; an exponential with τ, Eq. 18, τ scanned and the best
over all frames kept), both sides become the same twice-blurred scene when the model is right:
K_{k−1} ⊛ B_k = K_k ⊛ warp(B_{k−1}) (the kernels commute; the warp between two frames barely turns a
kernel). A per-frame gain and offset (an AGC) are fitted by least squares over the warp's support,
and the gap of a model is ‖left − fitted right‖ / ‖left − its mean‖ there: dividing by the blurred
signal's own size keeps a wider kernel from scoring by smoothing alone. The model with the least
gap over all frames explains the smear when it also beats the runner-up on a significant majority
of the frames (one-sided sign test, p < `SIGNIFICANCE`), else the verdict is undecided; the
per-frame gaps are the evidence. The motion may be the recording's gyro or the track estimated from
the video: the rule needs no truth and no static scene.
docs/design.md §8, "Which kernel explains the smear".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import binomtest

from thermod.errors import RecordingError
from thermod.physics.calibration import RANGES, Calibration
from thermod.physics.deconv.temporal import warp, warp_maps, warped_support
from thermod.physics.kernels.blur import blur
from thermod.physics.kernels.render import render_photon_kernel, render_thermal_kernel
from thermod.physics.kernels.types import KernelError

MODELS = ("none", "box", "exponential")
MIN_EXTENT_PX = 2.0        # a frame smears when its exponential kernel (the calibration's τ) spans this
TAU_SCAN = np.geomspace(0.5, 2.0, 9)   # τ scanned, × the calibration's
SIGNIFICANCE = 0.05        # the leader is named when it wins this clearly frame by frame (sign test)
MIN_PIXELS = 1000          # of warp support for a frame to count


@dataclass
class SmearComparison:
    """Per-frame gaps of each model's prediction (`MODELS`), their totals and the verdict."""

    frames: list[int] = field(default_factory=list)       # frame indices predicted
    extent_px: list[float] = field(default_factory=list)  # their exponential kernel's extent (px)
    gaps: dict[str, list[float]] = field(default_factory=dict)
    total: dict[str, float] = field(default_factory=dict)  # √(Σ SSR / Σ signal) over the frames
    tau_s: float = math.nan                                # the exponential's τ that fits best
    best: str | None = None         # the leader, when it leads on a significant share of the frames
    leader: str | None = None       # the model with the least total gap
    margin: float = math.nan        # the runner-up's total / the leader's (> 1)
    wins: int = 0                   # frames on which the leader's gap is below the runner-up's
    p_value: float = math.nan       # one-sided sign test of those wins
    note: str = ""

    def to_dict(self) -> dict:
        return {"models": list(MODELS), "frames": self.frames, "extent_px": self.extent_px,
                "gaps": self.gaps, "total": self.total, "tau_s": self.tau_s, "best": self.best,
                "leader": self.leader, "margin": self.margin, "wins": self.wins, "p_value": self.p_value,
                "note": self.note}

    def summary(self) -> str:
        if not self.frames:
            return f"which kernel explains the smear: undecided ({self.note})"
        tot = ", ".join(f"{m} {self.total[m]:.4f}" for m in MODELS)
        evidence = (f"gap over {len(self.frames)} smeared frames: {tot}; τ {1e3 * self.tau_s:.1f} ms; "
                    f"{self.leader} ahead of the runner-up on {self.wins} frames, "
                    f"sign test p {self.p_value:.2g}")
        if self.best is None:
            return f"which kernel explains the smear: undecided ({self.note}; {evidence})"
        return f"which kernel explains the smear: {self.best} ({evidence})"


def _affine_residual(measured: np.ndarray, pred: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(SSR after the best gain and offset, Σ (measured − its mean)²) over `mask`."""
    m = measured[mask].astype(np.float64)
    p = pred[mask].astype(np.float64)
    A = np.stack([p, np.ones_like(p)], axis=1)
    coef, *_ = np.linalg.lstsq(A, m, rcond=None)
    r = m - A @ coef
    return float(r @ r), float(np.sum((m - m.mean()) ** 2))


def compare(frames, frame_t, gyro_t, gyro_rate, calib: Calibration, *,
            max_frames: int = 40) -> SmearComparison:
    """The rule of the module docstring on up to `max_frames` smeared frames (the most smeared first)."""
    frames = np.asarray(frames)
    t = np.asarray(frame_t, np.float64)
    if frames.ndim != 3 or len(frames) != len(t):
        raise RecordingError("smear comparison", "camera/frames",
                             f"[N, H, W] with N frame times expected, got {frames.shape} and {t.shape}")
    out = SmearComparison(gaps={m: [] for m in MODELS})
    extent = np.zeros(len(t))
    for k in range(len(t)):
        try:
            extent[k] = render_thermal_kernel(gyro_t, gyro_rate, calib, float(t[k]), psf=False).extent_px
        except KernelError:          # no gyro around this frame: it is not compared
            extent[k] = math.nan
    cand = [k for k in range(1, len(t)) if extent[k] >= MIN_EXTENT_PX and np.isfinite(extent[k - 1])]
    cand = sorted(sorted(cand, key=lambda k: -extent[k])[:max_frames])
    # the scan stays inside the range a Calibration accepts (a τ near 1 s scans below it only)
    taus = np.clip(float(calib.tau_s) * TAU_SCAN, *RANGES["tau_s"][:2])
    taus = taus[np.r_[True, np.diff(taus) > 0]]

    def kernels(tk: float, tj: float, c: Calibration, photon: bool):
        render = render_photon_kernel if photon else render_thermal_kernel
        return render(gyro_t, gyro_rate, c, tk), render(gyro_t, gyro_rate, c, tj)

    ssr: dict = {"none": [], "box": [], **{i: [] for i in range(len(taus))}}
    sig: dict = {key: [] for key in ssr}
    for k in cand:
        maps = warp_maps(calib, gyro_t, gyro_rate, float(t[k]), float(t[k - 1]))
        if maps is None:
            continue
        mask = warped_support(maps, frames.shape[1:]) > 0
        if mask.sum() < MIN_PIXELS:
            continue
        src = warp(frames[k - 1], maps)
        measured = frames[k].astype(np.float32)
        pairs = {"none": (measured, src)}
        try:
            kk, kj = kernels(float(t[k]), float(t[k - 1]), calib, True)
            pairs["box"] = (blur(measured, kj), blur(src, kk))
            for i, tau in enumerate(taus):
                kk, kj = kernels(float(t[k]), float(t[k - 1]), calib.replace(tau_s=float(tau)), False)
                pairs[i] = (blur(measured, kj), blur(src, kk))
        except KernelError:     # a kernel of the scan (the box, a longer τ) beyond what renders: not compared
            continue
        for key, (left, right) in pairs.items():
            r, s_ = _affine_residual(left, right, mask)
            ssr[key].append(r)
            sig[key].append(s_)
        out.frames.append(int(k))
        out.extent_px.append(float(extent[k]))
    if not out.frames:
        out.note = f"no frame smears by ≥ {MIN_EXTENT_PX:g} px with the frame before it in view"
        return out

    def total(key) -> float:
        return math.sqrt(float(np.sum(ssr[key])) / max(float(np.sum(sig[key])), 1e-30))

    best_tau = min(range(len(taus)), key=total)
    out.tau_s = float(taus[best_tau])
    keys = {"none": "none", "box": "box", "exponential": best_tau}
    for m in MODELS:
        key = keys[m]
        out.gaps[m] = [float(v) for v in np.sqrt(np.asarray(ssr[key]) / np.maximum(sig[key], 1e-30))]
        out.total[m] = total(key)
    order = sorted(MODELS, key=lambda m: out.total[m])
    out.leader = order[0]
    out.margin = out.total[order[1]] / max(out.total[order[0]], 1e-30)
    out.wins = int(np.sum(np.asarray(out.gaps[order[0]]) < np.asarray(out.gaps[order[1]])))
    out.p_value = float(binomtest(out.wins, len(out.frames), 0.5, alternative="greater").pvalue)
    notes = []
    if out.p_value < SIGNIFICANCE:
        out.best = out.leader
    else:
        notes.append(f"{order[0]} and {order[1]} not told apart frame by frame")
    if best_tau in (0, len(taus) - 1):
        notes.append("τ at the edge of its scan (0.5–2× the calibration's)" if len(taus) == len(TAU_SCAN)
                     else f"τ at the edge of its scan ({1e3 * taus[0]:.3g}–{1e3 * taus[-1]:.3g} ms)")
    out.note = "; ".join(notes)
    return out


def plot(result: SmearComparison, path) -> None:
    """Per-frame gaps of the three predictions against each frame's smear (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for m, marker in zip(MODELS, ("o", "s", "^"), strict=True):
        label = f"{m} (τ {1e3 * result.tau_s:.1f} ms)" if m == "exponential" else m
        total = result.total.get(m, math.nan)
        ax.plot(result.extent_px, result.gaps.get(m, []), marker, label=f"{label}: {total:.4f}")
    ax.set_xlabel("smear of the frame (exponential kernel extent, px)")
    ax.set_ylabel("gap: frames k and k − 1, each blurred\nby the other's kernel")
    ax.set_title("which kernel explains the smear: " + (result.best or f"undecided ({result.leader} ahead, "
                                                                   f"p {result.p_value:.2g})"))
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


__all__ = ["MODELS", "SmearComparison", "compare", "plot"]
