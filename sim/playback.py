"""Looping playback for the real-time simulated payload — the "faster approximation".

The fine-time renderer (`thermod.sim.detector`) costs ~0.1–0.5 s per 640×480 frame, too slow to
feed a daemon at 50 Hz. Instead a short sequence under a smooth *periodic* motion (orientation
back at its start after the loop) is rendered once with the full physics, cached on disk, and
played in a loop; a real-time gyro emulator samples the same motion through `rate_gyro(t)`.
Approximations against a live fine-time render: the world repeats every loop, and the sensor
noise of a frame repeats with it (it is rendered once).

Cache: `thermod.paths.cache_dir()`, one format-v1 recording per parameter set and scene
source (`playback-<hash>.h5`), re-rendered when missing or unreadable.

    pb = playback.load(PlaybackSpec(scene="real:2", seconds=2.0))
    frame = pb.frames[pb.index_at(t)]            # t: seconds since the payload started
    raw = pb.rate_gyro(t_samples)                # [n, 3] rad/s in the gyro frame (true calibration)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from thermod import paths
from thermod.errors import RecordingError, ThermodError
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim.scenes import scene_source

log = logging.getLogger(__name__)
CACHE_VERSION = 2


@dataclass(frozen=True)
class PlaybackSpec:
    """What to pre-render. `motion`: "sway[:deg]" (period snapped to the loop), "static", or a
    sine motion ("shake:…", "vibration:…") whose frequencies are snapped to whole cycles per loop."""

    scene: str = "real"
    motion: str = "sway:2"
    seconds: float = 2.0
    seed: int = 0
    calib: Calibration = field(default_factory=Calibration)
    effects: tuple = ()              # ((name, value), …) hidden truth effects, as in synth.simulate

    def key(self) -> str:
        """The cache key: every parameter, and the scene's actual source (`scenes.scene_source`), so a
        loop rendered from the procedural stand-in is not reused once the real frames appear (nor the
        reverse, nor after the image changes)."""
        d = {"v": CACHE_VERSION, "scene": self.scene, "source": scene_source(self.scene),
             "motion": self.motion, "seconds": self.seconds, "seed": self.seed,
             "calib": self.calib.as_dict(), "effects": [list(e) for e in self.effects]}
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:20]


def loop_motion(spec: str, loop_s: float, seed: int = 0) -> mo.Motion:
    """A motion whose orientation returns exactly to its start after `loop_s`."""
    m = mo.parse(spec, seed)
    if isinstance(m, mo.Static):
        return m
    if isinstance(m, mo.Sway):
        n = max(1, round(loop_s / m.period_s))
        return dataclasses.replace(m, period_s=loop_s / n, spec=f"{m.spec}@{loop_s:g}s")
    if isinstance(m, mo.SumOfSines):
        # whole cycles per loop; each axis' angle is a sum of sines, so it returns to 0 (small angles:
        # these are shakes and vibrations of a few degrees at most)
        f = np.maximum(1.0, np.round(m.freqs * loop_s)) / loop_s
        return mo.SumOfSines(f, m.amps, m.phases, spec=f"{m.spec}@{loop_s:g}s")
    raise ThermodError(f"playback motion {spec!r}: not periodic; use sway[:deg], static, shake or vibration")


@dataclass(frozen=True)
class LoopMotion:
    """The loop's motion as the gyro sees it: what a real-time emulator samples. Small and picklable,
    so the gyro process (`thermod.runtime.gyro_process`) gets it without the loop's frames."""

    motion: mo.Motion
    period_s: float
    true_calib: Calibration

    def omega_camera(self, t) -> np.ndarray:
        """True camera-frame rate (rad/s) at loop time t (any real t; periodic)."""
        return self.motion.omega(np.mod(np.asarray(t, np.float64), self.period_s))

    def rate_gyro(self, t) -> np.ndarray:
        """What an ideal gyro outputs at camera time t (gyro frame, raw: ω_g = scale⁻¹ Rᵀ ω_cam + bias
        with the TRUE calibration), for a real-time emulator to sample and add its own noise to."""
        return self.true_calib.camera_to_gyro(self.omega_camera(t))


class Playback:
    """A pre-rendered loop: `frames` uint16 [N, H, W] read at loop times `t` (k/fps, last row),
    `period_s` = N/fps, the nominal = true `calib`, and the motion for the gyro (`gyro_motion`)."""

    def __init__(self, rec: recording.Recording, motion: mo.Motion, spec: PlaybackSpec):
        self.frames = rec.frames
        self.t = rec.t - rec.t[0]
        self.calib = rec.calibration
        self.period_s = len(self.t) / rec.calibration.frame_rate_hz
        self.motion, self.spec = motion, spec
        self.truth = rec.extras.get("truth/frames")
        self.true_calib = Calibration.from_attrs(rec.extra_attrs["truth"], rec.extra_attrs["truth"]) \
            if "truth" in rec.extra_attrs else rec.calibration
        self.gyro_motion = LoopMotion(motion, self.period_s, self.true_calib)

    def index_at(self, t: float) -> int:
        """The loop frame whose read time is the last one at or before t (seconds since start)."""
        return int(math.floor(t * self.calib.frame_rate_hz + 1e-9)) % len(self.frames)

    def omega_camera(self, t) -> np.ndarray:
        return self.gyro_motion.omega_camera(t)

    def rate_gyro(self, t) -> np.ndarray:
        return self.gyro_motion.rate_gyro(t)


def cache_dir() -> Path:
    return paths.cache_dir()


def cache_path(spec: PlaybackSpec, directory: str | os.PathLike | None = None) -> Path:
    """Where the loop for `spec` is (or will be) cached."""
    return (Path(directory) if directory is not None else cache_dir()) / f"playback-{spec.key()}.h5"


def load(spec: PlaybackSpec | None = None, directory: str | os.PathLike | None = None,
         progress=False) -> Playback:
    """The cached loop for `spec` (default `PlaybackSpec()`), rendering and caching it first if needed
    (`progress` as `thermod.sim.synth.simulate`'s)."""
    from thermod.sim.synth import simulate

    spec = spec or PlaybackSpec()
    if not 0 < spec.seconds <= 60:
        raise ThermodError(f"playback seconds: expected 0 < s ≤ 60, got {spec.seconds}")
    n = round(spec.seconds * spec.calib.frame_rate_hz)
    loop_s = n / spec.calib.frame_rate_hz
    motion = loop_motion(spec.motion, loop_s, spec.seed)
    path = cache_path(spec, directory)
    d = path.parent
    if path.exists():
        try:
            rec = recording.read(path)
            if rec.extra_attrs.get("playback", {}).get("key") == spec.key():
                return Playback(rec, motion, spec)
            log.warning("playback cache %s: key mismatch, re-rendering", path)
        except RecordingError as e:
            log.warning("playback cache unreadable (%s), re-rendering", e)
    rec = simulate(spec.scene, motion, loop_s, spec.calib, effects=dict(spec.effects), seed=spec.seed,
                   progress=progress, t0=0.0, truth=True)
    rec.extras = {"truth/frames": rec.extras["truth/frames"]}
    rec.extra_attrs["playback"] = {"key": spec.key(), "motion": motion.spec, "loop_s": loop_s}
    try:
        d.mkdir(parents=True, exist_ok=True)
        recording.write(path, rec)
    except OSError as e:                       # a read-only cache must not stop the payload
        log.warning("playback cache %s not writable (%s); continuing without it", d, e)
    return Playback(rec, motion, spec)
