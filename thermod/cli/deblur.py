"""`thermod deblur IN.h5 -o OUT.h5` / `thermod deblur A.h5 B.h5 … -o DIR/`: offline deblurring.

For every frame the gyro samples of its m·τ history give the blur kernel (Eq. 18, thermal, or
Eq. 17, photon baseline) through `thermod.runtime.pipeline.render` — the same dispatch as the
daemon — and `thermod.physics.deconv` removes it: by default spatially varying (a grid of kernels,
deconvolved in blended tiles — camera roll makes the blur vary across the frame), or one kernel
per frame with `--uniform` (the paper's method). Every other default is `DeblurConfig()`'s.

The output holds the input's /camera and /gyro (and any other datasets, e.g. /truth) plus
/deblurred/frames (float32, the input's counts) and /deblurred/t. A frame whose gyro window is
incomplete (coverage < `--min-coverage`) or whose kernel cannot be rendered is passed through
unchanged (as float32) and reported, never dropped; /deblurred/deblurred (bool [N]) says which
frames were deblurred and /deblurred/lambda (float64 [N]) the data weight each one used.
With `--celsius`, /deblurred/celsius (float32 [N, H, W], °C; attrs units = "degC" and the model's
keys) converts each frame of /deblurred/frames — the deblurred counts, or a passed-through frame's
raw counts, as the daemon does — with a radiometric model (`thermod.physics.radiometry`):
`--radiometry FILE`'s [radiometry] table, else `--config`'s, else the recording's own /radiometry
attributes (same keys as the table). A recording with no model fails before any output is written.

Frames are read, deblurred and written one at a time (memory does not grow with the recording),
into ``OUT.h5.part``, renamed to ``OUT.h5`` only when complete: an existing output is never left
half-written. In a batch, a file that fails (input or output side) is reported and the others go
on; the command then lists the failures and exits 2.
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

from thermod.errors import RecordingError, ThermodError
from thermod.io import recording
from thermod.runtime.config import DeblurConfig

log = logging.getLogger(__name__)

# Offline there is no latency budget, so the kernel grid is the default (benchmarks/bench_quality.py:
# as good as uniform when the blur is uniform, then solved once, and +9.9 dB under roll); the daemon
# defaults to uniform. Everything else is the one set of defaults, DeblurConfig's.
OFFLINE = dataclasses.replace(DeblurConfig(), mode="grid")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = OFFLINE
    parser.add_argument("inputs", nargs="+", type=Path, metavar="IN.h5", help="recording(s), format v1")
    parser.add_argument("-o", "--output", required=True, type=Path,
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


def deblur_config(args) -> DeblurConfig:
    """The command line's settings as the DeblurConfig that `pipeline.render` takes."""
    grid = tuple(int(g) for g in args.grid)
    if grid[0] < 1 or grid[1] < 1:
        raise ThermodError(f"--grid {grid[0]} {grid[1]}: expected at least 1 row and 1 column")
    if args.exposure is not None and not args.exposure > 0:
        raise ThermodError(f"--exposure {args.exposure}: expected a positive time in seconds")
    if not 0 <= args.min_coverage <= 1:
        raise ThermodError(f"--min-coverage {args.min_coverage}: expected a fraction in [0, 1]")
    uniform = args.uniform or grid == (1, 1)
    return dataclasses.replace(OFFLINE, method=args.method, lam=args.lam, alpha=float(args.alpha),
                               kernel=args.kernel, exposure_s=args.exposure, psf=not args.no_psf,
                               mode="uniform" if uniform else "grid", grid=grid,
                               min_coverage=float(args.min_coverage))


def _outputs(inputs: list[Path], output: Path) -> list[Path]:
    """Output path per input; several inputs (or -o DIR/) write DIR/<input name>."""
    as_dir = len(inputs) > 1 or str(output).endswith(os.sep) or output.is_dir()
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


