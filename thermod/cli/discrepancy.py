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

from thermod.calib import smear
from thermod.calib.discrepancy import CANDIDATES, EFFECTS, Model, analyse, prepare, write_report
from thermod.errors import ConfigError
from thermod.io import recording as recording_io
from thermod.io.json_safe import jsonable
from thermod.io.toml_tables import read_toml
from thermod.paths import directory_problem, output_problem
from thermod.physics.calibration import Calibration
from thermod.runtime import config as cfgmod

log = logging.getLogger("thermod.calib.discrepancy")


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


def _smear(recs, paths, calib: Calibration, out: Path, say) -> None:
    """smear.json and smear_<i>.png: which kernel explains each recording's smear (`thermod.calib.smear`)."""
    results = []
    for i, (p, r) in enumerate(zip(paths, recs, strict=True)):
        res = smear.compare(r.frames, r.t, r.gyro_t, r.gyro_rate, calib)
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

    recs = [recording_io.read(p) for p in args.recordings]
    calib, config_text = load_model(args.config, recs, args.recordings)
    data = []
    for p, r in zip(args.recordings, recs, strict=True):
        source = str(r.extra_attrs.get("motion", {}).get("source", "gyro"))
        if source != "gyro":      # thermod import VIDEO without --gyro: no independent motion
            say(f"{p}: the motion was estimated from the {source}'s own pictures, not measured by a "
                "gyro: the gaps below measure the model against that estimate")
        d = prepare(r, calib, name=p, work_width=args.work_width)
        if d.reference == "static":
            say(f"{p}: {d.n_static} static frames, motion from t={d.t_onset:.3f} s, {len(d.frame_t)} motion "
                f"frames; noise σ {math.sqrt(d.noise_var):.2f} counts at {d.fm.w}×{d.fm.h}")
        else:
            say(f"{p}: no static lead-in: motion-only reference (scene canvas {d.scene.shape[1]}×"
                f"{d.scene.shape[0]} at the pose of t={d.t_ref:.3f} s), {len(d.frame_t)} frames at "
                f"{d.fm.w}×{d.fm.h}")
        data.append(d)
    ana = analyse(data, Model(calib), candidates=cands, max_steps=args.max_steps, fpn=not args.no_fpn,
                  progress=say)
    if config_text is None:       # model.toml: the packaged default configuration, new calibration
        config_text = cfgmod.default_path().read_text()
    write_report(ana, args.out, args.recordings, config_text)
    _smear(recs, args.recordings, calib, Path(args.out), say)
    for a in ana.ambiguous:
        say(f"{a['label']}: not named; model.toml keeps their values under test; to separate them record "
            f"{a['separating_motion']}")
    say(f"report: {Path(args.out) / 'report.md'}; model: {Path(args.out) / 'model.toml'}")
    return 0
