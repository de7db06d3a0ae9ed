"""Reading and writing flights from other tools: seconds per minute of video or log.

    python benchmarks/bench_flight_io.py [--quick]

Video: a seeded moving texture (a smooth random field panned 2 px per frame), 30 fps, written as 8-bit
H.264 (crf 18, `thermod.io.video.write_video`) and read back (`read_video`: decode + luma plane).
Logs: the real Betaflight blackbox and PX4 ULog of tests/data/flightlogs, and 2 kHz gcsv, Betaflight
CSV and 1 kHz ArduPilot .bin written by `thermod.io.flightlog`, read with `read_flight_log`. Each
time is the best of `--repeat` runs, scaled to one minute of video or log.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from thermod.io import flightlog, video

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "flightlogs"


def texture_video(width: int, height: int, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.normal(0, 1, (height, width + 2 * n)).astype(np.float32), (0, 0), 3)
    big = (big - big.min()) / np.ptp(big) * 255
    return np.stack([big[:, 2 * k:2 * k + width] for k in range(n)]).astype(np.uint8)


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter inputs, one repeat")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    repeat = 1 if args.quick else args.repeat
    seconds = 4.0 if args.quick else 10.0
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for w, h in ((160, 120), (640, 512)):
            n = int(seconds * 30)
            frames = texture_video(w, h, n)
            t = np.arange(n) / 30.0
            path = d / f"v{w}.mp4"
            tw = best(lambda p=path, f=frames, t=t: video.write_video(p, f, t), repeat)
            tr = best(lambda p=path: video.read_video(p), repeat)
            mb = path.stat().st_size / 1e6 * 60 / seconds
            rows.append((f"video {w}×{h} 30 fps H.264", "write_video", f"{tw * 60 / seconds:.2f}",
                         f"{mb:.1f} MB/min"))
            rows.append((f"video {w}×{h} 30 fps H.264", "read_video", f"{tr * 60 / seconds:.2f}", ""))
        rng = np.random.default_rng(1)
        span = 30.0 if args.quick else 60.0
        for name, hz, writer in (("gcsv", 2000, flightlog.write_gcsv),
                                 ("betaflight-csv", 2000, flightlog.write_betaflight_csv),
                                 ("ardupilot .bin", 1000, flightlog.write_ardupilot_bin)):
            tl = 10.0 + np.arange(int(span * hz)) / hz
            path = writer(d / f"log_{name.split()[0]}", tl, rng.normal(0, 1, (len(tl), 3)))
            tr = best(lambda p=path: flightlog.read_flight_log(p), repeat)
            rows.append((f"{name} {hz} Hz (written)", "read_flight_log", f"{tr * 60 / span:.2f}",
                         f"{path.stat().st_size / 1e6 * 60 / span:.1f} MB/min"))
        for path in (DATA / "betaflight_btfl_001.bbl", DATA / "px4_sample_appended_multiple.ulg"):
            log = flightlog.read_flight_log(path)
            tr = best(lambda p=path: flightlog.read_flight_log(p), repeat)
            rows.append((f"{log.source_format} {log.rate_hz:.0f} Hz (real, {log.duration_s:.0f} s)",
                         "read_flight_log", f"{tr * 60 / log.duration_s:.2f}", ""))
    print("| input | call | s per minute | size |")
    print("|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