def _recording_radiometry(r: recording.Reader, src: Path):
    """The recording's own model, from its /radiometry attributes; a RecordingError naming the file
    when it has none."""
    from thermod.physics import radiometry

    attrs = r.group_attrs().get(radiometry.RECORDING_GROUP)
    if not attrs:
        raise RecordingError(src, "/radiometry", "no attributes, and --celsius needs a radiometric model: "
                             "give --radiometry FILE (a [radiometry] table) or --config with one")
    try:
        model = radiometry.from_mapping(attrs)
    except radiometry.RadiometryError as e:
        raise RecordingError(src, f"radiometry.attrs['{e.field}']", e.problem) from None
    if model is None:
        raise RecordingError(src, "radiometry.attrs['model']", "is 'none': no model to convert with")
    return model


class OutputError(ThermodError):
    """The output of one file cannot be written (disk full, permissions, a directory in the way)."""

    def __init__(self, dst: Path, why):
        super().__init__(f"{dst}: cannot write the output ({why})")


def _deblur_frame(frame: np.ndarray, reader: recording.Reader, calib, t: float, cfg: DeblurConfig, dec):
    """(deblurred frame, "") or (None, why it is passed through)."""
    from thermod.runtime.pipeline import render

    try:
        kernel, info = render(reader.gyro_t, reader.gyro_rate, calib, t, cfg)
        if info["coverage"] < cfg.min_coverage:
            return None, f"gyro coverage {info['coverage']:.3f} < {cfg.min_coverage}"
        return (dec.run_varying(frame, kernel) if cfg.mode == "grid" else dec.run(frame, kernel)), ""
    except ThermodError as e:   # a kernel that cannot be rendered or inverted: keep the frame
        return None, str(e)


def _deblur_file(src: Path, dst: Path, cfg: DeblurConfig, dec, bar, config: Path | None = None,
                 celsius: bool = False, model=None) -> dict:
    """Deblur one recording into `dst`; with `celsius`, convert with `model` (None: the recording's)."""
    if dst.is_dir():
        raise OutputError(dst, "a directory is in the way")
    with recording.Reader(src) as r:
        calib = r.calibration
        if config is not None:
            from thermod.runtime.config import load_calibration

            calib = load_calibration(config, base=r.calibration)
            if (calib.height, calib.width) != r.frame_shape:
                raise ThermodError(f"{config}: calibration is {calib.width}×{calib.height} but {src} has "
                                   f"{r.frame_shape[1]}×{r.frame_shape[0]} frames")
        if celsius and model is None:       # before any output is written
            model = _recording_radiometry(r, src)
        try:
            writer = recording.Writer(dst)
        except RecordingError as e:
            raise OutputError(dst, e.problem) from None
        try:
            with writer:
                return _deblur_stream(r, calib, src, writer, cfg, dec, bar, model)
        except OSError as e:   # output side: full disk, permissions, a directory in the way …
            raise OutputError(dst, e) from None
        except RecordingError as e:
            if Path(e.path) != src:      # the writer's checks are about the output
                raise OutputError(dst, f"{e.field}: {e.problem}") from None
            raise


