"""`thermod discrepancy REC.h5 [REC2.h5 …] --out DIR [--config model.toml]`: which calibration effect
is the model missing, and how large is it? The workflow is `thermod.calib.discrepancy`; which kernel
explains the smear (none, box, exponential) is `thermod.calib.smear` (smear.json, smear_<i>.png)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import tomllib
from pathlib import Path

import cv2
import numpy as np

from thermod.calib import smear
from thermod.calib.discrepancy import CANDIDATES, EFFECTS, Model, analyse, prepare, write_report
from thermod.calib.discrepancy.data import working_scale
from thermod.errors import ConfigError, RecordingError
from thermod.io import recording as recording_io
from thermod.io.json_safe import jsonable
from thermod.io.toml_tables import read_toml
from thermod.paths import directory_problem, output_problem
from thermod.physics.calibration import CAMERA_KEYS, RANGES, Calibration, CalibrationError
from thermod.runtime import config as cfgmod

log = logging.getLogger("thermod.calib.discrepancy")

# What one recording may hold in memory: its frames (full resolution when they fit, else binned to the
# working resolution as they are read, then only the first ones), and its timeline.
MAX_FRAMES_MB = 512.0
MAX_TIMELINE_BYTES = 512 * 2**20
# The search's forward-model work (`ForwardModel.work`: IIR pixel-steps, a warped view's pixel counting
# `WARP_COST`) at the default --work-width, in proportion to the working area at others. Every phase of
# the search costs a bounded number of passes over the views, but their size follows the file (image
# speed, τ, frames: up to `data.WORK_VIEWS_MB`, 8× what `thermod sim`'s default recording needs) and
# each effect found adds a step: bounded here, past it no further phase starts and the report says so.
# 5e11 is about 20 min of one core (2.4 ns a unit): `thermod sim`'s default size (640×480, 1 s of
# shake:2) with one effect found took 1.25e11 (305 s of CPU), the suite's analyses at most 1e10; a file
# at the views' budget (8× the default's) searching four steps would take some 4e12 (hours) without it.
MAX_SEARCH_WORK = 5e11


def load(path: str, work_width: int) -> tuple[recording_io.Recording, float]:
    """The recording with at most `MAX_FRAMES_MB` of frames in memory, read one at a time; returns it
    and the scale its frames are stored at (1: full resolution). Each reduction is logged."""
    with recording_io.Reader(path, max_timeline_bytes=MAX_TIMELINE_BYTES) as r:
        calib = r.calibration
        n, (h, w) = r.n_frames, r.frame_shape
        scale, keep, dtype = 1.0, n, np.uint16
        if n * h * w * 2 / 1e6 > MAX_FRAMES_MB:
            scale = working_scale(calib, work_width)
            if scale < 1.0:
                dtype = np.float32
                intr = calib.intrinsics.scaled(scale)
                h, w = intr.height, intr.width
                log.warning("%s: %d frames of %d×%d are %.0f MB: binning them to %d×%d as they are read",
                            path, n, calib.width, calib.height, n * calib.width * calib.height * 2e-6, w, h)
            keep = min(n, int(MAX_FRAMES_MB * 1e6 // (h * w * np.dtype(dtype).itemsize)))
            if keep < n:
                log.warning("%s: keeping the first %d of %d frames (%.3g of %.3g s; %.0f MB of frames at "
                            "most)", path, keep, n, r.t[keep - 1] - r.t[0], r.t[-1] - r.t[0], MAX_FRAMES_MB)
        frames = np.empty((keep, h, w), dtype)
        for i in range(keep):
            f = r.frame(i)
            frames[i] = f if scale == 1.0 else cv2.resize(f.astype(np.float32), (w, h),
                                                          interpolation=cv2.INTER_AREA)
        rec = recording_io.Recording(frames, r.t[:keep], r.gyro_t, r.gyro_rate, calib,
                                     extra_attrs=r.group_attrs())
    return rec, scale


def scaled_calibration(calib: Calibration, scale: float) -> Calibration:
    """The camera of frames binned to `scale` × their size: intrinsics scaled, the pixel pitch grown (so
    Eq. 19's σ in pixels shrinks with them)."""
    if scale == 1.0:
        return calib
    i = calib.intrinsics.scaled(scale)
    return calib.replace(width=i.width, height=i.height, fx=i.fx, fy=i.fy, cx=i.cx, cy=i.cy,
                         pixel_pitch_um=min(calib.pixel_pitch_um / scale, RANGES["pixel_pitch_um"][1]))


def _named(e: CalibrationError, source: str, config: str | None):
    """A value the analysis stepped to is out of the Calibration's range: name the model's source (the
    --config file, else the recording whose attributes are the model) and the field."""
    if config is not None:
        return ConfigError(f"{config}: [calibration] {e.field}: {e.problem}")
    group = "camera" if e.field in CAMERA_KEYS else "gyro"
    return RecordingError(source, f"{group}.attrs['{e.field}']", e.problem)


def _config_calibration(path: str) -> tuple[Calibration, str | None]:
    """[calibration] of a thermod TOML, validated by `runtime.config`; also the file's text when it is a
    full configuration (so model.toml can be the same configuration with the table replaced).

    A file holding only a [calibration] table (like the model.toml this command writes without
    `--config`) is validated by slotting it into the packaged default configuration.
    """
    raw = read_toml(Path(path))         # a regular file of bounded size, valid UTF-8 TOML, or a ConfigError
    if "sources" in raw:
        return cfgmod.load(path, check_devices=False).calibration, Path(path).read_text()
    other = sorted(set(raw) - {"calibration"})
    if other or "calibration" not in raw:
        raise ConfigError(f"{path}: expected a full thermod configuration (with [sources]) or a file with "
                          "only "
                          f"a [calibration] table; found tables {sorted(raw)}")
    cal = raw["calibration"]
    base = tomllib.loads(cfgmod.default_path().read_text())
    base["calibration"] = cal
    if isinstance(cal, dict):   # the simulated default checks that its rates match the calibration's
        for ck, sk in (("frame_rate_hz", "frame_rate_hz"), ("rate_hz", "gyro_rate_hz")):
            if isinstance(cal.get(ck), (int, float)) and not isinstance(cal.get(ck), bool):
                base.setdefault("sim", {})[sk] = cal[ck]
    return cfgmod.parse(base, str(path), check_devices=False).calibration, None


def _check_out(out: Path) -> None:
    """--out is (made) a directory, and the report's files there are regular files or new, before the
    minutes of analysis (a FIFO named report.md would block the write at the end)."""
    if (problem := directory_problem(out)) is not None:
        raise ConfigError(f"--out {out}: {problem}")
    names = ("report.json", "model.toml", "report.md", "smear.json")
    for f in [out / n for n in names] + sorted(out.glob("*.png")):
        if f.exists() and (problem := output_problem(f)) is not None:
            raise ConfigError(f"--out {out}: {f.name}: {problem}")


def load_model(config: str | None, recs: list, paths: list[str]) -> tuple[Calibration, str | None]:
    """The model under test: `--config` TOML's [calibration], else the first recording's attributes.

    Returns (calibration, text of the configuration file when it is a full one, else None).
    """
    if config is not None:
        return _config_calibration(config)
    calib = recs[0].calibration
    for p, r in zip(paths[1:], recs[1:], strict=True):
        if r.calibration.as_dict() != calib.as_dict():
            log.warning("%s: calibration attributes differ from %s; testing the first one's model",
                        p, paths[0])
    return calib, None


def _smear(recs, paths, calib: Calibration, out: Path, say, scales, config: str | None) -> None:
    """smear.json and smear_<i>.png: which kernel explains each recording's smear (`thermod.calib.smear`),
    at the scale each recording's frames are held at."""
    results = []
    for i, (p, r) in enumerate(zip(paths, recs, strict=True)):
        try:
            res = smear.compare(r.frames, r.t, r.gyro_t, r.gyro_rate, scaled_calibration(calib, scales[i]))
        except CalibrationError as e:
            raise _named(e, p, config) from None
        results.append({"recording": str(p), **res.to_dict()})
        if res.frames:
            smear.plot(res, out / f"smear_{i}.png")
        say(f"{p}: {res.summary()}")
    (out / "smear.json").write_text(json.dumps(jsonable(results), indent=1, allow_nan=False))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recordings", nargs="+", metavar="REC.h5",
                        help="format-v1 recordings: a static segment followed by motion, or motion only")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory for the report")
    parser.add_argument("--config", metavar="TOML", help="thermod TOML whose [calibration] is the model to "
                        "test (default: the first recording's attributes)")
    parser.add_argument("--candidates", default=",".join(CANDIDATES),
                        help=f"comma-separated effects to try (default: all: {','.join(CANDIDATES)})")
    parser.add_argument("--work-width", type=int, default=160,
                        help="approximate working image width in pixels (default 160; frames are halved "
                             "until within 1.5× of it)")
    parser.add_argument("--max-steps", type=int, default=4, help="most effects to add (default 4)")
    parser.add_argument("--no-fpn", action="store_true", help="do not estimate fixed-pattern noise")


