"""Deconvolution speed: thermod.physics.deconv beside a plain NumPy/SciPy K&F of the same algorithm.

    .venv/bin/python -m benchmarks.bench_deconv [--quick]

For each frame size (320×256, 640×480, 1280×1024) and comet kernel length (17, 33, 65 px) it
prints the median time of one frame on one core (K&F α = 2/3 and Wiener), the plain version's
median (float64 NumPy, scipy.fft, OTF rebuilt per call, K&F's analytic quartic evaluated every
iteration — the reference Matlab algorithm transcribed), the speed-up, both PSNRs (equal PSNR
= same algorithm), and frames/s with two threads (one Deconvolver each) on 2 cores.
A second table compares the FFT back ends (pyFFTW vs scipy.fft) on the same solver.
Target: 640×480 with a 65 px kernel ≤ 15 ms median on one core and ≥ 8× the plain version.

Spatially varying table (`--only varying`; 640×480, roll blur rendered on a 12×16 grid of
tangential comets): the uniform solve (OTF cached, and a new kernel every frame as in the daemon)
beside tile solves on 3×4 (full blending: the reference) and 6×8 (blend ramp 0.25 of the spacing)
grids, one tile at a time (the previous loop, `tile_by_tile`) and stacked (`run_varying`),
interleaved medians of the thread's CPU time, the ratio to uniform ("× uniform") and PSNR.
Roll-family table (`--only roll`): the same solves on bench_quality's roll-heavy family (real
Betaflight roll segments, held-out scenes), mean 8-bit PSNR and median CPU time per frame.
Target: spatially varying ≤ 2× uniform at ≥ the 3×4 reference's PSNR − 0.2 dB.

Large-sensor table: K&F and Wiener at 640×480, 640×512, 1280×1024 beside the FFT floor (one
float32 rfft2 + irfft2 pair at the solver's padded size, same plan type), in ms and ms per
megapixel, with the per-frame budget of a 2-worker daemon (2 / fps).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy.fft  # noqa: E402

from thermod.physics import deconv  # noqa: E402
from thermod.physics.kernels import blur  # noqa: E402
from thermod.sim.kernels import comet  # noqa: E402
from thermod.sim.scenes import shared_data_dir, texture  # noqa: E402


def scene(shape: tuple[int, int]) -> tuple[np.ndarray, str]:
    """(frame of `shape` + 160 px, its name): a real DJI frame, else the procedural texture."""
    h, w = shape
    name = "H30T_DJI_0001_R.png" if w > 640 else "H20T_DJI_0002_R.png"
    data = shared_data_dir()
    path = data / "thermal" / name if data else None
    if path is not None and path.exists():
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32)
    else:
        img, name = texture(h + 160, w + 160, seed=0), "procedural texture (no shared/data)"
    return cv2.resize(img, (w + 160, h + 160), interpolation=cv2.INTER_AREA), name


# ------------------------------------------------------------------------ plain NumPy/SciPy K&F
def plain_kf(y: np.ndarray, weights: np.ndarray, origin, lam: float, alpha: float,
             margin: int = 8) -> np.ndarray:
    """The same algorithm (same padding, scaling, β schedule, w-/x-steps) in plain float64 NumPy."""
    lo, hi = deconv.robust_range(y)
    h, w = y.shape
    kh, kw = weights.shape
    hp = int(scipy.fft.next_fast_len(h + kh + margin, real=True))
    wp = int(scipy.fft.next_fast_len(w + kw + margin, real=True))
    x = np.empty((hp, wp))
    x[:h, :w] = (y - lo) / (hi - lo)
    cx = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, wp - w + 1) / (wp - w + 1))
    x[:h, w:] = (1 - cx) * x[:h, w - 1:w] + cx * x[:h, 0:1]
    cy = (0.5 - 0.5 * np.cos(np.pi * np.arange(1, hp - h + 1) / (hp - h + 1)))[:, None]
    x[h:, :] = (1 - cy) * x[h - 1:h, :] + cy * x[0:1, :]
    psf = np.zeros((hp, wp))
    psf[:kh, :kw] = weights
    psf = np.roll(psf, (-origin[0], -origin[1]), axis=(0, 1))
    K = np.fft.rfft2(psf)
    ky = np.fft.fftfreq(hp)[:, None]
    kx = np.fft.rfftfreq(wp)[None, :]
    G2 = (2 - 2 * np.cos(2 * np.pi * kx)) + (2 - 2 * np.cos(2 * np.pi * ky))
    KtY = np.conj(K) * np.fft.rfft2(x)
    K2 = np.abs(K) ** 2
    for beta in deconv.beta_schedule():
        gx = np.roll(x, -1, axis=1) - x
        gy = np.roll(x, -1, axis=0) - x
        if alpha == 1:
            wx = np.sign(gx) * np.maximum(np.abs(gx) - 1 / beta, 0)
            wy = np.sign(gy) * np.maximum(np.abs(gy) - 1 / beta, 0)
        else:
            wx = deconv.shrink_23_analytic(gx, beta)
            wy = deconv.shrink_23_analytic(gy, beta)
        div = (np.roll(wx, 1, axis=1) - wx) + (np.roll(wy, 1, axis=0) - wy)
        c = beta / lam
        x = np.fft.irfft2((KtY + c * np.fft.rfft2(div)) / (K2 + c * G2), s=(hp, wp))
    return (x[:h, :w] * (hi - lo) + lo).astype(np.float32)


def median_ms(fn, reps: int, best: list | None = None) -> float:
    """Median wall time (ms) of `reps` calls after one warm-up; appends the fastest to `best`."""
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    if best is not None:
        best.append(1e3 * min(ts))
    return 1e3 * float(np.median(ts))


def fps_two_threads(frames, kernel, n_per_thread: int) -> float:
    def work(d):
        for i in range(n_per_thread):
            d.run(frames[i % len(frames)], kernel)
    ds = [deconv.Deconvolver(), deconv.Deconvolver()]
    for d in ds:
        d.run(frames[0], kernel)  # plans + OTF warm
    threads = [threading.Thread(target=work, args=(d,)) for d in ds]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return 2 * n_per_thread / (time.perf_counter() - t0)


def roll_grid(rows, cols, full_shape, crop, px_per_radius=0.06):
    """Kernel grid for the frame cropped by `crop` px under roll about the optical axis: comets
    tangential to the centre of the uncropped frame, length ∝ radius (exponential thermal tail)."""
    from thermod.physics.kernels import KernelGrid
    h, w = full_shape
    hh, ww = h - 2 * crop, w - 2 * crop
    ye = np.linspace(0, hh, rows + 1)
    xe = np.linspace(0, ww, cols + 1)
    kernels = []
    for i in range(rows):
        row = []
        for j in range(cols):
            y, x = (ye[i] + ye[i + 1]) / 2 + crop - h / 2, (xe[j] + xe[j + 1]) / 2 + crop - w / 2
            length = max(2, round(px_per_radius * math.hypot(x, y)))
            row.append(comet(length, length / 3, math.degrees(math.atan2(x, -y))))
        kernels.append(row)
    centers = np.array([[((ye[i] + ye[i + 1] - 1) / 2, (xe[j] + xe[j + 1] - 1) / 2) for j in range(cols)]
                        for i in range(rows)])
    bounds = np.array([[(ye[i], ye[i + 1], xe[j], xe[j + 1]) for j in range(cols)] for i in range(rows)])
    return KernelGrid(kernels, centers, bounds.astype(int), np.zeros(rows), (hh, ww))


def interleaved_ms(fns: dict, reps: int, clock=time.perf_counter) -> dict:
    """{name: median ms} of the callables run in turn `reps` times (after one warm-up each), so that
    load from other processes hits them alike. clock=time.thread_time: CPU time of this thread
    (every FFT and numba pass of a one-core Deconvolver runs in it), which load inflates less."""
    for fn in fns.values():
        fn()
    ts = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            t0 = clock()
            fn()
            ts[k].append(clock() - t0)
    return {k: 1e3 * float(np.median(v)) for k, v in ts.items()}


def tile_by_tile(d: deconv.Deconvolver, img: np.ndarray, grid, overlap: float) -> np.ndarray:
    """The previous tile solve, kept as the reference: one tile at a time through the one-kernel
    solver (`_solve`: its own FFT calls, numba passes and OTF per tile), blended in NumPy."""
    from thermod.physics.deconv.plans import fast_len
    from thermod.physics.deconv.tiles import tile_weights
    h, w = img.shape
    centers = np.asarray(grid.centers, np.float64)
    lo, hi = deconv.robust_range(img)
    lam = d.lam_for(img, lo, hi)
    wys = tile_weights(h, centers[:, :, 0].mean(axis=1), overlap)
    wxs = tile_weights(w, centers[:, :, 1].mean(axis=0), overlap)
    m = deconv.TILE_MARGIN_PX
    ybox = [(max(0, a - m), min(h, b + m)) for a, b, _ in wys]
    xbox = [(max(0, a - m), min(w, b + m)) for a, b, _ in wxs]
    pshape = (fast_len(max(b - a for a, b in ybox) + d.margin),
              fast_len(max(b - a for a, b in xbox) + d.margin))
    out = np.zeros((h, w), np.float32)
    for r, (ys, ye, wy) in enumerate(wys):
        for c, (xs, xe, wx) in enumerate(wxs):
            (y0, y1), (x0, x1) = ybox[r], xbox[c]
            k = grid.kernels[r][c]
            tile = d._solve(img, (y0, y1, x0, x1), k.weights, k.origin, lo, hi, lam, pshape)
            out[ys:ye, xs:xe] += tile[ys - y0:ye - y0, xs - x0:xe - x0] * wy[:, None] * wx[None, :]
    return out


def varying_table(reps: int) -> None:
    from thermod.physics.kernels import blur_varying
    h, w = 480, 640
    big, name = scene((h, w))
    fine = roll_grid(12, 16, big.shape, 0)
    truth = big[80:80 + h, 80:80 + w]
    lo, hi = deconv.robust_range(truth)
    noise = np.random.default_rng(3).normal(0, 0.003 * (hi - lo), (h, w)).astype(np.float32)
    b = blur_varying(big, fine)[80:80 + h, 80:80 + w] + noise
    g34, g68 = roll_grid(3, 4, big.shape, 80), roll_grid(6, 8, big.shape, 80)
    g710 = roll_grid(7, 10, big.shape, 80)
    kmax = max(max(k.weights.shape) for row in g34.kernels for k in row)
    d = deconv.Deconvolver()
    live = deconv.Deconvolver(cache_size=1)

    def uniform_live():
        live._otfs.clear()   # the daemon's kernels never repeat: every frame computes its OTF
        return live.run(b, g34.kernels[1][1])
    fns = {
        "uniform (central kernel, OTF cached)": lambda: d.run(b, g34.kernels[1][1]),
        "uniform (a new kernel every frame, as live)": uniform_live,
        "3×4 tiles, overlap 1, one tile at a time (the reference)": lambda: tile_by_tile(d, b, g34, 1.0),
        "3×4 tiles, overlap 1, stacked": lambda: d.run_varying(b, g34, overlap=1.0),
        "6×8 tiles, overlap 0.25, one tile at a time (before)": lambda: tile_by_tile(d, b, g68, 0.25),
        "**6×8 tiles, overlap 0.25, stacked (now)**": lambda: d.run_varying(b, g68, overlap=0.25),
        "7×10 tiles, overlap 0.25, stacked, no real margins (96² FFTs)":
            lambda: d.run_varying(b, g710, overlap=0.25, margin_px=0),
    }
    load0 = os.getloadavg()[0]
    t = interleaved_ms(fns, reps, time.thread_time)
    emit(f"\n## Spatially varying, 640×480 ({name}, roll: comets tangential to the centre, 0.06 px of "
         f"tail per px of radius, up to {kmax} px; kernel_spread of the 3×4 grid "
         f"{deconv.kernel_spread(g34):.1f} px; one core, CPU time of the thread, interleaved medians of "
         f"{reps}; load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after, "
         f"{os.cpu_count()} cores)\n")
    emit("| solve | CPU ms | × uniform (OTF cached) | × uniform (as live) | PSNR dB |\n|---|---|---|---|---|")
    emit(f"| blurry input | – | – | – | {psnr(b, truth):.2f} |")
    t_uni = t["uniform (central kernel, OTF cached)"]
    t_live = t["uniform (a new kernel every frame, as live)"]
    for k, fn in fns.items():
        emit(f"| {k} | {t[k]:.1f} | {t[k] / t_uni:.2f}× | {t[k] / t_live:.2f}× | {psnr(fn(), truth):.2f} |")


def roll_table(reps: int, n_frames: int = 2) -> None:
    """Quality and CPU time on bench_quality's roll-heavy family (real Betaflight roll segments over
    its held-out scenes, 640×480, NETD 30 mK, paper gyro): per frame, every solve in turn."""
    from skimage.metrics import peak_signal_noise_ratio

    from benchmarks import bench_quality as bq
    from thermod.physics import kernels
    log = bq.mo.load_gyro_log()
    d = deconv.Deconvolver()
    m = deconv.TILE_MARGIN_PX
    rows = {"uniform (one kernel per frame, as live)": None,
            "3×4 tiles, overlap 1, one tile at a time (the reference)": ((3, 4), 1.0, m, False),
            "6×8 tiles, overlap 0.25, one tile at a time (before)": ((6, 8), 0.25, m, False),
            "**6×8 tiles, overlap 0.25, stacked (now)**": ((6, 8), 0.25, None, True),
            "6×8 tiles, overlap 0.25, stacked, no real margins (28 px periodic pad)": ((6, 8), 0.25, 0, True),
            "6×8 tiles, overlap 0.5, stacked": ((6, 8), 0.5, None, True),
            "4×6 tiles, overlap 0.25, stacked": ((4, 6), 0.25, None, True),
            "7×10 tiles, overlap 0.25, stacked, no real margins (96² FFTs)": ((7, 10), 0.25, 0, True),
            f"7×10 tiles, overlap 0.25, stacked, {m} px margins (128² FFTs)": ((7, 10), 0.25, m, True)}
    scores = {k: [] for k in rows}
    times = {k: [] for k in rows}
    load0 = os.getloadavg()[0]
    for j, start in enumerate(bq.ROLL_STARTS):
        sc = bq.REPORT_SCENES[j % len(bq.REPORT_SCENES)]
        motion = bq.mo.GyroLog(log.t_log, log.w_cam, start, spec=f"log:{start:g}")
        rec = bq.simulate(sc, motion, n_frames, 7 + j)
        c = rec.calibration
        for i in range(n_frames):
            truth = rec.extras["truth/frames"][i]
            lo, hi = (float(v) for v in np.percentile(truth, (0.5, 99.5)))
            b = rec.frames[i].astype(np.float32)
            t = float(rec.t[i])
            solves = {}
            for name, how in rows.items():
                if how is None:
                    k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, c, t)

                    def solve(k=k, b=b):
                        d._otfs.clear()   # the daemon's kernels never repeat
                        return d.run(b, k)
                else:
                    (gr, ov, mp, stacked) = how
                    g = kernels.render_kernel_grid(rec.gyro_t, rec.gyro_rate, c, t, gr)

                    def solve(g=g, ov=ov, mp=mp, stacked=stacked, b=b):
                        if stacked:
                            return d.run_varying(b, g, overlap=ov, uniform_tol_px=0, margin_px=mp)
                        return tile_by_tile(d, b, g, ov)
                solves[name] = solve
            for name, solve in solves.items():
                scores[name].append(peak_signal_noise_ratio(bq.to8(truth, lo, hi), bq.to8(solve(), lo, hi),
                                                            data_range=255))
            ms = interleaved_ms(solves, reps, time.thread_time)
            for name in rows:
                times[name].append(ms[name])
    t_uni = float(np.median(times["uniform (one kernel per frame, as live)"]))
    emit(f"\n## Spatially varying on the roll-heavy family ({len(bq.ROLL_STARTS)} log segments × "
         f"{n_frames} frames of bench_quality's roll-heavy family: held-out scenes "
         f"{', '.join(bq.REPORT_SCENES)}, 640×480, NETD 30 mK, paper gyro; K&F α = {deconv.DEFAULT_ALPHA:g}, "
         f"shipped λ rule; kernels rendered from the gyro; per frame the solves run in turn, CPU time of "
         f"the thread, median over frames of each frame's median of {reps}; load average {load0:.1f} "
         f"before, {os.getloadavg()[0]:.1f} after, {os.cpu_count()} cores)\n")
    emit("| solve | mean 8-bit PSNR dB | CPU ms | × uniform |\n|---|---|---|---|")
    for name in rows:
        ms = float(np.median(times[name]))
        emit(f"| {name} | {np.mean(scores[name]):.2f} | {ms:.1f} | {ms / t_uni:.2f}× |")


def floor_table(reps: int) -> None:
    from thermod.physics.deconv.plans import Plan
    emit(f"\n## Large sensors: cost per megapixel beside the FFT floor (33 px comet; one core, interleaved "
         f"medians of {reps})\n")
    emit("| frame | padded FFT size | K&F ms | K&F ms/MP | K&F split 2×2 ms | PSNR whole / split dB | "
         "Wiener ms | Wiener ms/MP | FFT pair ms | pair ms/MP | K&F / pair | 2-worker budget |")
    emit("|---|---|---|---|---|---|---|---|---|---|---|---|")
    k = comet(33, 33 / 4, 30.0)
    for (h, w), fps in (((480, 640), 50), ((512, 640), 60), ((1024, 1280), 30)):
        big, _ = scene((h, w))
        truth = big[80:80 + h, 80:80 + w]
        lo, hi = deconv.robust_range(truth)
        noise = np.random.default_rng(5).normal(0, 0.003 * (hi - lo), (h, w)).astype(np.float32)
        b = blur(big, k)[80:80 + h, 80:80 + w] + noise
        d, dw = deconv.Deconvolver(), deconv.Deconvolver(method="wiener")
        ds = deconv.Deconvolver(split=(2, 2))
        shape = d.padded_shape((h, w), k.weights.shape)
        plan = Plan(shape, d.fft, 1)
        plan.rin[:] = 0.5

        def pair(plan=plan):
            plan.cin[:] = plan.fwd()
            plan.inv()
        t = interleaved_ms({"kf": lambda: d.run(b, k), "split": lambda: ds.run(b, k),  # noqa: B023
                            "wiener": lambda: dw.run(b, k), "pair": pair}, reps)  # noqa: B023
        mp = h * w / 1e6
        emit(f"| {w}×{h} | {shape[1]}×{shape[0]} | {t['kf']:.1f} | {t['kf'] / mp:.1f} | {t['split']:.1f} | "
             f"{psnr(d.run(b, k), truth):.2f} / {psnr(ds.run(b, k), truth):.2f} | {t['wiener']:.1f} | "
             f"{t['wiener'] / mp:.1f} | {t['pair']:.2f} | {t['pair'] / mp:.2f} | {t['kf'] / t['pair']:.1f} | "
             f"{2000 / fps:.0f} ms at {fps} fps |")


def psnr(a, ref):
    r = float(np.percentile(ref, 99.5) - np.percentile(ref, 0.5))
    return 10 * math.log10(r * r / float(np.mean((a.astype(np.float64) - ref) ** 2)))


LINES: list[str] = []


def emit(text: str = "") -> None:
    print(text, flush=True)
    LINES.append(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions and sizes")
    ap.add_argument("--only", choices=("speed", "varying", "roll", "floor"), default=None,
                    help="run one table (speed: the per-size table and FFT back ends)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "deconv.md",
                    help="markdown copy of the tables (default benchmarks/results/deconv.md)")
    args = ap.parse_args(argv)
    sizes = [(256, 320), (480, 640)] + ([] if args.quick else [(1024, 1280)])
    klens = [17, 65] if args.quick else [17, 33, 65]
    reps = 5 if args.quick else 25
    emit("# Deconvolution speed\n")
    emit(f"`benchmarks/bench_deconv.py{' --quick' if args.quick else ''}`: FFT back end "
         f"{deconv.Deconvolver().fft}, one core per Deconvolver, medians of {reps} runs; load average "
         f"before the run {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (the machine is shared).\n")
    emit("Scenes: " + "; ".join(f"{w}×{h} {scene((h, w))[1]}" for h, w in sizes) + ".\n")
    if args.only in (None, "varying"):
        varying_table(reps)
    if args.only in (None, "roll"):
        roll_table(max(3, reps // 5))
    if args.only in (None, "floor"):
        floor_table(reps)
    if args.only in ("varying", "roll", "floor"):
        emit(f"\nload average after the run {os.getloadavg()[0]:.1f}")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(LINES) + "\n")
        return 0
    emit("\n## Speed per frame size and kernel\n")
    emit("| frame | kernel | K&F α=2/3 ms (fastest) | Wiener ms | plain K&F ms | speed-up | "
         "PSNR thermod / plain (dB) | blurry dB | fps, 2 threads |")
    emit("|---|---|---|---|---|---|---|---|---|")
    results = []
    for h, w in sizes:
        big, _ = scene((h, w))
        for L in klens:
            k = comet(L, L / 4, 30.0)
            truth = big[80:80 + h, 80:80 + w]
            rng = np.random.default_rng(L)
            lo, hi = deconv.robust_range(truth)   # noise 0.3 % of the scene's range (NETD-like)
            noise = rng.normal(0, 0.003 * (hi - lo), (h, w)).astype(np.float32)
            b = blur(big, k)[80:80 + h, 80:80 + w] + noise
            d = deconv.Deconvolver()
            dw = deconv.Deconvolver(method="wiener")
            best: list = []
            t_kf = median_ms(lambda: d.run(b, k), reps, best)  # noqa: B023
            t_w = median_ms(lambda: dw.run(b, k), reps)  # noqa: B023
            out = d.run(b, k)
            lam = d.last_lam   # the noise-adaptive λ thermod chose: the plain version uses the same
            preps = max(2, reps // (3 if h < 1000 else 6))
            t_plain = median_ms(lambda: plain_kf(b, k.weights, k.origin, lam, 2 / 3), preps)  # noqa: B023
            ref = plain_kf(b, k.weights, k.origin, lam, 2 / 3)
            fps = fps_two_threads([b, b.copy()], k, 4 if args.quick else 10)
            kname = f"{L} px ({k.weights.shape[1]}×{k.weights.shape[0]})"
            row = (f"{w}×{h}", kname, t_kf, t_w, t_plain, t_plain / t_kf,
                   psnr(out, truth), psnr(ref, truth), psnr(b, truth), fps)
            results.append(row)
            emit(f"| {row[0]} | {row[1]} | {t_kf:.1f} ({best[0]:.1f}) | {t_w:.1f} | {t_plain:.0f} | "
                 f"{row[5]:.1f}× | {row[6]:.2f} / {row[7]:.2f} | {row[8]:.2f} | {fps:.0f} |")
    # FFT back ends on the same solver, timed alternately so that load from other processes hits both
    emit("\n| FFT back end | 640×480, 65 px K&F ms (interleaved runs) |\n|---|---|")
    big, _ = scene((480, 640))
    k = comet(65, 65 / 4, 30.0)
    b = blur(big, k)[80:560, 80:720]
    decs = {}
    for fft in ("scipy", "fftw"):
        try:
            decs[fft] = deconv.Deconvolver(fft=fft)
            decs[fft].run(b, k)
        except deconv.DeconvError as e:
            emit(f"| {fft} | unavailable ({e}) |")
    times = {fft: [] for fft in decs}
    for _ in range(2 * reps):
        for fft, d in decs.items():
            t0 = time.perf_counter()
            d.run(b, k)
            times[fft].append(time.perf_counter() - t0)
    for fft, ts in times.items():
        emit(f"| {fft} | {1e3 * float(np.median(ts)):.1f} |")
    target = [r for r in results if r[0] == "640×480" and r[1].startswith("65 px")]
    if target:
        r = target[0]
        ok = r[2] <= 15 and r[5] >= 8
        emit(f"\ntarget 640×480 / 65 px: {r[2]:.1f} ms (≤ 15), {r[5]:.1f}× plain (≥ 8): "
             f"{'met' if ok else 'NOT met'}; load average after the run {os.getloadavg()[0]:.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(LINES) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