def _deblur_stream(r: recording.Reader, calib, src: Path, w: recording.Writer, cfg: DeblurConfig, dec,
                   bar, model=None) -> dict:
    n, (h, w_px) = r.n_frames, r.frame_shape
    bar.total = (bar.total or 0) + n
    bar.refresh()
    w.reserve("camera/frames", n, (h, w_px), np.uint16)
    w.reserve("camera/t", n, (), np.float64)
    w.reserve("deblurred/frames", n, (h, w_px), np.float32)
    if model is not None:
        w.reserve("deblurred/celsius", n, (h, w_px), np.float32)
        w.set_attrs("deblurred/celsius", {"units": "degC", **model.as_dict()})
    w.put("gyro/t", r.gyro_t)
    w.put("gyro/rate", r.gyro_rate)
    r.copy_extras_into(w.file)
    passed: list[tuple[int, str]] = []
    times = []
    lams = np.full(n, np.nan)
    ok = np.zeros(n, dtype=bool)
    for i in range(n):
        frame = r.frame(i)
        w.append_frame(frame, r.t[i])
        t0 = time.perf_counter()
        out, why = _deblur_frame(frame, r, calib, float(r.t[i]), cfg, dec)
        times.append(time.perf_counter() - t0)
        if out is None:
            passed.append((i, why))
            log.info("%s: frame %d passed through: %s", src, i, why)
            out = frame.astype(np.float32)
        else:
            ok[i] = True
            lams[i] = dec.last_lam
        w.append("deblurred/frames", out, np.float32)
        if model is not None:     # °C after deblurring: counts, not temperatures, are linear in flux
            w.append("deblurred/celsius", model.to_celsius(out), np.float32)
        bar.update(1)
    w.put("deblurred/t", r.t)
    w.put("deblurred/deblurred", ok)
    w.put("deblurred/lambda", lams)      # per frame (noise-adaptive unless --lambda)
    w.set_attrs("deblurred", {"kernel": cfg.kernel, "method": dec.method, "mode": cfg.mode,
                              "lambda_mode": "adaptive" if dec.lam is None else "fixed",
                              "alpha": dec.alpha, "m": cfg.m,
                              "grid": np.asarray((1, 1) if cfg.mode == "uniform" else cfg.grid),
                              "psf": cfg.psf, "min_coverage": cfg.min_coverage, "source": str(src)})
    w.commit(calib)
    return {"src": src, "dst": w.path, "n": n, "passed": passed, "times": times, "lams": lams}


def run(args) -> int:
    from tqdm import tqdm

    from thermod.physics.deconv import Deconvolver  # numba start-up only when deblurring

    cfg = deblur_config(args)
    celsius = args.celsius or args.radiometry is not None
    model = command_radiometry(args) if celsius else None
    outs = _outputs(list(args.inputs), args.output)
    # per-frame kernels never repeat: a tiny OTF cache (one entry per tile of a frame is plenty)
    dec = Deconvolver(method=cfg.method, alpha=cfg.alpha, lam=cfg.lam, cache_size=2)
    reports, failed = [], []
    t_start = time.perf_counter()
    with tqdm(total=0, unit="frame", desc="thermod deblur", disable=None, file=sys.stderr) as bar:
        for src, dst in zip(args.inputs, outs, strict=True):
            try:
                reports.append(_deblur_file(src, dst, cfg, dec, bar, args.config, celsius, model))
            except ThermodError as e:    # this file fails; the others go on
                failed.append((src, str(e)))
            except Exception as e:       # noqa: BLE001 - a bug must not cost the rest of the batch
                log.debug("%s failed", src, exc_info=True)
                failed.append((src, f"{src}: unexpected {type(e).__name__}: {e} (-v for the traceback)"))
            if failed and failed[-1][0] is src:
                print(f"thermod deblur: error: {failed[-1][1]}", file=sys.stderr)
    wall = time.perf_counter() - t_start
    n_all = sum(r["n"] for r in reports)
    n_pass = sum(len(r["passed"]) for r in reports)
    for r in reports:
        ms = 1e3 * float(np.median(r["times"])) if r["times"] else 0.0
        lam = float(np.nanmedian(r["lams"])) if np.isfinite(r["lams"]).any() else float("nan")
        print(f"{r['src']} → {r['dst']}: {r['n'] - len(r['passed'])} deblurred, {len(r['passed'])} passed "
              f"through, {ms:.1f} ms/frame (median), λ {lam:.0f} (median)")
        for i, why in r["passed"][:20]:
            print(f"  frame {i} passed through: {why}")
        if len(r["passed"]) > 20:
            print(f"  … and {len(r['passed']) - 20} more")
    mode = "uniform" if cfg.mode == "uniform" else f"grid {cfg.grid[0]}×{cfg.grid[1]}"
    print(f"total: {n_all - n_pass} frames deblurred, {n_pass} passed through, {len(reports)} file(s) in "
          f"{wall:.1f} s ({1e3 * wall / max(n_all, 1):.1f} ms/frame; "
          f"{cfg.kernel} kernel, {dec.method}, {mode})")
    if failed:
        print(f"thermod deblur: {len(failed)} of {len(outs)} file(s) failed: "
              f"{', '.join(str(src) for src, _ in failed)}", file=sys.stderr)
        return 2
    return 0
