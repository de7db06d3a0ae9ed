"""The daemon's temporal rungs against its single-frame rungs, on the simulator's fine-time truth.

    .venv/bin/python -m benchmarks.bench_temporal_daemon [--quick] [--frames 10] [--score 5] [--full-test]

Simulated as benchmarks/bench_temporal.py does (640×480 at 50 Hz, paper gyro errors, real thermal
scenes, the SBTI constant rotations and roll-heavy segments of the real Betaflight log, NETD 10, 30
and 60 mK). Each case is a stream of `frames` frames restored in read order from the first (as the
daemon starts), each with the kernel grid the daemon renders for it (`restore.plan.render`,
adaptive mode: the grid the roll needs); the last `score` frames are scored.

Methods (the daemon's rungs, `thermod.runtime.governor`):
- kf: K&F alone (the single-frame default before temporal rungs, when it fits);
- wiener: Wiener alone (what the daemon ran at 640×480, 50 fps on 2 cores);
- temporal: `RecursiveDeconvolver` over Wiener, the prior from frame t − 1;
- temporal t−2: the same with the prior from t − 2 (two workers, t − 1 still being solved: two
  interleaved chains, each warp spanning two frame periods);
- temporal_kf: `RecursiveDeconvolver` over K&F, prior from t − 1.

PSNR on bench_quality's 8-bit scale (the truth's 0.5–99.5 % range). CPU ms per frame (thread CPU
time, one FFT thread; a shared machine: compare ratios) and FFT pairs per frame (one forward + one
inverse real FFT of the whole frame's padded size; tiles by their share of points).

Writes benchmarks/results/temporal_daemon.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from skimage.metrics import peak_signal_noise_ratio  # noqa: E402

from benchmarks.bench_quality import REPORT_SCENES, pan_motion, simulate, to8  # noqa: E402
from thermod.physics.deconv import Deconvolver  # noqa: E402
from thermod.physics.deconv.recursive import MEMORY, REGISTRATION_PX, RecursiveDeconvolver  # noqa: E402
from thermod.restore.plan import render  # noqa: E402
from thermod.restore.settings import DeblurConfig  # noqa: E402
from thermod.sim import motion as mo  # noqa: E402

HERE = Path(__file__).resolve().parent
NETDS = (0.01, 0.03, 0.06)
SPEEDS = (6.25, 25.0, 50.0, 100.0)
LOG_STARTS = (2.5, 6.5, 22.5)
METHODS = ("kf", "wiener", "temporal", "temporal t−2", "temporal_kf")
INTERPOLATIONS = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "lanczos4": cv2.INTER_LANCZOS4}


class Chain:
    """A recursive solver fed every `stride`-th prior (stride 2: two interleaved chains)."""

    def __init__(self, calib, method, stride, memory, registration_px, interpolation, half_test):
        self.rd = RecursiveDeconvolver(calib, Deconvolver(method=method), memory=memory,
                                       registration_px=registration_px, interpolation=interpolation,
                                       half_test=half_test)
        self.stride = stride
        self.estimates: dict[int, object] = {}

    def __call__(self, i, frame, kernel, t, gyro_t, gyro_rate):
        out, est = self.rd.solve(frame, kernel, t, gyro_t, gyro_rate, self.estimates.get(i - self.stride))
        self.estimates[i] = est
        return out, self.rd.last_cpu_seconds[0] + self.rd.last_cpu_seconds[1], self.rd.last_fft_pairs


def run_case(scene, motion, seed, netd, frames, score, memory, registration_px, interpolation,
             half_test=True):
    """{method: [(psnr, cpu s, fft pairs)]} over the scored frames."""
    rec = simulate(scene, motion, frames, seed, netd)
    c = rec.calibration
    cfg = DeblurConfig()
    singles = {m: Deconvolver(method=m) for m in ("kf", "wiener")}
    kw = dict(memory=memory, registration_px=registration_px, interpolation=interpolation,
              half_test=half_test)
    chains = {"temporal": Chain(c, "wiener", 1, **kw), "temporal t−2": Chain(c, "wiener", 2, **kw),
              "temporal_kf": Chain(c, "kf", 1, **kw)}
    res: dict[str, list] = {m: [] for m in METHODS}
    for i in range(frames):
        t = float(rec.t[i])
        kernel, _ = render(rec.gyro_t, rec.gyro_rate, c, t, cfg)
        frame = rec.frames[i]
        outs = {}
        for m, d in singles.items():
            t0 = time.thread_time()
            outs[m] = d.run_varying(frame, kernel) if hasattr(kernel, "kernels") else d.run(frame, kernel)
            pairs = float((len(d._betas) if m == "kf" else 0) + 1)
            outs[m] = (outs[m], time.thread_time() - t0, pairs)
        for m, ch in chains.items():
            outs[m] = ch(i, frame, kernel, t, rec.gyro_t, rec.gyro_rate)
        if i < frames - score:
            continue
        truth = rec.extras["truth/frames"][i]
        lo, hi = (float(v) for v in np.percentile(truth, (0.5, 99.5)))
        t8 = to8(truth, lo, hi)
        for m in METHODS:
            img, cpu, pairs = outs[m]
            res[m].append((peak_signal_noise_ratio(t8, to8(img, lo, hi), data_range=255), cpu, pairs))
    return res


def stage_profile(size, half_test, calls=25):
    """Median thread CPU ms per stage of one temporal solve (uniform 27 °/s pan kernel, rolling
    readout 15 ms, a smooth random scene) and of the Wiener solve on the same frame; the ratio is
    the median of the per-call ratios (a loaded host slows both alike)."""
    from thermod.physics import kernels
    from thermod.physics.calibration import Calibration
    from thermod.physics.deconv import recursive

    W, H = size
    calib = Calibration(width=W, height=H, cx=(W - 1) / 2, cy=(H - 1) / 2, readout_s=0.015)
    gyro_t = np.arange(0.0, 1.0, 1e-3)
    gyro_rate = np.tile(np.radians([10.0, 25.0, 0.0]), (len(gyro_t), 1))
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.normal(size=(H, W)).astype(np.float32), (0, 0), 3) * 50 + 3000
    img += rng.normal(size=(H, W)).astype(np.float32) * 0.5
    k = kernels.render_thermal_kernel(gyro_t, gyro_rate, calib, 0.5)
    rd = RecursiveDeconvolver(calib, half_test=half_test)
    _, prior = rd.solve(img, k, 0.48, gyro_t, gyro_rate, None)
    rows = []
    for i in range(calls + 3):
        t0 = time.thread_time()
        rd.single.run(img, k)
        t1 = time.thread_time()
        recursive.PROFILE.clear()
        rd.solve(img, k, 0.5, gyro_t, gyro_rate, prior)
        t2 = time.thread_time()
        if i >= 3:
            rows.append({"wiener": t1 - t0, "temporal": t2 - t1, "single solve": rd.last_cpu_seconds[0],
                         **recursive.PROFILE})
    med = {key: float(np.median([r[key] for r in rows])) * 1e3 for key in rows[0]}
    return med, float(np.median([r["temporal"] / r["wiener"] for r in rows]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one scene, 30 mK only")
    ap.add_argument("--frames", type=int, default=10, help="frames per stream (from the first)")
    ap.add_argument("--score", type=int, default=5, help="scored frames at the end of each stream")
    ap.add_argument("--memory", type=float, default=MEMORY)
    ap.add_argument("--registration-px", type=float, default=REGISTRATION_PX)
    ap.add_argument("--interpolation", choices=tuple(INTERPOLATIONS), default="cubic",
                    help="the warp's cv2 interpolation")
    ap.add_argument("--full-test", action="store_true",
                    help="the recursive solve's disagreement test at full size (default: on 2×2 means)")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    scenes = REPORT_SCENES[:1] if args.quick else REPORT_SCENES
    netds = (0.03,) if args.quick else NETDS
    say = lambda s: print(s, flush=True)  # noqa: E731
    t_start = time.perf_counter()
    log = mo.load_gyro_log()
    results: dict = {}
    for netd in netds:
        cases = [(f"{sp:g}", scenes[j], pan_motion(sp, 0.35 + 1.1 * j), 100 * i + j)
                 for i, sp in enumerate(SPEEDS) for j in range(len(scenes))]
        starts = LOG_STARTS[:1] if args.quick else LOG_STARTS
        cases += [(f"log@{s:g}s", scenes[j % len(scenes)],
                   mo.GyroLog(log.t_log, log.w_cam, s, spec=f"log:{s:g}"), 7 + j)
                  for j, s in enumerate(starts)]
        for level, scene, motion, seed in cases:
            res = run_case(scene, motion, seed, netd, args.frames, args.score, args.memory,
                           args.registration_px, INTERPOLATIONS[args.interpolation],
                           not args.full_test)
            acc = results.setdefault(netd, {}).setdefault(level, {m: [] for m in METHODS})
            for m in METHODS:
                acc[m].extend(res[m])
            say(f"  NETD {netd * 1000:.0f} mK {level} {scene}: " + ", ".join(
                f"{m} {np.mean([r[0] for r in res[m]]):.2f}" for m in METHODS))
    cmd = " ".join(["benchmarks/bench_temporal_daemon.py", *(argv if argv is not None else sys.argv[1:])])
    lines = ["# The daemon's temporal rungs", "",
             f"Generated by `{cmd}`: {len(scenes)} held-out scenes ({', '.join(scenes)}), streams of "
             f"{args.frames} frames restored from the first, the last {args.score} scored; recursive "
             f"memory γ = {args.memory:g}, registration δ = {args.registration_px:g} px, warp "
             f"{args.interpolation}, disagreement test "
             f"{'at full size' if args.full_test else 'on 2×2 means'}; "
             "640×480 at 50 Hz, "
             "paper gyro, the kernel grid the roll needs (adaptive). PSNR in dB (8-bit scale of the "
             "truth's 0.5–99.5 % range); `temporal t−2` takes its prior from two frames back (the "
             "2-worker case where t − 1 is still being solved).", ""]
    summary = []
    for netd, res in results.items():
        lines += [f"## NETD {netd * 1000:.0f} mK", "",
                  "| motion (°/s or log segment) | " + " | ".join(METHODS) + " | temporal − wiener "
                  "| temporal − kf |", "|---|" + "---|" * (len(METHODS) + 2)]
        for level, r in res.items():
            mean = {m: np.mean([x[0] for x in r[m]]) for m in METHODS}
            gw, gk = mean["temporal"] - mean["wiener"], mean["temporal"] - mean["kf"]
            lines.append(f"| {level} | " + " | ".join(f"{mean[m]:.2f}" for m in METHODS)
                         + f" | {gw:+.2f} | {gk:+.2f} |")
        allm = {m: np.mean([x[0] for r in res.values() for x in r[m]]) for m in METHODS}
        gw, gk = allm["temporal"] - allm["wiener"], allm["temporal"] - allm["kf"]
        lines.append("| **mean** | " + " | ".join(f"**{allm[m]:.2f}**" for m in METHODS)
                     + f" | **{gw:+.2f}** | **{gk:+.2f}** |")
        worst = min(np.mean([x[0] for x in r["temporal"]]) - np.mean([x[0] for x in r["wiener"]])
                    for r in res.values())
        lines += ["", f"Worst level's mean gain of temporal over wiener: {worst:+.2f} dB.", ""]
        summary.append((netd, allm["temporal"] - allm["wiener"], allm["temporal"] - allm["kf"]))
    lines += ["## Cost per frame", "", "| method | CPU ms (median) | FFT pairs (median) |", "|---|---|---|"]
    for m in METHODS:
        rows = [x for res in results.values() for r in res.values() for x in r[m]]
        lines.append(f"| {m} | {np.median([x[1] for x in rows]) * 1e3:.1f} "
                     f"| {np.median([x[2] for x in rows]):.1f} |")
    sizes = ((640, 480), (1280, 1024))
    profiles = {(sz, half): stage_profile(sz, half) for sz in sizes for half in (False, True)}
    cols = [(sz, half) for sz in sizes for half in (False, True)]
    lines += ["", "## CPU per stage of one temporal solve", "",
              "`stage_profile`: median thread CPU ms over 25 calls, one core (uniform pan kernel; the "
              "stages of `RecursiveDeconvolver._correct`, `recursive.PROFILE`); test: the disagreement "
              "test at full size or on 2×2 means.", "",
              "| stage | " + " | ".join(f"{w}×{h} test {'2×2' if half else 'full'}" for (w, h), half in cols)
              + " |", "|---|" + "---|" * len(cols)]
    for key in profiles[cols[0]][0]:
        lines.append(f"| {key} | " + " | ".join(f"{profiles[c][0].get(key, 0.0):.2f}" for c in cols) + " |")
    lines.append("| **temporal / wiener** | " + " | ".join(f"**{profiles[c][1]:.2f}**" for c in cols) + " |")
    netd_text = "/".join(f"{n * 1000:.0f}" for n, _, _ in summary)
    lines.insert(1, f"<!-- summary: daemon temporal rung over single-frame Wiener / K&F, NETD {netd_text} "
                    "mK | "
                    + ", ".join(f"{w:+.2f}/{k:+.2f}" for _, w, k in summary)
                    + " dB | > 0 dB over both -->")
    lines += ["", f"Run time {time.perf_counter() - t_start:.0f} s; load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} cores at the end (a shared machine: CPU times are loaded; compare ratios)."]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "temporal_daemon.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
