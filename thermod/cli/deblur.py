"""`thermod deblur IN.h5 -o OUT.h5` / `thermod deblur A.h5 B.h5 … -o DIR/`: offline deblurring.

For every frame the gyro samples of its 5τ history give the blur kernel (Eq. 18, thermal, or
Eq. 17, photon baseline), and `thermod.physics.deconv` removes it: by default spatially varying (a grid
of kernels, deconvolved in blended tiles — camera roll makes the blur vary across the frame),
or one kernel per frame with `--uniform` (the paper's method).

The output holds the input's /camera and /gyro (and any other datasets, e.g. /truth) plus
/deblurred/frames (float32, the input's counts) and /deblurred/t. A frame whose gyro window is
incomplete (coverage < `--min-coverage`) or whose kernel cannot be rendered is passed through
unchanged (as float32) and reported, never dropped; /deblurred/deblurred (bool [N]) says which
frames were deblurred and /deblurred/lambda (float64 [N]) the data weight each one used.
With `--celsius`, /deblurred/celsius (float32 [N, H, W], °C) converts the deblurred counts with a
radiometric model (`thermod.physics.radiometry`): `--radiometry FILE`'s [radiometry] table, else
`--config`'s, else the recording's own /radiometry attributes (same keys as the table).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from thermod.errors import RecordingError, ThermodError
from thermod.io import recording

log = logging.getLogger(__name__)

# Defaults chosen by benchmarks/bench_quality.py (six real scenes × seven speeds, and a roll-heavy
# real-gyro family): K&F α = 2/3 with the noise-adaptive λ, spatially varying on a 3×4 grid — as
# good as uniform when the blur is uniform (then solved once), +9.9 dB under roll.
DEFAULT_GRID = (3, 4)
MIN_COVERAGE = 0.99


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", type=Path, metavar="IN.h5", help="recording(s), format v1")
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="output file (one input) or directory (several inputs, or a path ending in /)")
    parser.add_argument("--kernel", choices=("thermal", "photon"), default="thermal",
                        help="blur model: microbolometer (Eq. 18, default) or photon-detector box (Eq. 17)")
    parser.add_argument("--exposure", type=float, default=None, metavar="S",
                        help="exposure of the photon kernel (s; default one frame period)")
    parser.add_argument("--method", choices=("kf", "wiener"), default="kf",
                        help="Krishnan–Fergus hyper-Laplacian (default) or Wiener/Tikhonov (fast)")
    parser.add_argument("--uniform", action="store_true",
                        help="one kernel per frame (the paper's method) instead of a kernel grid")
    parser.add_argument("--lambda", dest="lam", type=float, default=None,
                        help="data weight λ for a unit-range frame (K&F convention); default: adapted to "
                             "each frame's noise (see thermod.physics.deconv.Deconvolver)")
    parser.add_argument("--alpha", type=float, default=2.0 / 3.0,
                        help="K&F prior exponent (1 or 2/3; default 2/3)")
    parser.add_argument("--grid", type=int, nargs=2, default=list(DEFAULT_GRID), metavar=("R", "C"),
                        help=f"kernel grid rows and columns for spatially varying deblurring "
                             f"(default {DEFAULT_GRID[0]} {DEFAULT_GRID[1]})")
    parser.add_argument("--no-psf", action="store_true", help="do not include the optical PSF (Eq. 19)")
    parser.add_argument("--config", type=Path, default=None, metavar="TOML",
                        help="take the calibration from this file's [calibration] table (e.g. the "
                             "model.toml of `thermod discrepancy`); keys it omits keep the recording's")
    parser.add_argument("--celsius", action="store_true",
                        help="also write /deblurred/celsius (float32 °C) converted after deblurring")
    parser.add_argument("--radiometry", type=Path, default=None, metavar="TOML",
                        help="the counts→°C model for --celsius (implies it): this file's [radiometry] table "
                             "(default: --config's, else the recording's /radiometry attributes)")
    parser.add_argument("--min-coverage", type=float, default=MIN_COVERAGE,
                        help=f"pass a frame through when its gyro window coverage is below this "
                             f"(default {MIN_COVERAGE})")


def _outputs(inputs: list[Path], output: Path) -> list[Path]:
    """Output path per input; several inputs (or -o DIR/) write DIR/<input name>."""
    as_dir = len(inputs) > 1 or str(output).endswith(os.sep) or output.is_dir()
    if not as_dir:
        outs = [output]
    else:
        if output.exists() and not output.is_dir():
            raise ThermodError(f"-o {output}: several inputs need an output directory, this is a file")
        output.mkdir(parents=True, exist_ok=True)
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


class _FrameDeblurrer:
    """Kernel rendering + deconvolution of one frame, with the CLI's options."""

    def __init__(self, args):
        from thermod.physics import deconv  # numba start-up only when deblurring

        self.kind = args.kernel
        self.exposure = args.exposure
        self.uniform = args.uniform
        self.grid = tuple(int(g) for g in args.grid)
        self.psf = not args.no_psf
        self.min_coverage = float(args.min_coverage)
        if self.grid[0] < 1 or self.grid[1] < 1:
            raise ThermodError(f"--grid {self.grid[0]} {self.grid[1]}: expected at least 1 row and 1 column")
        if self.exposure is not None and not self.exposure > 0:
            raise ThermodError(f"--exposure {self.exposure}: expected a positive time in seconds")
        if not 0 <= self.min_coverage <= 1:
            raise ThermodError(f"--min-coverage {self.min_coverage}: expected a fraction in [0, 1]")
        # per-frame kernels never repeat: a tiny OTF cache (one entry per tile of a frame is plenty)
        self.dec = deconv.Deconvolver(method=args.method, alpha=args.alpha, lam=args.lam, cache_size=2)
        self.celsius = bool(getattr(args, "celsius", False) or getattr(args, "radiometry", None))
        self.radiometry = _file_radiometry(args) if self.celsius else None  # None: the recording's own

    def __call__(self, rec: recording.Recording, i: int) -> tuple[np.ndarray | None, str]:
        """(deblurred frame, "") or (None, why it was passed through)."""
        from thermod.physics import kernels

        c = rec.calibration
        t = float(rec.t[i])
        exposure = self.exposure if self.exposure is not None else 1.0 / float(c.frame_rate_hz)
        if self.uniform or self.grid == (1, 1):
            if self.kind == "thermal":
                k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, c, t, psf=self.psf)
            else:
                k = kernels.render_photon_kernel(rec.gyro_t, rec.gyro_rate, c, t, exposure, psf=self.psf)
            if k.coverage < self.min_coverage:
                return None, f"gyro coverage {k.coverage:.3f} < {self.min_coverage}"
            return self.dec.run(rec.frames[i], k), ""
        g = kernels.render_kernel_grid(rec.gyro_t, rec.gyro_rate, c, t, self.grid, kind=self.kind,
                                       psf=self.psf, exposure_s=exposure if self.kind == "photon" else None)
        if g.coverage < self.min_coverage:
            return None, f"gyro coverage {g.coverage:.3f} < {self.min_coverage}"
        return self.dec.run_varying(rec.frames[i], g), ""


