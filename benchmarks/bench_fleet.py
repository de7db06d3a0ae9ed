"""Fleets of recordings: `thermod deblur` throughput, local default vs a Dask LocalCluster of 1 and 2 workers.

    .venv/bin/python benchmarks/bench_fleet.py [--quick] [--n N] [--frames F] [--size W H] [--reps R]

One simulated recording (rolling camera, `--size`, `--frames`, NETD 30 mK) is copied to N files (the
work per file is what matters, not its content; simulating N would dominate the run). Each engine
deblurs all N with the default settings (K&F, kernel grid) through the real command line,
`thermod deblur … -o DIR/ [--scheduler ADDR]`, start-up included; the clusters are started once
(worker processes, 1 thread each) and stay warm between repetitions, as a standing fleet would.
Repetitions are interleaved (local, 1 worker, 2 workers, local, …); the table prints the median wall
time, recordings per hour and whether every output is byte-identical to the local run's.
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


def deblur(inputs: list[Path], out: Path, scheduler: str | None) -> float:
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "thermod.cli", "deblur", *map(str, inputs), "-o", f"{out}/"]
    cmd += ["--scheduler", scheduler] if scheduler else []
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr}")
    return wall


def identical(a: Path, b: Path, names: list[str]) -> bool:
    return all((a / n).read_bytes() == (b / n).read_bytes() for n in names)


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
        clusters = {k: LocalCluster(n_workers=k, threads_per_worker=1, processes=True,
                                    dashboard_address=":0", silence_logs=40) for k in (1, 2)}
        engines = {"local (default)": None, "LocalCluster, 1 worker": clusters[1].scheduler_address,
                   "LocalCluster, 2 workers": clusters[2].scheduler_address}
        walls: dict[str, list[float]] = {e: [] for e in engines}
        same: dict[str, bool] = {e: True for e in engines}
        load = []
        try:
            for rep in range(args.reps):
                for engine, address in engines.items():
                    out = tmp / f"out_{engine.split()[0]}_{address is None or address[-5:]}"
                    walls[engine].append(deblur(inputs, out, address))
                    load.append(os.getloadavg()[0])
                    if address is None:
                        local_out = tmp / "local_ref"
                        if rep == 0:
                            shutil.copytree(out, local_out)
                        same[engine] &= identical(out, local_out, names)
                    else:
                        same[engine] &= identical(out, tmp / "local_ref", names)
                    print(f"  rep {rep + 1} {engine}: {walls[engine][-1]:.1f} s", flush=True)
        finally:
            for c in clusters.values():
                c.close()
    frames = args.n * args.frames
    print(f"\n{args.n} recordings × {args.frames} frames, {args.size[0]}×{args.size[1]}, K&F grid; "
          f"median of {args.reps} interleaved run(s); {os.cpu_count()} CPUs; "
          f"load average during runs {min(load):.1f}–{max(load):.1f}\n")
    print("| engine | wall (s) | recordings/hour | ms/frame (wall) | bytes = local run |")
    print("|---|---:|---:|---:|---|")
    for engine in engines:
        wall = statistics.median(walls[engine])
        print(f"| {engine} | {wall:.1f} | {3600 * args.n / wall:.0f} | {1e3 * wall / frames:.0f} | "
              f"{'yes' if same[engine] else 'NO'} |")
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
