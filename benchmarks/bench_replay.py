"""The daemon against `thermod deblur` on the same recordings: six simulated flights with truth, each
replayed in real time through the default daemon and deblurred offline, both scored against the truth.

    .venv/bin/python -m benchmarks.bench_replay [--seconds 6] [--cases N] [--size 640x480]
    .venv/bin/python -m benchmarks.bench_replay --like-yardstick 326   # a machine of that yardstick
    .venv/bin/python -m benchmarks.bench_replay --rung-in-order     # the ceiling at 100 % temporal
    .venv/bin/python -m benchmarks.bench_replay --rung-columns 2    # where across the frame it loses

Each recording (`thermod.sim.synth`, `make run`'s camera: 640×480 at 50 fps, τ 8 ms, NETD 50 mK, a
paper-grade gyro) is a scene under a motion the tests do not use; they are cached in
$TMPDIR/thermod_replay. The daemon is `config/sim.toml`'s but for its sources (``replay`` at speed 1,
no loop): the same deblur, pipeline, governor and monitor. It is fed by its replay drivers and
observed from a subscriber in this process; `thermod deblur` runs with its defaults. PSNR: the whole
frame on the truth's 8-bit 0.5–99.5 % scale, the median over the frames after the first `--skip`
seconds (the daemon's warm-up) that both deblurred. Prints, per recording, the daemon's and the
offline PSNR, the blurry frames', the gap (and its mean over the frames: a stream that mixes methods
has a median between them), the daemon's share deblurred and temporal and its latency p95 and p99
(published − frame time), and the machine's yardstick. Target (issue 35): the daemon within 0.3 dB of
`thermod deblur`, ≥ 80 % temporal, ≥ 99.5 % deblurred, p95 ≤ 45 and p99 ≤ 60 ms on 2 cores.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
THERMOD = Path(sys.executable).with_name("thermod")
# (scene, motion): held-out pairs, none the daemon tests or the payload use together
CASES = (("real:2", "multirotor:40"), ("real:3", "shake:3"), ("texture", "pan:80"),
         ("real:4", "vibration:15:45"), ("real:5", "multirotor:80"), ("texture", "sway"))


def calibration(size):
    from thermod.physics.calibration import Calibration

    w, h = size
    f = (w / 640) / math.radians(0.0391)      # the paper's SBTI field of view (config/sim.toml) at any size
    return Calibration(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2, tau_s=0.008,
                       frame_rate_hz=50.0)


def recording_for(case: int, seconds: float, size, directory: Path) -> Path:
    """The case's recording (simulated once, then cached; `recording.write` is atomic)."""
    from thermod.io import recording
    from thermod.sim import synth
    from thermod.sim.gyro_model import GyroErrorModel

    scene, motion = CASES[case]
    path = directory / f"case{case}-{size[0]}x{size[1]}-{seconds:g}s.h5"
    if not path.exists():
        rec = synth.simulate(scene, motion, seconds, calibration(size), effects={"netd": 0.05},
                             seed=20 + case, gyro=GyroErrorModel.paper())
        recording.write(path, rec)
    return path


def replay_toml(rec: Path, endpoint: str, out: Path) -> Path:
    """config/sim.toml with replayed sources: its [calibration] goes (the recording's is used) and
    so does [sim] (no simulated payload)."""
    import tomllib

    raw = tomllib.loads((REPO / "config" / "sim.toml").read_text())
    keep = ("deblur", "pipeline", "monitor")
    lines = [f'[sources.gyro]\nkind = "replay"\npath = "{rec}"\nloop = false\nspeed = 1.0\n',
             f'[sources.camera]\nkind = "replay"\npath = "{rec}"\nloop = false\nspeed = 1.0\n',
             f'[publish]\nendpoint = "{endpoint}"\n']
    for name in keep:
        lines.append(f"[{name}]")
        for k, v in raw[name].items():
            lines.append(f"{k} = {_toml(v)}")
    out.write_text("\n".join(lines) + "\n")
    return out


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(v)


def on_truth_scale(est, truth) -> tuple[np.ndarray, np.ndarray]:
    """(truth, est) on the truth's 8-bit 0.5–99.5 % scale."""
    from benchmarks.bench_quality import to8

    lo, hi = (float(v) for v in np.percentile(truth, (0.5, 99.5)))
    return to8(truth, lo, hi), to8(est, lo, hi)


def psnr(est, truth) -> float:
    """PSNR (dB) on the truth's 8-bit 0.5–99.5 % scale, as bench_temporal_daemon scores."""
    from skimage.metrics import peak_signal_noise_ratio

    return float(peak_signal_noise_ratio(*on_truth_scale(est, truth), data_range=255))


