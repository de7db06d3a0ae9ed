"""No gyro: deblurring with the motion estimated from the pictures, against the true gyro and the
frame-times oracle.

    python -m benchmarks.bench_video_motion [--quick]

Each clip is a `thermod.sim.flight_video.simulate_flight`: a 640×512 camera (50° HFOV, τ 10 ms, 30
fps) turned by a stretch of the real Betaflight flight (shared/data/gyro/
betaflight_smooth_2khz.csv, `thermod.sim.motion.gyro_log`, forward-looking: body roll is the
camera's roll; "pitch" starts where the flight pitches at ~100 °/s RMS, "roll" where it rolls at
~110 °/s), its counts through a percentile AGC
(each frame its own gain and offset) to 8-bit H.264 (crf 18). The "+logo" clip has a static
white-on-black logo burnt into its top-left corner after the AGC (re-encoded, crf 18), as a camera
maker's overlay is (its box is left out of that clip's PSNR; the overlay the import finds is kept
out of the solve, `thermod.restore.overlay`, for every variant). The "+readout" clip is read row by row
over 20 ms (the camera file says so; its truth is each row's sharp view at its read time). Every
variant is the same recording (the video's frames, the true intrinsics, τ and readout, gyro axes =
camera axes) with another gyro:

- **true gyro**: the simulator's camera-frame rate at 1 kHz, noise-free;
- **oracle**: the true orientation known only at the frame times, a cubic spline of the cumulative
  rotation between them (`RotationTrack.gyro` with the true interval rotations and no lag);
- **video**: `thermod import VIDEO` without --gyro (`thermod.ingest.video_only.import_video`).

Each is deblurred by `thermod deblur --jobs 1` (in process; the default spatially varying grid,
temporal solve). PSNR is against the simulator's sharp truth put on the video's scale (each truth
frame through its frame's AGC gain and offset, clipped to 0–255), the deblurred frame clipped to
0–255, peak 255, an 8 px border left out, median over frames; "blurry" is the video's frame itself.
The rate error is the RMS per axis of (written − true) mean rate over the frame intervals moved back by
the track's lag; "truth shift" is the time shift of the truth (±10 ms, 1 ms steps) that fits the
written gyro best (0 when the blur's lag is modelled right).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from thermod.ingest.video_only import import_video
from thermod.io import video
from thermod.io.recording import OVERLAY_DATASET, Reader, Writer
from thermod.motion.track import RotationTrack
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim.flight_video import simulate_flight
from thermod.sync.gyro import cumulative_rotation

OUT = Path(__file__).resolve().parent / "results" / "video_motion.md"
BORDER = 8
TAU = 0.010
SIZE = (640, 512)
# name, start in the real log (s), logo, rolling readout (s)
CLIPS = (("pitch", 13.0, False, 0.0), ("roll", 24.0, False, 0.0), ("pitch+logo", 13.0, True, 0.0),
         ("pitch+readout", 13.0, False, 0.02))
LOGO_BOX = (12, 12, 150, 52)      # x0, y0, x1, y1 (px) of the burnt-in logo


def psnr(a: np.ndarray, b: np.ndarray, logo: bool = False) -> float:
    ok = np.zeros(a.shape, bool)
    ok[BORDER:-BORDER, BORDER:-BORDER] = True
    if logo:
        x0, y0, x1, y1 = LOGO_BOX
        ok[y0 - 2:y1 + 3, x0 - 2:x1 + 3] = False
    mse = float(np.mean((a[ok] - b[ok]) ** 2))
    return 10 * math.log10(255.0 ** 2 / max(mse, 1e-12))


def deblur(rec: Path, out: Path) -> np.ndarray:
    from thermod import cli

    with contextlib.redirect_stdout(io.StringIO()):
        rc = cli.main(["deblur", str(rec), "-o", str(out), "--jobs", "1"])
    if rc:
        raise SystemExit(f"thermod deblur {rec} failed ({rc})")
    with h5py.File(out) as f:
        return f["deblurred/frames"][()]


def burn_logo(path: Path) -> Path:
    """The video with a static logo (text and a frame) drawn into its top-left corner after the AGC."""
    import cv2

    vf = video.read_video(path)
    frames = vf.frames.copy()
    x0, y0, x1, y1 = LOGO_BOX
    for f in frames:
        cv2.rectangle(f, (x0, y0), (x1, y1), 0, -1)
        cv2.rectangle(f, (x0, y0), (x1, y1), 255, 2)
        cv2.putText(f, "THERMCO", (20, 44), cv2.FONT_HERSHEY_SIMPLEX, 0.9, 255, 2, cv2.LINE_AA)
    return video.write_video(path.with_name("logo.mp4"), frames, vf.t - vf.t[0] + vf.t[0], crf=18)


def write_variant(out: Path, frames, t, calib: Calibration, gt, gr, overlay=None) -> Path:
    w = Writer(out)
    w.reserve("camera/frames", len(t), (calib.height, calib.width), np.uint16)
    for f, ti in zip(frames, t, strict=True):
        w.append_frame(f.astype(np.uint16), float(ti))
    w.put("gyro/t", np.asarray(gt, np.float64))
    w.put("gyro/rate", np.asarray(gr, np.float32))
    if overlay is not None:            # the overlay the import found is the video's, whatever the gyro
        w.put(OVERLAY_DATASET, overlay.astype(np.uint8))
    w.set_attrs("import", {"video_bit_depth": 8})
    return w.commit(calib)


def case(tmp: Path, name: str, start_s: float, logo: bool, readout_s: float, seconds: float, size) -> dict:
    d = tmp / name.replace("+", "_")
    d.mkdir()
    t0 = time.perf_counter()
    sim = simulate_flight(d, seconds=seconds, log_seconds=seconds + 3.0, width=size[0], height=size[1],
                          fps=30.0, tau_s=TAU, formats=("gcsv",), seed=1, mount=0, video_start_s=1.0,
                          body=mo.gyro_log(None, start_s),
                          effects={"rolling_readout": readout_s} if readout_s else None)
    t_sim = time.perf_counter() - t0
    vpath = burn_logo(sim.video_path) if logo else sim.video_path
    vf = video.read_video(vpath)
    c = sim.recording.calibration
    cam = Calibration().replace(width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
                                frame_rate_hz=c.frame_rate_hz, tau_s=TAU, rate_hz=1000.0, readout_s=readout_s)
    # the truth on the video clock, camera frame
    tv = sim.body_t_log - sim.log_offset_s
    w_true = sim.body_rate @ sim.camera_from_body.T
    keep = (tv > vf.t[0] - 0.5) & (tv < vf.t[-1] + 0.5)
    tv, w_true = tv[keep], w_true[keep]
    G = cumulative_rotation(tv, w_true)
    Gf = np.stack([np.interp(vf.t, tv, G[:, a]) for a in range(3)], axis=1)
    oracle = RotationTrack(vf.t, np.diff(Gf, axis=0), np.zeros(len(vf.t) - 1),
                           np.full(len(vf.t) - 1, "ok"), 0.0, None, 1.0)
    og_t, og_w, _ = oracle.gyro(1000.0, lead_s=0.1, tail_s=0.1)
    t0 = time.perf_counter()
    imp = import_video(vpath, d / "video.h5", cam)
    t_import = time.perf_counter() - t0
    with Reader(imp.path) as r:
        overlay = r.overlay()
    recs = {"true": write_variant(d / "true.h5", vf.frames, vf.t, cam, tv, w_true, overlay),
            "oracle": write_variant(d / "oracle.h5", vf.frames, vf.t, cam, og_t, og_w, overlay),
            "video": imp.path}
    truth = sim.recording.extras.get("truth/frames_rolling", sim.recording.extras["truth/frames"])
    t8 = [np.clip((truth[k].astype(np.float64) - sim.agc_offset[k]) * sim.agc_gain[k], 0, 255)
          for k in range(len(vf.t))]
    row = {"clip": name, "frames": len(vf.t), "sim_s": t_sim, "import_s": t_import,
           "blurry": float(np.median([psnr(vf.frames[k].astype(np.float64), t8[k], logo)
                                      for k in range(len(t8))]))}
    for key, rec in recs.items():
        t0 = time.perf_counter()
        deb = deblur(rec, d / f"deb_{key}.h5")
        row[f"{key}_s"] = time.perf_counter() - t0
        row[key] = float(np.median([psnr(np.clip(deb[k], 0, 255), t8[k], logo) for k in range(len(t8))]))
    # the written gyro against the truth, as mean rates over the frame intervals moved back by the track's
    # lag (away from the held ends), and the time shift of the truth that fits it best (0: timed right)
    with h5py.File(imp.path) as f:
        gt, gr = f["gyro/t"][()], f["gyro/rate"][()].astype(np.float64)
    Gw = cumulative_rotation(gt, gr)
    win = vf.t[2:-2] - imp.track.lag_s

    def means(t, g, shift=0.0):
        Gi = np.stack([np.interp(win - shift, t, g[:, a]) for a in range(3)], axis=1)
        return np.diff(Gi, axis=0) / np.diff(win)[:, None]

    written, true = means(gt, Gw), means(tv, G)
    shifts = np.arange(-0.010, 0.0101, 0.001)
    errs = [float(np.sqrt(np.mean((written - means(tv, G, x)) ** 2))) for x in shifts]
    row.update(rate_rms_deg_s=math.degrees(float(np.sqrt(np.mean(true ** 2)))),
               err_deg_s=math.degrees(float(np.sqrt(np.mean((written - true) ** 2)))),
               lag_ms=imp.track.lag_s * 1e3, best_shift_ms=float(shifts[int(np.argmin(errs))]) * 1e3,
               overlay=float(imp.track.overlay.mean()) if imp.track.overlay is not None else 0.0,
               flagged=sum(len(v) for v in imp.track.flagged().values()))
    if os.environ.get("BENCH_PLOT_DIR"):
        from thermod.ingest.video_only import plot_track
        plot_track(imp.track, gt, gr, Path(os.environ["BENCH_PLOT_DIR"]) / f"{d.name}.png",
                   truth=(tv, w_true))
    return row


def main() -> None:
    from benchmarks.yardstick import yardstick_line

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one 1 s clip at 320×256 (not written to results)")
    ap.add_argument("--seconds", type=float, default=1.5, help="seconds per clip (default 1.5)")
    args = ap.parse_args()
    clips, size, seconds = CLIPS, SIZE, args.seconds
    if args.quick:
        clips, size, seconds = CLIPS[:1], (320, 256), 1.0
    rows = []
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for name, start, logo, readout in clips:
            rows.append(case(Path(tmp), name, start, logo, readout, seconds, size))
            r = rows[-1]
            print(f"{name}: blurry {r['blurry']:.2f}, true {r['true']:.2f}, oracle {r['oracle']:.2f}, "
                  f"video {r['video']:.2f} dB; seconds: sim {r['sim_s']:.0f}, import {r['import_s']:.0f}, "
                  f"deblur {r['true_s']:.0f}/{r['oracle_s']:.0f}/{r['video_s']:.0f}", flush=True)
    wall = time.perf_counter() - t_all
    head = ("| clip | frames | blurry (dB) | true gyro (dB) | oracle (dB) | video-estimated (dB) "
            "| video − true (dB) | video − blurry (dB) | true rate RMS (°/s per axis) "
            "| written gyro's rate error (°/s) | lag (ms) | truth shift that fits best (ms) | overlay found "
            "| flagged | import (s) |")
    lines = [head, "|" + "---|" * 15]
    for r in rows:
        lines.append(f"| {r['clip']} | {r['frames']} | {r['blurry']:.2f} | {r['true']:.2f} "
                     f"| {r['oracle']:.2f} | {r['video']:.2f} | {r['video'] - r['true']:+.2f} "
                     f"| {r['video'] - r['blurry']:+.2f} "
                     f"| {r['rate_rms_deg_s']:.1f} | {r['err_deg_s']:.2f} | {r['lag_ms']:.1f} "
                     f"| {r['best_shift_ms']:+.0f} | {r['overlay']:.1%} "
                     f"| {r['flagged']} | {r['import_s']:.1f} |")
    table = "\n".join(lines)
    print(table)
    if args.quick:
        return
    ys = yardstick_line()
    gap = max(r["true"] - r["video"] for r in rows)
    least = min(rows, key=lambda r: r["video"] - r["blurry"])
    gain, ceiling = least["video"] - least["blurry"], least["true"] - least["blurry"]
    text = [f"<!-- summary: no gyro, motion from the video, {len(rows)} clips {size[0]}×{size[1]} from the "
            f"real Betaflight flight: worst gap to the true gyro, least gain over blurry (the true gyro's "
            f"there) | {gap:.2f} dB, {gain:+.2f} dB ({ceiling:+.2f} dB) | ≤ 1.5 dB, ≥ +6 dB -->",
            "# Motion from the video: deblurring without a gyro", "",
            f"`python -m benchmarks.bench_video_motion` ({wall:.0f} s on this machine; {ys}). "
            f"{seconds:g} s clips, 640×512, 30 fps, τ 10 ms, "
            "per-frame AGC, 8-bit H.264; the clips, variants and scoring are in the script's docstring.", "",
            table, "",
            f"Targets (issue 32): within 1.5 dB of the true gyro (worst gap here {gap:.2f} dB) and ≥ +6 dB "
            f"over the blurry video (least gain here {gain:+.2f} dB, on {least['clip']}, where the true gyro "
            f"itself gains {ceiling:+.2f} dB).", "",
            "Reading the table: the flagged intervals are the fastest ones (beyond the tracker's reach, or a "
            "fit its neighbours contradict); their frames pass through, which the median PSNR hardly sees. "
            "A static logo is kept out of every variant's solve (the mask the import found): solved with "
            "the scene's kernel, a printed overlay rings into the scene around it. The truth shift says "
            "how far the assumed lag (τ, + ½ readout) is from the best one; the rolling-readout clip's rate "
            "error comes mostly from the banded fit's ends next to the flagged intervals (held beyond "
            "them).", ""]
    OUT.write_text("\n".join(text))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