def _file_radiometry(args):
    """--celsius's model from --radiometry (required to have one) or --config (optional), else None."""
    from thermod.runtime.config import load_radiometry

    if getattr(args, "radiometry", None) is not None:
        model = load_radiometry(args.radiometry)
        if model is None:
            raise ThermodError(f"--radiometry {args.radiometry}: no [radiometry] table with model = 'planck' "
                               "or 'linear'")
        return model
    return load_radiometry(args.config) if args.config is not None else None


def _recording_radiometry(rec: recording.Recording, src: Path, fd: _FrameDeblurrer):
    """The model --celsius converts with: the command line's, else the recording's /radiometry attrs."""
    from thermod.physics import radiometry

    if fd.radiometry is not None:
        return fd.radiometry
    attrs = rec.extra_attrs.get(radiometry.RECORDING_GROUP)
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


def _deblur_file(src: Path, dst: Path, fd: _FrameDeblurrer, bar, config: Path | None = None) -> dict:
    rec = recording.read(src)
    if config is not None:
        from thermod.runtime.config import load_calibration

        c = load_calibration(config, base=rec.calibration)
        if (c.height, c.width) != rec.frames.shape[1:]:
            raise ThermodError(f"{config}: calibration is {c.width}×{c.height} but {src} has "
                               f"{rec.frames.shape[2]}×{rec.frames.shape[1]} frames")
        rec.calibration = c  # deblur with it; the output's /camera and /gyro attrs record it too
    try:
        return _deblur_recording(rec, src, dst, fd, bar)
    except OSError as e:  # output side: full disk, permissions, missing directory …
        raise ThermodError(f"{dst}: cannot write the output ({e})") from None


