"""`thermod deblur IN.h5 -o OUT.h5` / `thermod deblur A.h5 B.h5 … -o DIR/`: offline deblurring.

Each frame's kernel comes from its gyro history through `thermod.restore.plan.render`, the daemon's
dispatch, and `thermod.physics.deconv` removes it: spatially varying by default (`--uniform`: one
kernel), solved jointly with its predecessors (`DeblurConfig.temporal_views`; `--single-frame`:
alone). Every other default is `DeblurConfig()`'s.

The rules it keeps: no frame is dropped (a frame with an incomplete gyro window or no kernel is
passed through as float32 and reported); an output is written into ``OUT.h5.part`` and renamed
only when complete, never left half-written; frames are processed one at a time. ``--celsius``
takes its model from ``--radiometry``, else ``--config``, else the recording, and fails before any
output without one. ``--video`` writes a playable 8-bit H.264 (``--side-by-side``).

In a batch, a file that fails is reported and the others go on; the command then lists the
failures and exits 2. Several files run in local worker processes (`--jobs N`; `thermod.batch.local`)
or one task per file on a Dask cluster (`--scheduler tcp://HOST:8786`; `thermod.batch.cluster`), both
through the same per-file job (`thermod.batch.job`) and writing the same bytes; this module is the
command line. Output datasets and engines: docs/design.md §3 and §7.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from thermod.errors import ThermodError
from thermod.restore.settings import DeblurConfig

log = logging.getLogger(__name__)

# Offline there is no latency budget, so the finest kernel grid is the default (benchmarks/
# bench_quality.py: as good as uniform when the blur is uniform, then solved once, and +9.9 dB under
# roll); the daemon picks the grid each frame's roll needs (mode "adaptive"). Everything else is the
# one set of defaults, DeblurConfig's.
OFFLINE = dataclasses.replace(DeblurConfig(), mode="grid")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = OFFLINE
    parser.add_argument("inputs", nargs="+", type=Path, metavar="IN.h5", help="recording(s), format v1")
    parser.add_argument("-o", "--output", required=True,     # a str: Path() would drop "DIR/"'s slash
                        help="output file (one input) or directory (several inputs, or a path ending in /)")
    parser.add_argument("--kernel", choices=("thermal", "photon"), default=d.kernel,
                        help=f"blur model: microbolometer (Eq. 18) or photon-detector box (Eq. 17); "
                             f"default {d.kernel}")
    parser.add_argument("--exposure", type=float, default=d.exposure_s, metavar="S",
                        help="exposure of the photon kernel (s; default one frame period)")
    parser.add_argument("--method", choices=("kf", "wiener"), default=d.method,
                        help=f"Krishnan–Fergus hyper-Laplacian or Wiener/Tikhonov (fast); default {d.method}")
    parser.add_argument("--uniform", action="store_true",
                        help="one kernel per frame (the paper's method) instead of a kernel grid")
    parser.add_argument("--adaptive", action="store_true",
                        help="per frame, the coarsest grid (up to --grid) the roll in its window needs, as "
                             "the daemon renders it (mode \"adaptive\"); default: always the --grid")
    parser.add_argument("--views", type=int, default=d.temporal_views, metavar="N",
                        help=f"frames per temporal solve, the frame itself included (default "
                             f"{d.temporal_views}; 1 = --single-frame)")
    parser.add_argument("--single-frame", action="store_true",
                        help="solve each frame alone (no temporal solve; faster, noisier)")
    parser.add_argument("--lambda", dest="lam", type=float, default=d.lam,
                        help="data weight λ for a unit-range frame (K&F convention); default: adapted to "
                             "each frame's noise (see thermod.physics.deconv.Deconvolver)")
    parser.add_argument("--alpha", type=float, default=d.alpha,
                        help=f"K&F prior exponent (1 or 2/3; default {d.alpha:.4g})")
    parser.add_argument("--grid", type=int, nargs=2, default=list(d.grid), metavar=("R", "C"),
                        help=f"kernel grid rows and columns for spatially varying deblurring "
                             f"(default {d.grid[0]} {d.grid[1]})")
    parser.add_argument("--no-psf", action="store_true", help="do not include the optical PSF (Eq. 19)")
    parser.add_argument("--config", type=Path, default=None, metavar="TOML",
                        help="take the calibration from this file's [calibration] table (e.g. the "
                             "model.toml of `thermod discrepancy`); keys it omits keep the recording's")
    parser.add_argument("--celsius", action="store_true",
                        help="also write /deblurred/celsius (float32 °C) converted after deblurring")
    parser.add_argument("--radiometry", type=Path, default=None, metavar="TOML",
                        help="the counts→°C model for --celsius (implies it): this file's [radiometry] table "
                             "(default: --config's, else the recording's /radiometry attributes)")
    parser.add_argument("--min-coverage", type=float, default=d.min_coverage,
                        help=f"pass a frame through when its gyro window coverage is below this "
                             f"(default {d.min_coverage})")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                        help="run one task per file on this Dask distributed scheduler's workers (they "
                             "must see the inputs and the output directory at the same paths: a shared "
                             "filesystem); default: local processes (--jobs)")
    parser.add_argument("--jobs", type=int, default=0, metavar="N",
                        help="local worker processes for several files (default 0: one per usable core; "
                             "1: one after another in this process)")
    parser.add_argument("--video", type=Path, default=None, metavar="OUT.mp4",
                        help="also write the deblurred frames as 8-bit H.264 with the input's AGC "
                             "(one input)")
    parser.add_argument("--side-by-side", action="store_true",
                        help="with --video: input (left) and deblurred (right) in one picture")
    parser.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                        help="give up on --scheduler after this many seconds without an answer (default 10)")


def deblur_config(args) -> DeblurConfig:
    """The command line's settings as a DeblurConfig, checked by the daemon's ``[deblur]`` schema
    (`thermod.restore.settings.deblur_settings`: the same ranges, choices and α rule); a ConfigError
    names each bad option."""
    from thermod.restore.settings import deblur_settings

    if args.uniform and args.adaptive:
        raise ThermodError("--uniform and --adaptive: expected one of them (one kernel, or the grid each "
                           "frame needs)")
    grid = [int(g) for g in args.grid]
    mode = "uniform" if args.uniform or grid == [1, 1] else "adaptive" if args.adaptive else OFFLINE.mode
    values = {"method": args.method, "lambda": args.lam, "alpha": float(args.alpha), "kernel": args.kernel,
              "exposure_s": args.exposure, "psf": not args.no_psf, "mode": mode, "grid": grid,
              "min_coverage": float(args.min_coverage),
              "temporal_views": 1 if args.single_frame else int(args.views)}
    origins = {"method": "--method", "lambda": "--lambda", "alpha": "--alpha", "kernel": "--kernel",
               "exposure_s": "--exposure", "psf": "--no-psf", "mode": "--uniform / --adaptive",
               "grid": "--grid", "min_coverage": "--min-coverage", "temporal_views": "--views"}
    return deblur_settings(values, origins)


def _outputs(inputs: list[Path], output: str | Path) -> list[Path]:
    """Output path per input; several inputs (or -o DIR/) write DIR/<input name>."""
    as_dir = len(inputs) > 1 or str(output).endswith(os.sep) or Path(output).is_dir()
    output = Path(output)
    if not as_dir:
        outs = [output]
    else:
        if output.exists() and not output.is_dir():
            raise ThermodError(f"-o {output}: several inputs need an output directory, this is a file")
        try:
            output.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ThermodError(f"-o {output}: cannot create the output directory ({e.strerror or e})") \
                from None
        outs = [output / p.name for p in inputs]
        seen = {}
        for p, o in zip(inputs, outs, strict=True):
            if o in seen:
                raise ThermodError(f"{p} and {seen[o]} would both be written to {o}: rename one")
            seen[o] = p
    for p, o in zip(inputs, outs, strict=True):
        if p.exists() and o.exists() and os.path.samefile(p, o):
            raise ThermodError(f"-o {o}: would overwrite the input {p}; choose another output")
    return outs


def command_radiometry(args):
    """--celsius's model from the command line: --radiometry's table (which must hold one), else
    --config's (optional); None leaves it to each recording's /radiometry attributes."""
    from thermod.runtime.config import load_radiometry

    if args.radiometry is not None:
        model = load_radiometry(args.radiometry)
        if model is None:
            raise ThermodError(f"--radiometry {args.radiometry}: no [radiometry] table with model = 'planck' "
                               "or 'linear'")
        return model
    return load_radiometry(args.config) if args.config is not None else None


def run(args) -> int:
    from thermod.batch import job as batch_job

    cfg = deblur_config(args)
    if args.jobs < 0:
        raise ThermodError(f"--jobs {args.jobs}: expected 0 (one process per usable core) or a positive "
                           "number")
    celsius = args.celsius or args.radiometry is not None
    model = command_radiometry(args) if celsius else None
    outs = _outputs(list(args.inputs), args.output)
    if args.side_by_side and args.video is None:
        raise ThermodError("--side-by-side: applies to --video OUT.mp4")
    if args.video is not None:
        if len(args.inputs) != 1:
            raise ThermodError(f"--video {args.video}: takes one input recording, got {len(args.inputs)}")
        from thermod.io.video import VideoWriter

        VideoWriter.check_path(args.video)     # a name H.264 cannot go in: refused before the deblur
    batch_job.deconvolver(cfg)     # bad --lambda/--alpha: one error before any file (and warm locally)
    jobs = [batch_job.Job(src, dst, cfg, args.config, celsius, model)
            for src, dst in zip(args.inputs, outs, strict=True)]
    t_start = time.perf_counter()
    if args.scheduler:
        from thermod.batch import cluster

        outcomes = cluster.run(jobs, args.scheduler, connect_timeout_s=args.connect_timeout)
    else:
        from thermod.batch import local

        processes = args.jobs if args.jobs > 0 else local.usable_cores()
        outcomes = local.run(jobs, processes=processes)
    wall = time.perf_counter() - t_start
    reports = [o.report for o in outcomes if o.ok]
    failed = [o.job.src for o in outcomes if not o.ok]
    n_all = sum(r.n for r in reports)
    n_pass = sum(len(r.passed) for r in reports)
    for r in reports:
        ms = 1e3 * float(np.median(r.times)) if r.times else 0.0
        lam = float(np.nanmedian(r.lams)) if np.isfinite(r.lams).any() else float("nan")
        print(f"{r.src} → {r.dst}: {r.n - len(r.passed)} deblurred, {len(r.passed)} passed "
              f"through, {ms:.1f} ms/frame (median), λ {lam:.0f} (median)")
        if r.motion_source != "gyro":
            print(f"  motion from the {r.motion_source}: estimated, not measured by a gyro (see /motion in "
                  f"{r.src})")
        for i, why in r.passed[:20]:
            print(f"  frame {i} passed through: {why}")
        if len(r.passed) > 20:
            print(f"  … and {len(r.passed) - 20} more")
    grid = f"{cfg.grid[0]}×{cfg.grid[1]}"
    mode = {"uniform": "uniform", "adaptive": f"adaptive grid up to {grid}"}.get(cfg.mode, f"grid {grid}")
    mode += f", temporal {cfg.temporal_views} views" if cfg.temporal_views > 1 else ", single-frame"
    where = f" on {args.scheduler}" if args.scheduler else ""
    if n_all:      # a per-frame time only over frames that exist (failed files have none)
        print(f"total: {n_all - n_pass} frames deblurred, {n_pass} passed through, {len(reports)} file(s) "
              f"in {wall:.1f} s{where} ({1e3 * wall / n_all:.1f} ms/frame; "
              f"{cfg.kernel} kernel, {cfg.method}, {mode})")
    elif reports:
        print(f"total: no frames in {len(reports)} file(s)")
    if failed:
        print(f"thermod deblur: {len(failed)} of {len(outs)} file(s) failed: "
              f"{', '.join(str(src) for src in failed)}", file=sys.stderr)
        return 2
    if args.video is not None:
        n = write_playable(args.inputs[0], outs[0], args.video, args.side_by_side)
        print(f"wrote {args.video}: {n} frames, 8-bit H.264" + (", input | deblurred" if args.side_by_side
                                                                 else ""))
    return 0


def write_playable(src: Path, deblurred: Path, out: Path, side_by_side: bool = False, crf: int = 18) -> int:
    """Write `deblurred`'s /deblurred/frames as 8-bit H.264 with the input's AGC; returns the frames.

    A recording imported from an 8-bit video (its /import ``video_bit_depth`` is 8) is already on that
    video's AGC scale, frame by frame: the deblurred frame is rounded and clipped to 0–255. Any other
    recording goes through `thermod.io.video.PercentileAGC`: each input frame sets the stretch and the
    deblurred frame is shown with the same gain and offset (a blur kernel sums to one, so both share
    a scale)."""
    from thermod.io import video
    from thermod.io.recording import Reader

    with Reader(src) as r:
        imported = r.group_attrs().get("import", {})
        eight_bit = int(imported.get("video_bit_depth", 16)) == 8
        # written with the range the input video had (limited unless it said full), as a player shows it
        full_range = bool(imported.get("video_full_range", True))
    agc = video.PercentileAGC()
    with Reader(deblurred) as r:
        deb = r.dataset("deblurred/frames")
        width = r.calibration.width * (2 if side_by_side else 1)
        rate = r.calibration.frame_rate_hz
        with video.VideoWriter(out, width, r.calibration.height, crf=crf, nominal_fps=rate,
                               full_range=full_range) as w:
            for i, (t, frame) in enumerate(zip(r.t, r, strict=True)):
                d = np.asarray(deb[i], np.float32)
                if eight_bit:
                    shown = np.clip(frame, 0, 255).astype(np.uint8)
                    d8 = np.clip(d + 0.5, 0, 255).astype(np.uint8)
                else:
                    shown, gain, offset = agc.apply(frame, float(t))
                    d8 = agc.stretch(d, gain, offset)
                w.write(np.hstack([shown, d8]) if side_by_side else d8, float(t))
            return w.n_frames