def live(rec_path: Path, truth: np.ndarray, n_frames: int, work: Path, scale: float = 1.0,
         sets: tuple[str, ...] = ()) -> dict:
    """Replay through `thermod run` (with `sets` overrides); per frame (index in the recording):
    deblurred, method, latency (ms ÷ `scale`, the recording's clock slowdown), PSNR. The frames are
    scored after the run: scoring them as they arrive took CPU from the daemon."""
    from thermod.client.subscriber import Subscriber

    ep = f"ipc://{work}/pub.sock"
    toml = replay_toml(rec_path, ep, work / "replay.toml")
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    cmd = [str(THERMOD), "run", "-c", str(toml)]
    for kv in sets:
        cmd += ["--set", kv]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env=env, text=True)
    got: dict[int, tuple] = {}
    try:
        with Subscriber(ep, topics=("frame",), rcvhwm=100000) as sub:
            deadline = time.monotonic() + 240 + scale * n_frames / 50.0
            while time.monotonic() < deadline and proc.poll() is None:
                m = sub.recv(timeout=0.5)
                if m is None:
                    if got and len(got) >= n_frames:
                        break
                    continue
                _, h, img = m
                k = int(h["frame_id"])         # a replay numbers its frames by their index in the recording
                ms = 1e3 * (h["published"] - h["t"]) / scale
                got[k] = (bool(h["deblurred"]), h.get("method"), ms, img)
                if len(got) >= n_frames:
                    break
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    return {k: (d, m, ms, psnr(img, truth[k]) if 0 <= k < len(truth) else math.nan)
            for k, (d, m, ms, img) in got.items()}


