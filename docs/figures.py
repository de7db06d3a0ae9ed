"""Regenerate the figures of the docs from the real renderer and commands: `python docs/figures.py`.

before_after.png — the README's picture: `thermod sim` renders a 75 °/s pan over a real DJI thermal
frame (the simulator's fine-time microbolometer, NETD 30 mK), `thermod deblur` restores it with the
defaults; blurry | deblurred | truth of the middle frame, each titled with its PSNR against the truth
(8-bit scale of the truth's range). Without the real frames the simulator's procedural scene is used.

kernels.png — the thermal (Eq. 18) and photon (Eq. 17) kernels of the same 50 °/s pan on the
paper's SBTI camera (τ = 8 ms, IFOV 0.0391°, 1 kHz gyro, no optical PSF), and a roll-heavy motion
rendered as a 3 × 4 kernel grid (the blur varies across the frame; kernels drawn magnified).
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from thermod.physics.calibration import Calibration  # noqa: E402
from thermod.physics.kernels import render_kernel_grid, render_photon_kernel, render_thermal_kernel  # noqa: E402

OUT = Path(__file__).with_name("kernels.png")
BEFORE_AFTER = Path(__file__).with_name("before_after.png")
MAGNIFY = 5          # the grid panel draws each kernel this many times its size in pixels


def _gyro(rate_cam_rad_s) -> tuple[np.ndarray, np.ndarray]:
    """0.2 s of ideal 1 kHz samples of a constant camera-frame rate (identity calibration)."""
    t = np.arange(-0.2, 0.01, 0.001)
    return t, np.tile(np.float32(rate_cam_rad_s), (len(t), 1))


def _psnr(x: np.ndarray, truth: np.ndarray) -> float:
    """PSNR on the 8-bit scale of benchmarks/bench_quality.py: the truth's 0.5–99.5 % range → 0–255,
    both images clipped to it."""
    lo, hi = np.percentile(truth, (0.5, 99.5))
    to8 = lambda a: np.clip((a - lo) / (hi - lo), 0, 1) * 255.0  # noqa: E731
    return 10 * math.log10(255.0 ** 2 / float(np.mean((to8(x) - to8(truth)) ** 2)))


def before_after() -> None:
    """blurry | deblurred | truth of one simulated 75 °/s pan, through the real commands."""
    import h5py

    thermod = [sys.executable, "-m", "thermod.cli"]
    with tempfile.TemporaryDirectory(prefix="thermod-figure-") as tmp:
        rec, out = Path(tmp) / "pan.h5", Path(tmp) / "pan_sharp.h5"
        subprocess.run([*thermod, "sim", "-o", str(rec), "--scene", "real:3", "--motion", "pan:75",
                        "--seconds", "0.3", "--effect", "netd=0.03", "--seed", "1", "--no-progress"],
                       check=True)
        subprocess.run([*thermod, "deblur", str(rec), "-o", str(out)], check=True)
        with h5py.File(rec) as f, h5py.File(out) as g:
            k = f["camera/frames"].shape[0] // 2
            blurry = f["camera/frames"][k].astype(np.float64)
            truth = f["truth/frames"][k].astype(np.float64)
            sharp = g["deblurred/frames"][k].astype(np.float64)
    lo, hi = np.percentile(truth, (0.5, 99.5))
    fig = plt.figure(figsize=(12, 3.4), layout="constrained")
    for ax, img, title in zip(fig.subplots(1, 3), (blurry, sharp, truth),
                              (f"microbolometer frame, {_psnr(blurry, truth):.1f} dB",
                               f"thermod, {_psnr(sharp, truth):.1f} dB", "truth"), strict=True):
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi)
        ax.set_title(title)
        ax.set_axis_off()
    fig.savefig(BEFORE_AFTER, dpi=90)
    print(f"wrote {BEFORE_AFTER}: blurry {_psnr(blurry, truth):.2f} dB, "
          f"deblurred {_psnr(sharp, truth):.2f} dB")


def kernels() -> None:
    calib = Calibration()
    t, pan = _gyro([0.0, math.radians(50.0), 0.0])           # +y: the camera turns right
    thermal = render_thermal_kernel(t, pan, calib, 0.0, psf=False)
    photon = render_photon_kernel(t, pan, calib, 0.0, 1.0 / calib.frame_rate_hz, psf=False)
    t, roll = _gyro([0.0, math.radians(5.0), math.radians(100.0)])   # mostly about the optical axis
    grid = render_kernel_grid(t, roll, calib, 0.0, grid=(3, 4), psf=False)

    fig = plt.figure(figsize=(11, 3.6), layout="constrained")
    axes = fig.subplots(1, 2, width_ratios=[1.2, 1])
    ax = axes[0]
    for k, label in ((thermal, "thermal (Eq. 18, 5τ window)"), (photon, "photon (Eq. 17, 20 ms box)")):
        profile = k.weights.sum(axis=0)
        ax.step(np.arange(profile.size) - k.origin[1], profile, where="mid", label=label)
    ax.set_xlabel("displacement u_x (px); 0 = where the pixel looks at the read time")
    ax.set_ylabel("kernel weight per column")
    ax.set_title("one 50 °/s pan, two detectors")
    ax.legend()

    ax = axes[1]
    h, w = grid.image_shape
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    for i, row in enumerate(grid.kernels):
        for j, k in enumerate(row):
            cy, cx = grid.centers[i, j]
            kh, kw = k.weights.shape
            oy, ox = k.origin
            m = MAGNIFY
            ax.imshow(k.weights ** 0.5, cmap="gray_r", interpolation="nearest",
                      extent=(cx - m * (ox + 0.5), cx + m * (kw - ox - 0.5), cy + m * (kh - oy - 0.5),
                              cy - m * (oy + 0.5)))
            ax.plot(cx, cy, "r+", ms=8)
    ax.set_title(f"100 °/s roll: a 3 × 4 kernel grid (√weight, ×{MAGNIFY})")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}: thermal extent {thermal.extent_px:.1f} px, photon extent {photon.extent_px:.1f} px, "
          f"roll grid extents {min(k.extent_px for r in grid.kernels for k in r):.1f}–"
          f"{grid.max_extent_px:.1f} px")


if __name__ == "__main__":
    if sys.argv[1:] != ["before_after"]:
        kernels()
    before_after()
