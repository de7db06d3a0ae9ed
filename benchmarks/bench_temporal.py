"""Temporal deconvolution against today's single-frame default, on the simulator's fine-time truth.

    .venv/bin/python -m benchmarks.bench_temporal [--quick] [--views 4] [--frames 2]

Simulated with `thermod.sim` as benchmarks/bench_quality.py does (640×480 at 50 Hz, IFOV 0.0391°,
τ = 8 ms, paper gyro errors, real thermal scenes from ../shared/data): the SBTI constant rotations at
6.25–100 °/s and the roll-heavy segments of the real Betaflight log, at NETD 10, 30 and 60 mK, on
bench_quality's REPORT_SCENES (the agreement thresholds of `deconv.temporal` were set on its fit
scenes real:0 and real:6). Each case renders `views − 1 + frames` frames; the last `frames` are
scored, each restored with its full history.

Methods: the single-frame default (`thermod deblur`: thermal kernel grid 6×8, K&F α = 1,
noise-adaptive λ, `Deconvolver.run_varying`) and `TemporalDeconvolver(views)` fed the same grids
(whose single-frame solve is that very default). PSNR on the 8-bit scale of bench_quality (the
truth's 0.5–99.5 % range); CPU ms per frame (process time, one FFT thread, a shared loaded machine:
compare the ratio) and FFT pairs per frame (one forward + one inverse real FFT of the whole frame's
padded size; tiles counted by their share of points).

Writes benchmarks/results/temporal.md and temporal.png (a crop of one frame at 30 mK and 25 °/s:
blurry, single-frame, temporal, truth, and both estimates' errors).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

import numpy as np  # noqa: E402
from skimage.metrics import peak_signal_noise_ratio  # noqa: E402

from benchmarks.bench_quality import REPORT_SCENES, ROLL_STARTS, SPEEDS, pan_motion, simulate, to8  # noqa: E402
from thermod.physics import kernels  # noqa: E402
from thermod.physics.deconv.temporal import DEFAULT_VIEWS, LAM_SCALE, TemporalDeconvolver  # noqa: E402
from thermod.sim import motion as mo  # noqa: E402

HERE = Path(__file__).resolve().parent
NETDS = (0.01, 0.03, 0.06)
GRID = (6, 8)   # `thermod deblur`'s default (cli.deblur.OFFLINE.grid)
TARGET_DB = {0.01: 0.3, 0.03: 1.5, 0.06: 1.5}


def run_case(scene, motion, seed, netd, views, frames, lam_scale=LAM_SCALE):
    """[(single psnr, temporal psnr, single cpu s, temporal cpu s, single pairs, temporal pairs)] of
    the last `frames` frames, and the images of the last one (blurry, single, temporal, truth)."""
    n = views - 1 + frames
    rec = simulate(scene, motion, n, seed, netd)
    c = rec.calibration
    td = TemporalDeconvolver(c, views=views, lam_scale=lam_scale)
    rows, last = [], None
    for i in range(n):
        t = float(rec.t[i])
        g = kernels.render_kernel_grid(rec.gyro_t, rec.gyro_rate, c, t, GRID)
        out = td.run(rec.frames[i], g, t, rec.gyro_t, rec.gyro_rate)
        if i < n - frames:
            continue
        single_pairs = td.last_fft_pairs_single
        truth = rec.extras["truth/frames"][i]
        lo, hi = (float(v) for v in np.percentile(truth, (0.5, 99.5)))
        t8 = to8(truth, lo, hi)
        ps = peak_signal_noise_ratio(t8, to8(td.last_single, lo, hi), data_range=255)
        pt = peak_signal_noise_ratio(t8, to8(out, lo, hi), data_range=255)
        cs, ct = td.last_cpu_seconds
        rows.append((ps, pt, cs, cs + ct, single_pairs, td.last_fft_pairs))
        last = (to8(rec.frames[i], lo, hi), to8(td.last_single, lo, hi), to8(out, lo, hi), t8)
    return rows, last


def figure(images, title: str, path: Path) -> None:
    """A crop at 2×: blurry, single-frame, temporal, truth; below, each estimate's error (±12 levels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    crop = (slice(180, 300), slice(200, 360))
    fig, ax = plt.subplots(2, 4, figsize=(16, 6.4))
    names = ("blurry", "single-frame default", "temporal", "truth")
    for a, im, name in zip(ax[0], images, names, strict=True):
        a.imshow(im[crop], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        a.set_title(name)
    truth = images[3]
    for a, im, name in zip(ax[1, 1:3], images[1:3], ("single − truth", "temporal − truth"), strict=True):
        a.imshow((im - truth)[crop], cmap="RdBu_r", vmin=-12, vmax=12, interpolation="nearest")
        a.set_title(name)
    for a in ax.ravel():
        a.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one scene, one frame, 30 mK only")
    ap.add_argument("--views", type=int, default=DEFAULT_VIEWS)
    ap.add_argument("--lam-scale", type=float, default=LAM_SCALE, help="joint λ / single λ")
    ap.add_argument("--frames", type=int, default=None, help="scored frames per case (default 2, quick 1)")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    frames = args.frames or (1 if args.quick else 2)
    scenes = REPORT_SCENES[:1] if args.quick else REPORT_SCENES
    netds = (0.03,) if args.quick else NETDS
    say = lambda s: print(s, flush=True)  # noqa: E731
    t_start = time.perf_counter()
    log = mo.load_gyro_log()
    results: dict = {}
    fig_images, fig_title = None, ""
    for netd in netds:
        cases = [(f"{sp:g}", scenes[j], pan_motion(sp, 0.35 + 1.1 * j), 100 * i + j)
                 for i, sp in enumerate(SPEEDS) for j in range(len(scenes))]
        starts = ROLL_STARTS[:len(scenes)] if args.quick else ROLL_STARTS
        cases += [(f"log@{s:g}s", scenes[j % len(scenes)],
                   mo.GyroLog(log.t_log, log.w_cam, s, spec=f"log:{s:g}"), 7 + j)
                  for j, s in enumerate(starts)]
        for level, scene, motion, seed in cases:
            rows, last = run_case(scene, motion, seed, netd, args.views, frames, args.lam_scale)
            results.setdefault(netd, {}).setdefault(level, []).extend(rows)
            r = np.array(rows)
            say(f"  NETD {netd * 1000:.0f} mK {level} {scene}: single {r[:, 0].mean():.2f} temporal "
                f"{r[:, 1].mean():.2f} ({r[:, 1].mean() - r[:, 0].mean():+.2f} dB), CPU "
                f"{r[:, 2].mean() * 1e3:.0f} → {r[:, 3].mean() * 1e3:.0f} ms")
            if netd == 0.03 and level == "25" and fig_images is None:
                fig_images = last
                fig_title = (f"{scene}, {level} °/s, NETD 30 mK, {args.views} views: PSNR single "
                             f"{rows[-1][0]:.2f} dB, temporal {rows[-1][1]:.2f} dB")
    lines = ["# Temporal deconvolution", "",
             f"Generated by `{' '.join(['benchmarks/bench_temporal.py', *(argv or sys.argv[1:])])}`: "
             f"{len(scenes)} held-out scenes ({', '.join(scenes)}) × {frames} scored frames per level, "
             f"{args.views} views (frame t and {args.views - 1} predecessors), joint λ ×{args.lam_scale:g}, "
             f"kernel grid {GRID[0]}×{GRID[1]}, "
             "640×480 at 50 Hz, paper gyro. Single = today's single-frame default (`thermod deblur`); "
             "PSNR in dB (8-bit scale of the truth's 0.5–99.5 % range).", ""]
    summary = []
    for netd, res in results.items():
        lines += [f"## NETD {netd * 1000:.0f} mK", "",
                  "| motion (°/s or log segment) | single | temporal | gain | worst frame gain "
                  "| CPU ms single → temporal | FFT pairs single → temporal |",
                  "|---|---|---|---|---|---|---|"]
        gains, sbti_gains = [], []
        for level, rows in res.items():
            r = np.array(rows)
            g = r[:, 1] - r[:, 0]
            gains.append(g.mean())
            if not level.startswith("log"):
                sbti_gains.append(g.mean())
            lines.append(f"| {level} | {r[:, 0].mean():.2f} | {r[:, 1].mean():.2f} | {g.mean():+.2f} "
                         f"| {g.min():+.2f} "
                         f"| {np.median(r[:, 2]) * 1e3:.0f} → {np.median(r[:, 3]) * 1e3:.0f} "
                         f"| {np.median(r[:, 4]):.1f} → {np.median(r[:, 5]):.1f} |")
        allr = np.concatenate([np.array(v) for v in res.values()])
        mean_gain = float(allr[:, 1].mean() - allr[:, 0].mean())
        lines.append(f"| **mean** | **{allr[:, 0].mean():.2f}** | **{allr[:, 1].mean():.2f}** "
                     f"| **{mean_gain:+.2f}** "
                     f"| {(allr[:, 1] - allr[:, 0]).min():+.2f} | {np.median(allr[:, 2]) * 1e3:.0f} → "
                     f"{np.median(allr[:, 3]) * 1e3:.0f} | {np.median(allr[:, 4]):.1f} → "
                     f"{np.median(allr[:, 5]):.1f} |")
        lines.append("")
        summary.append((netd, mean_gain, min(gains), TARGET_DB[netd]))
    gains_text = ", ".join(f"{g:+.2f}" for _, g, _, _ in summary)
    targets_text = ", ".join(f"+{t:.1f}" for _, _, _, t in summary)
    netds = "/".join(f"{n * 1000:.0f}" for n, _, _, _ in summary)
    lines.insert(1, f"<!-- summary: temporal deblurring ({args.views} views) over the single-frame default, "
                    f"NETD {netds} mK | {gains_text} dB | {targets_text} dB -->")
    lines += ["## Targets (issue 26, goal 3)", "",
              "| NETD | mean gain | target | met | worst level's mean gain (≥ 0 wanted) | met |",
              "|---|---|---|---|---|---|"]
    for netd, g, worst, target in summary:
        lines.append(f"| {netd * 1000:.0f} mK | {g:+.2f} dB | +{target:.1f} dB "
                     f"| {'yes' if g >= target else 'NO'} "
                     f"| {worst:+.2f} dB | {'yes' if worst >= 0 else 'NO'} |")
    lines += ["", f"Run time {time.perf_counter() - t_start:.0f} s; load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} cores at the end (a shared machine: CPU times are loaded; compare ratios)."]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "temporal.md").write_text("\n".join(lines) + "\n")
    if fig_images is not None:
        figure(fig_images, fig_title, args.out / "temporal.png")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