def deblur_offline(rec_path: Path, work: Path):
    """`thermod deblur` with its defaults: (the restored frames, which were deblurred, wall seconds)."""
    import h5py

    from thermod.io import recording

    out = work / "offline.h5"
    t0 = time.perf_counter()
    subprocess.run([str(THERMOD), "deblur", str(rec_path), "-o", str(out)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wall = time.perf_counter() - t0
    with h5py.File(out) as f:
        ok = f["deblurred/deblurred"][()].astype(bool).tolist()
    return recording.read(out).deblurred, ok, wall


def offline(rec_path: Path, truth: np.ndarray, work: Path) -> tuple[list[float], list[bool], float]:
    restored, ok, wall = deblur_offline(rec_path, work)
    return [psnr(restored[k], truth[k]) for k in range(len(truth))], ok, wall


def rung_in_order(rec, truth: np.ndarray, stride: int, keep=None) -> list[float]:
    """PSNR per frame of the daemon's temporal rung at 100 %: `config/sim.toml`'s deblur, its adaptive
    kernel grid, the recursive solve over its Wiener solver with the prior from frame t − `stride`
    (2: two workers, each frame's predecessor still being solved), in read order. `keep(i, image)`
    sees each restored frame."""
    from thermod.physics.deconv.recursive import RecursiveDeconvolver
    from thermod.restore.plan import make_deconvolver, render
    from thermod.runtime.config import load
    from thermod.runtime.governor import ladder

    deblur = load(REPO / "config" / "sim.toml").deblur
    rung = ladder(deblur)[0]
    if not rung.temporal:
        raise SystemExit("--rung-in-order: config/sim.toml's ladder has no temporal rung")
    c = rec.calibration
    rd = RecursiveDeconvolver(c, make_deconvolver(rung.deblur(deblur), live=False),
                              min_coverage=deblur.min_coverage)
    estimates, out = {}, []
    for i in range(len(truth)):
        t = float(rec.t[i])
        kernel, _ = render(rec.gyro_t, rec.gyro_rate, c, t, deblur)
        frame = np.asarray(rec.frames[i], np.float32)
        prior = estimates.pop(i - stride, None)
        img, estimates[i] = rd.solve(frame, kernel, t, rec.gyro_t, rec.gyro_rate, prior)
        out.append(psnr(img, truth[i]))
        if keep is not None:
            keep(i, img)
    return out


def squared_errors(est, truth) -> np.ndarray:
    """Per-pixel squared error on `psnr`'s 8-bit scale."""
    t8, e8 = on_truth_scale(est, truth)
    return (e8.astype(np.float64) - t8.astype(np.float64)) ** 2


def by_columns(case: int, seconds: float, size, skip_s: float, cache: Path, bands: int = 10) -> list[tuple]:
    """[(first column, last column, rung MSE, offline MSE)]: the rung (prior t − 1) and `thermod deblur`
    on every 5th frame after `skip_s`, their squared errors averaged per band of columns."""
    from thermod.io import recording

    path = recording_for(case, seconds, size, cache)
    rec = recording.read(path)
    truth = np.asarray(rec.extras["truth/frames"], np.float32)
    with tempfile.TemporaryDirectory(prefix="thermod-replay-") as d:
        off, _, _ = deblur_offline(path, Path(d))
    first = int(round(skip_s * rec.calibration.frame_rate_hz))
    rung, offline_ = [], []

    def keep(i, img):
        if i >= first and i % 5 == 0:
            rung.append(squared_errors(img, truth[i]).mean(0))
            offline_.append(squared_errors(off[i], truth[i]).mean(0))

    rung_in_order(rec, truth, 1, keep)
    r, o = np.mean(rung, axis=0), np.mean(offline_, axis=0)
    edges = np.linspace(0, size[0], bands + 1).astype(int)
    return [(a, b, float(r[a:b].mean()), float(o[a:b].mean()))
            for a, b in zip(edges[:-1], edges[1:], strict=True)]


def run_in_order(case: int, seconds: float, size, skip_s: float, cache: Path) -> dict:
    """The daemon's temporal rung in read order (t − 1 and t − 2 priors) and `thermod deblur`."""
    from thermod.io import recording

    path = recording_for(case, seconds, size, cache)
    rec = recording.read(path)
    truth = np.asarray(rec.extras["truth/frames"], np.float32)
    with tempfile.TemporaryDirectory(prefix="thermod-replay-") as d:
        off, off_ok, _ = offline(path, truth, Path(d))
    first = int(round(skip_s * rec.calibration.frame_rate_hz))
    scored = [k for k in range(first, len(truth)) if off_ok[k]]
    row = {"case": f"{CASES[case][0]} / {CASES[case][1]}",
           "offline": float(np.median([off[k] for k in scored]))}
    for stride in (1, 2):
        got = rung_in_order(rec, truth, stride)
        row[f"t-{stride}"] = float(np.median([got[k] for k in scored]))
    return row


def run_case(case: int, seconds: float, size, skip_s: float, cache: Path, scale: float = 1.0,
             sets: tuple[str, ...] = ()) -> dict:
    """The daemon live (on the recording's clock slowed `scale` times, with `sets`) and `thermod deblur`
    (on the recording as made) on one recording."""
    from thermod.io import recording

    path = recording_for(case, seconds, size, cache)
    rec = recording.read(path)
    truth = np.asarray(rec.extras["truth/frames"], np.float32)
    blurry = [psnr(rec.frames[k].astype(np.float32), truth[k]) for k in range(len(truth))]
    with tempfile.TemporaryDirectory(prefix="thermod-replay-") as d:
        work = Path(d)
        live_path = path
        if scale != 1.0:     # the emulated machine's world: the recording's clock slowed `scale` times
            from benchmarks.emulation import stretched

            live_path = work / "slowed.h5"
            recording.write(live_path, stretched(rec, scale))
        lv = live(live_path, truth, len(truth), work, scale, sets)
        off, off_ok, off_wall = offline(path, truth, work)
    first = int(round(skip_s * rec.calibration.frame_rate_hz))
    both = [k for k in range(first, len(truth)) if k in lv and lv[k][0] and off_ok[k]]
    lat = [v[2] for k, v in lv.items() if k >= first]
    methods = [str(v[1]) for k, v in lv.items() if k >= first]
    return {"case": f"{CASES[case][0]} / {CASES[case][1]}", "frames": len(truth), "published": len(lv),
            "deblurred_pct": 100.0 * sum(v[0] for k, v in lv.items() if k >= first) / max(1, len(methods)),
            "temporal_pct": 100.0 * sum(m.startswith("temporal") for m in methods) / max(1, len(methods)),
            "p95_ms": float(np.percentile(lat, 95)) if lat else math.nan,
            "p99_ms": float(np.percentile(lat, 99)) if lat else math.nan,
            "live": float(np.median([lv[k][3] for k in both])) if both else math.nan,
            "offline": float(np.median([off[k] for k in both])) if both else math.nan,
            "blurry": float(np.median([blurry[k] for k in both])) if both else math.nan,
            "gap_mean": float(np.mean([lv[k][3] - off[k] for k in both])) if both else math.nan,
            "scored": len(both), "offline_s_per_frame": off_wall / len(truth)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="length of each recording")
    ap.add_argument("--skip", type=float, default=2.0, help="seconds of warm-up left out of the scores")
    ap.add_argument("--cases", type=int, default=len(CASES))
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--rung-columns", type=int, default=None, metavar="CASE",
                    help="no daemon: the rung in read order (prior t − 1) and `thermod deblur` on recording "
                         "CASE (0–5), their squared error per band of columns")
    ap.add_argument("--rung-in-order", action="store_true",
                    help="no daemon: its temporal rung run offline in read order (what it publishes at "
                         "100 %% temporal) against `thermod deblur`")
    ap.add_argument("--like-yardstick", type=float, default=None, metavar="MS",
                    help="emulate a machine whose yardstick reads MS ms/frame (benchmarks/emulation.py): "
                         "each recording replayed on a clock slowed by this machine's yardstick / MS, the "
                         "latencies reported on that machine's time scale")
    args = ap.parse_args(argv)
    if args.like_yardstick is not None and not args.like_yardstick > 0:
        ap.error(f"--like-yardstick: expected a yardstick in ms/frame > 0, got {args.like_yardstick:g}")
    size = tuple(int(v) for v in args.size.lower().replace("×", "x").split("x"))
    cache = Path(os.environ.get("TMPDIR", "/tmp")) / "thermod_replay"
    cache.mkdir(parents=True, exist_ok=True)
    from benchmarks.yardstick import jitter_line, yardstick_line, yardstick_ms

    here = yardstick_ms()
    print(yardstick_line(ms=here), "(before the runs)", flush=True)
    print(jitter_line(), flush=True)
    scale, sets = 1.0, ()
    if args.like_yardstick is not None and not (args.rung_in_order or args.rung_columns is not None):
        from benchmarks.emulation import daemon_sets

        scale = here / args.like_yardstick
        sets = tuple(daemon_sets(scale))
        print(f"emulating a machine at {args.like_yardstick:g} ms: recordings replayed {scale:.2f}× slower, "
              f"latencies ÷ {scale:.2f}", flush=True)
    if args.rung_columns is not None:
        if not 0 <= args.rung_columns < len(CASES):
            ap.error(f"--rung-columns: expected a recording 0–{len(CASES) - 1}, got {args.rung_columns}")
        print(f"{' / '.join(CASES[args.rung_columns])}, every 5th frame after {args.skip:g} s")
        print("| columns | rung MSE | `thermod deblur` MSE | rung − offline dB |")
        print("|---|---|---|---|")
        for a, b, r, o in by_columns(args.rung_columns, args.seconds, size, args.skip, cache):
            print(f"| {a}–{b} | {r:.2f} | {o:.2f} | {10 * np.log10(o / r):+.2f} |")
        return 0
    if args.rung_in_order:
        return print_in_order(args, size, cache)
    rows = []
    print("| recording (scene / motion) | daemon dB | `thermod deblur` dB | daemon − offline | blurry dB "
          "| its mean over frames | deblurred % | temporal % | p95 ms | p99 ms | frames scored |")
    print("|---|---|---|---|---|---|---|---|---|---|---|", flush=True)
    for case in range(min(args.cases, len(CASES))):
        r = run_case(case, args.seconds, size, args.skip, cache, scale, sets)
        rows.append(r)
        print(f"| {r['case']} | {r['live']:.2f} | {r['offline']:.2f} | {r['live'] - r['offline']:+.2f} | "
              f"{r['blurry']:.2f} | {r['gap_mean']:+.2f} | {r['deblurred_pct']:.1f} | "
              f"{r['temporal_pct']:.1f} | {r['p95_ms']:.1f} | {r['p99_ms']:.1f} | {r['scored']} |",
              flush=True)
    gaps = [r["live"] - r["offline"] for r in rows]
    per_frame = np.median([r["offline_s_per_frame"] for r in rows])
    print(f"\nmean daemon − offline {np.mean(gaps):+.2f} dB (worst {min(gaps):+.2f}; frame by frame "
          f"{np.mean([r['gap_mean'] for r in rows]):+.2f}); load average "
          f"{os.getloadavg()[0]:.1f} after the runs; offline {per_frame:.2f} s a frame (wall)")
    return 0


def print_in_order(args, size, cache: Path) -> int:
    print("| recording (scene / motion) | temporal rung, prior t − 1 | prior t − 2 | `thermod deblur` "
          "| t − 1 − offline | t − 2 − offline |")
    print("|---|---|---|---|---|---|", flush=True)
    gaps = []
    for case in range(min(args.cases, len(CASES))):
        r = run_in_order(case, args.seconds, size, args.skip, cache)
        gaps.append(r["t-2"] - r["offline"])
        print(f"| {r['case']} | {r['t-1']:.2f} | {r['t-2']:.2f} | {r['offline']:.2f} | "
              f"{r['t-1'] - r['offline']:+.2f} | {r['t-2'] - r['offline']:+.2f} |", flush=True)
    print(f"\nmean t − 2 − offline {np.mean(gaps):+.2f} dB (worst {min(gaps):+.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