def _deblur_recording(rec: recording.Recording, src: Path, dst: Path, fd: _FrameDeblurrer, bar) -> dict:
    n, h, w = rec.frames.shape
    model = _recording_radiometry(rec, src, fd) if fd.celsius else None  # before any output is written
    bar.total = (bar.total or 0) + n
    bar.refresh()
    part = dst.with_name(dst.name + ".part")
    base = recording.Recording(rec.frames, rec.t, rec.gyro_t, rec.gyro_rate, rec.calibration,
                               extras=rec.extras, extra_attrs={k: v for k, v in rec.extra_attrs.items()
                                                               if k.split("/")[0] != "deblurred"})
    recording.write(part, base)
    passed: list[tuple[int, str]] = []
    times = []
    lams = np.full(n, np.nan)
    try:
        with h5py.File(part, "r+") as f:
            g = f.require_group("deblurred")
            ds = g.create_dataset("frames", shape=(n, h, w), dtype=np.float32,
                                  chunks=(1, h, w) if n else None)
            ok = np.zeros(n, dtype=bool)
            if model is not None:  # °C after deblurring: counts, not temperatures, are linear in flux
                cds = g.create_dataset("celsius", shape=(n, h, w), dtype=np.float32,
                                       chunks=(1, h, w) if n else None)
                cds.attrs.update({"units": "degC", **model.as_dict()})
            for i in range(n):
                t0 = time.perf_counter()
                try:
                    out, why = fd(rec, i)
                except ThermodError as e:  # a kernel that cannot be rendered: keep the frame
                    out, why = None, str(e)
                times.append(time.perf_counter() - t0)
                if out is None:
                    passed.append((i, why))
                    log.info("%s: frame %d passed through: %s", src, i, why)
                    out = rec.frames[i].astype(np.float32)
                else:
                    ok[i] = True
                    lams[i] = fd.dec.last_lam
                ds[i] = out
                if model is not None:
                    cds[i] = model.to_celsius(out)
                bar.update(1)
            g.create_dataset("t", data=np.asarray(rec.t, np.float64))
            g.create_dataset("deblurred", data=ok)
            g.create_dataset("lambda", data=lams)    # per frame (noise-adaptive unless --lambda)
            g.attrs.update({"kernel": fd.kind, "method": fd.dec.method,
                            "lambda_mode": "adaptive" if fd.dec.lam is None else "fixed",
                            "alpha": fd.dec.alpha, "grid": np.asarray((1, 1) if fd.uniform else fd.grid),
                            "psf": fd.psf, "min_coverage": fd.min_coverage, "source": str(src)})
        os.replace(part, dst)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    return {"src": src, "dst": dst, "n": n, "passed": passed, "times": times, "lams": lams}


def run(args) -> int:
    from tqdm import tqdm

    outs = _outputs(list(args.inputs), args.output)
    fd = _FrameDeblurrer(args)
    reports, failed = [], []
    t_start = time.perf_counter()
    with tqdm(total=0, unit="frame", desc="thermod deblur", disable=None, file=sys.stderr) as bar:
        for src, dst in zip(args.inputs, outs, strict=True):
            try:
                reports.append(_deblur_file(src, dst, fd, bar, args.config))
            except RecordingError as e:
                if len(outs) == 1:
                    raise
                print(f"thermod deblur: error: {e}", file=sys.stderr)  # keep going with the others
                failed.append(src)
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
    mode = "uniform" if fd.uniform else f"grid {fd.grid[0]}×{fd.grid[1]}"
    print(f"total: {n_all - n_pass} frames deblurred, {n_pass} passed through, {len(reports)} file(s) in "
          f"{wall:.1f} s ({1e3 * wall / max(n_all, 1):.1f} ms/frame; "
          f"{fd.kind} kernel, {fd.dec.method}, {mode})")
    if failed:
        print(f"thermod deblur: {len(failed)} file(s) failed: {', '.join(map(str, failed))}", file=sys.stderr)
        return 2
    return 0
