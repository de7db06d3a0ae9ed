"""Fleets of recordings: `thermod deblur` throughput, local (one process; the default process pool) vs a
Dask LocalCluster of 1 and 2 workers.

    .venv/bin/python benchmarks/bench_fleet.py [--quick] [--n N] [--frames F] [--size W H] [--reps R]

One simulated recording (rolling camera, `--size`, `--frames`, NETD 30 mK) is copied to N files (the
work per file is what matters, not its content; simulating N would dominate the run). Each engine
deblurs all N with the default settings (K&F, kernel grid) through the real command line,
`thermod deblur … -o DIR/ [--jobs 1 | --scheduler ADDR]`, start-up included (the local pool's
processes start anew with every command); the clusters are started once
(worker processes, 1 thread each) and stay warm between repetitions, as a standing fleet would.
All share one FFTW wisdom file, planned by an untimed local warm-up. Repetitions are interleaved
(one process, pool, 1 worker, 2 workers, one process, …); the table prints the median wall time,
recordings per hour and whether every output is byte-identical to the one-process run's.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

from thermod.io import recording  # noqa: E402
from thermod.physics.calibration import Calibration  # noqa: E402
from thermod.sim import synth  # noqa: E402


def make_fleet(d: Path, n: int, frames: int, size: tuple[int, int]) -> list[Path]:
    w, h = size
    calib = Calibration(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2)
    rec = synth.simulate("texture", "roll:60", seconds=frames / calib.frame_rate_hz, calib=calib, seed=1,
                         truth=False, effects={"netd": 0.03})
    first = d / "rec0.h5"
    recording.write(first, rec)
    paths = [first]
    for i in range(1, n):
        paths.append(d / f"rec{i}.h5")
        shutil.copyfile(first, paths[-1])
    return paths


def deblur(inputs: list[Path], out: Path, engine: list[str]) -> float:
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "thermod.cli", "deblur", *map(str, inputs), "-o", f"{out}/", *engine]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr}")
    return wall


def compare(a: Path, b: Path, names: list[str]) -> str:
    """"yes" when every file's bytes match; else whether the datasets' values differ or only the layout."""
    import h5py
    import numpy as np

    worst = ""
    for n in names:
        if (a / n).read_bytes() == (b / n).read_bytes():
            continue
        with h5py.File(a / n) as fa, h5py.File(b / n) as fb:
            for key in ("deblurred/frames", "camera/frames", "deblurred/lambda"):
                x, y = fa[key][()], fb[key][()]
                if x.tobytes() != y.tobytes():
                    d = np.abs(x.astype(np.float64) - y.astype(np.float64))
                    return f"NO: {n} {key} differs (max {np.nanmax(d):.3g}, {int((d > 0).sum())} values)"
        worst = f"NO: {n} same values, other layout"
    return worst or "yes"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3 recordings of 10 frames at 160×120, 1 repetition")
    ap.add_argument("--n", type=int, default=4, help="recordings (default 4)")
    ap.add_argument("--frames", type=int, default=25, help="frames per recording (default 25)")
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    ap.add_argument("--reps", type=int, default=2, help="interleaved repetitions (default 2)")
    args = ap.parse_args()
    if args.quick:
        args.n, args.frames, args.size, args.reps = 3, 10, (160, 120), 1
    from distributed import LocalCluster

    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        inputs = make_fleet(tmp, args.n, args.frames, tuple(args.size))
        print(f"simulated {args.n} × {args.frames} frames at {args.size[0]}×{args.size[1]} "
              f"in {time.perf_counter() - t0:.0f} s", flush=True)
        names = [p.name for p in inputs]
        # One FFTW wisdom file for this run, planned by an untimed local warm-up: the clusters' workers
        # inherit the variable and load it, so every engine runs the same FFT plans. (The default
        # ~/.cache/thermod is rewritten by any thermod process on the machine; a plan measured anew
        # under load can differ, and so do the last bits of the result.)
        os.environ["THERMOD_CACHE_DIR"] = str(tmp / "cache")
        deblur(inputs[:1], tmp / "warmup", ["--jobs", "1"])
        clusters = {k: LocalCluster(n_workers=k, threads_per_worker=1, processes=True,
                                    dashboard_address=":0", silence_logs=40) for k in (1, 2)}
        engines = {"local, this process (--jobs 1)": ["--jobs", "1"],
                   "local processes (default: one per core)": [],
                   "LocalCluster, 1 worker": ["--scheduler", clusters[1].scheduler_address],
                   "LocalCluster, 2 workers": ["--scheduler", clusters[2].scheduler_address]}
        walls: dict[str, list[float]] = {e: [] for e in engines}
        same: dict[str, str] = {e: "yes" for e in engines}
        load = []
        try:
            for rep in range(args.reps):
                for k, (engine, argv) in enumerate(engines.items()):
                    out = tmp / f"out_{k}"
                    walls[engine].append(deblur(inputs, out, argv))
                    load.append(os.getloadavg()[0])
                    if k == 0 and rep == 0:         # the reference: one process, files in turn
                        shutil.copytree(out, tmp / "local_ref")
                    verdict = compare(out, tmp / "local_ref", names)
                    if verdict != "yes":
                        same[engine] = verdict
                    print(f"  rep {rep + 1} {engine}: {walls[engine][-1]:.1f} s", flush=True)
        finally:
            for c in clusters.values():
                c.close()
    frames = args.n * args.frames
    print(f"\n{args.n} recordings × {args.frames} frames, {args.size[0]}×{args.size[1]}, K&F grid; "
          f"median of {args.reps} interleaved run(s); {os.cpu_count()} CPUs; "
          f"load average during runs {min(load):.1f}–{max(load):.1f}\n")
    print("| engine | wall (s) | recordings/hour | ms/frame (wall) | bytes = one-process run |")
    print("|---|---:|---:|---:|---|")
    for engine in engines:
        wall = statistics.median(walls[engine])
        print(f"| {engine} | {wall:.1f} | {3600 * args.n / wall:.0f} | {1e3 * wall / frames:.0f} | "
              f"{same[engine]} |")
    return 0 if all(v == "yes" for v in same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
