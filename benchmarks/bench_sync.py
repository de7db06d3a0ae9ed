"""Sync of a video to a gyro log from the pictures alone (`thermod.sync`): offset error, mount
found and time per minute of video, over seeds and motions.

    python benchmarks/bench_sync.py [--quick] [--figure benchmarks/results/sync.png]
    python benchmarks/bench_sync.py --discrepancy

Flights (thermod.sim.sync_flights): the simulator's fine-time renderer, 50 Hz, τ = 8 ms, NETD 50 mK, a
50° field of view, each frame through an 8-bit AGC (jittered gain and level); the video starts at a
random point of a longer log (the real Betaflight log, 39 s, when ../shared/data is there, and a
procedural flight of 40 s), the gyro on a random one of the 24 axis-aligned mounts plus a
(0.57°, −0.46°, 0.69°) misalignment, a (0.01, −0.006, 0.004) rad/s bias and 0.5 °/s white noise.
The sync is told τ = 8 ms and readout 0 (a user's nominal values); "hidden" lists the true values
where they differ, and a clock drift of the log against the video (the two agreeing mid-video).
Offset error = found − true; σ = the jackknife standard error; the systematic bound from the
picture's lag is τ/2 = 4 ms. Readout and drift: fitted ± jackknife σ. Time: the whole `synchronise`
call (picture motion, whole-log correlation, fine fits) on one core of a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from thermod import sync as S  # noqa: E402
from thermod.physics.geometry import so3_log  # noqa: E402
from thermod.sim import sync_flights as sf  # noqa: E402


def cases(quick: bool):
    """(motion, seed, seconds, width, hidden effects); the mount is drawn per seed."""
    motions = (["real"] if sf.real_log() is not None else []) + ["procedural"]
    seeds = range(2) if quick else range(5)
    for m in motions:
        for s in seeds:
            yield m, s, 3.0, sf.WIDTH, {}
    if quick:
        return
    for m in motions:
        yield m, 5, 3.0, sf.WIDTH, {"rolling_readout": 0.010}
        yield m, 6, 3.0, sf.WIDTH, {"rolling_readout": 0.016, "time_constant": 0.011}
        yield m, 7, 6.0, sf.WIDTH, {"drift_ppm": 1000.0 if m == "procedural" else -500.0}
        yield m, 10, 10.0, sf.WIDTH, {}
        yield m, 11, 3.0, 320, {}


def _effects(fx: dict) -> str:
    names = {"rolling_readout": "readout", "time_constant": "τ"}
    return ", ".join(f"drift {v:g} ppm" if k == "drift_ppm" else f"{names[k]} {1e3 * v:g} ms"
                     for k, v in fx.items()) or "–"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two seeds per motion, 3 s at 160×120 only")
    ap.add_argument("--figure", metavar="PNG", help="also write the first flight's before/after figure")
    ap.add_argument("--discrepancy", action="store_true",
                    help="instead: the discrepancy workflow's fine stage on one flight (minutes)")
    args = ap.parse_args()
    if args.discrepancy:
        discrepancy_stage()
        return
    print("| motion | seed | video | size | hidden | mount true → found | cost ratio | NCC | "
          "offset error ms | σ ms | readout ms | drift ppm | misalignment error ° | bias error mrad/s | "
          "s per min of video |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    errs = []
    for motion, seed, seconds, width, fx in cases(args.quick):
        sim_fx = {k: v for k, v in fx.items() if k != "drift_ppm"}
        fl = sf.make_flight(seed, seconds, motion=motion, width=width, effects=sim_fx,
                            drift_ppm=fx.get("drift_ppm", 0.0))
        size = f"{width}×{width * 3 // 4}"
        t0 = time.perf_counter()
        try:
            r = S.synchronise(fl.frames, fl.frame_t, fl.gyro_t, fl.gyro_rate, fl.intrinsics, tau_s=fl.tau_s)
        except (S.SyncError, S.TooLittleMotion) as e:
            print(f"| {fl.motion} | {seed} | {seconds:g} s | {size} | {_effects(fx)} | refused: {e} |")
            continue
        dt = time.perf_counter() - t0
        if args.figure and not errs:
            S.plot_sync(r, fl.gyro_t, fl.gyro_rate, args.figure)
        err = (r.time_offset_s - fl.true_offset_s) * 1e3
        errs.append(err)
        ang = math.degrees(float(np.linalg.norm(so3_log(fl.true_R.T @ r.R_cam_gyro))))
        berr = 1e3 * float(np.max(np.abs(r.fine.bias_rad_s - fl.bias_rad_s)))
        ok = "✓" if r.mount_index == fl.mount_index else "✗"
        ratio = f"{r.mount_cost_ratio:.1f}" if math.isfinite(r.mount_cost_ratio) else "only one"
        print(f"| {fl.motion} | {seed} | {seconds:g} s | {size} | {_effects(fx)} | {fl.mount_index} → "
              f"{r.mount_index} {ok} | {ratio} | {r.coarse.ncc:.4f} | {err:+.2f} | "
              f"{1e3 * r.fine.time_offset_sigma_s:.2f} | {1e3 * r.fine.readout_s:.2f} ± "
              f"{1e3 * r.fine.readout_sigma_s:.2f} | {r.fine.clock_drift_ppm:.0f} ± "
              f"{r.fine.clock_drift_sigma_ppm:.0f} | {ang:.2f} | {berr:.1f} | {dt / seconds * 60:.1f} |",
              flush=True)
    if errs:
        a = np.abs(errs)
        print(f"\n|offset error|: median {np.median(a):.2f} ms, max {a.max():.2f} ms over {len(a)} flights "
              f"(one frame period: {1e3 / sf.FPS:.0f} ms)")


def discrepancy_stage() -> None:
    """The motion-only discrepancy workflow on the 1 s stretch that rotates most, after the sync: a
    procedural flight with a hidden 16 ms readout and τ = 11 ms (nominal 0 and 8 ms)."""
    from thermod.sync.discrepancy import refine_with_discrepancy

    hidden = {"rolling_readout": 0.016, "time_constant": 0.011}
    fl = sf.make_flight(6, 3.0, motion="procedural", effects=hidden)
    r = S.synchronise(fl.frames, fl.frame_t, fl.gyro_t, fl.gyro_rate, fl.intrinsics, tau_s=fl.tau_s)
    print("| stage | offset error ms | readout ms | τ ms | misalignment error ° | bias error mrad/s | "
          "named | s |")
    print("|---|---|---|---|---|---|---|---|")

    def row(stage, off, ro, tau, R, bias, named, sec):
        ang = math.degrees(float(np.linalg.norm(so3_log(fl.true_R.T @ np.asarray(R)))))
        berr = 1e3 * float(np.max(np.abs(np.asarray(bias) - fl.bias_rad_s)))
        print(f"| {stage} | {1e3 * (off - fl.true_offset_s):+.2f} | {1e3 * ro:.2f} | {1e3 * tau:.2f} | "
              f"{ang:.2f} | {berr:.1f} | {named} | {sec:.0f} |", flush=True)

    row("truth", fl.true_offset_s, 0.016, 0.011, fl.true_R, fl.bias_rad_s, "", 0)
    row("sync (rotations)", r.time_offset_s, r.fine.readout_s, r.tau_s, r.R_cam_gyro, r.fine.bias_rad_s, "",
        sum(r.seconds.values()))
    for agc in (True, False):
        t0 = time.perf_counter()
        frames = fl.frames if agc else fl.raw
        ref = refine_with_discrepancy(frames, fl.frame_t, fl.gyro_t, fl.gyro_rate, r, fl.intrinsics, agc=agc)
        d = ref.per_stretch[0]
        label = ("+ discrepancy (AGC'd video, AGC undone)" if agc
                 else "+ discrepancy (detector counts, no AGC)")
        row(label, d["time_offset_s"], d["readout_s"], d["tau_s"], d["R_cam_gyro"], d["gyro_bias_rad_s"],
            ", ".join(ref.named[0]) or "–", time.perf_counter() - t0)


if __name__ == "__main__":
    main()