def run(args) -> int:
    cands = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
    bad = [c for c in cands if c not in EFFECTS]
    if bad:
        raise ConfigError(f"--candidates: unknown effect(s) {', '.join(bad)}; known: {', '.join(CANDIDATES)}")
    if args.work_width < 32:
        raise ConfigError(f"--work-width: expected ≥ 32 pixels, got {args.work_width}")

    _check_out(Path(args.out))

    def say(msg):
        print(msg, flush=True)

    loaded = [load(p, args.work_width) for p in args.recordings]
    recs, scales = [r for r, _ in loaded], [s for _, s in loaded]
    calib, config_text = load_model(args.config, recs, args.recordings)
    data = []
    for p, r, fs in zip(args.recordings, recs, scales, strict=True):
        source = str(r.extra_attrs.get("motion", {}).get("source", "gyro"))
        if source != "gyro":      # thermod import VIDEO without --gyro: no independent motion
            say(f"{p}: the motion was estimated from the {source}'s own pictures, not measured by a "
                "gyro: the gaps below measure the model against that estimate")
        try:
            d = prepare(r, calib, name=p, work_width=args.work_width, frames_scale=fs)
        except CalibrationError as e:
            raise _named(e, p, args.config) from None
        if d.reference == "static":
            say(f"{p}: {d.n_static} static frames, motion from t={d.t_onset:.3f} s, {len(d.frame_t)} motion "
                f"frames; noise σ {math.sqrt(d.noise_var):.2f} counts at {d.fm.w}×{d.fm.h}")
        else:
            say(f"{p}: no static lead-in: motion-only reference (scene canvas {d.scene.shape[1]}×"
                f"{d.scene.shape[0]} at the pose of t={d.t_ref:.3f} s), {len(d.frame_t)} frames at "
                f"{d.fm.w}×{d.fm.h}")
        data.append(d)
    try:
        ana = analyse(data, Model(calib), candidates=cands, max_steps=args.max_steps, fpn=not args.no_fpn,
                      max_work=MAX_SEARCH_WORK * (args.work_width / 160) ** 2, progress=say)
    except CalibrationError as e:        # a search stepped a field out of its range
        raise _named(e, args.recordings[0], args.config) from None
    if config_text is None:       # model.toml: the packaged default configuration, new calibration
        config_text = cfgmod.default_path().read_text()
    write_report(ana, args.out, args.recordings, config_text)
    _smear(recs, args.recordings, calib, Path(args.out), say, scales, args.config)
    for a in ana.ambiguous:
        say(f"{a['label']}: not named; model.toml keeps their values under test; to separate them record "
            f"{a['separating_motion']}")
    say(f"report: {Path(args.out) / 'report.md'}; model: {Path(args.out) / 'model.toml'}")
    return 0
