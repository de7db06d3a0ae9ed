"""Sharp scenes in raw detector counts (float32, uint16-compatible range).

A scene is a texture laid on the sphere of view directions at the camera's angular pixel size
(see `thermod.sim.detector`); outside the texture it is mirror-tiled, so no motion ever exposes
an undefined border.

    bars       the paper's collimator targets: 4-bar groups (hot bars on a uniform background),
               tiled, horizontal and vertical, bar widths 2–8 px
    points     point sources (hot pinholes) on a uniform background, on a jittered grid
    texture    a seeded procedural scene: 1/f clutter plus warm objects with sharp edges
    real[:N]   the N-th real 16-bit frame of shared/data/thermal (sorted by name), default 0
    PATH       any 16-bit (or 8-bit) PNG/TIFF

Counts: background 18000 (like the real DJI frames), responsivity `COUNTS_PER_K` counts per kelvin.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from thermod.errors import ThermodError

log = logging.getLogger(__name__)

BACKGROUND = 18000.0
COUNTS_PER_K = 40.0          # ~25 mK/count, a typical 16-bit radiometric microbolometer stream


def shared_data_dir() -> Path | None:
    """shared/data: $THERMOD_SHARED_DATA, else the first `shared/data` walking up from this package."""
    env = os.environ.get("THERMOD_SHARED_DATA")
    if env:
        p = Path(env)
        return p if p.is_dir() else None
    for parent in Path(__file__).resolve().parents:
        cand = parent / "shared" / "data"
        if cand.is_dir():
            return cand
    return None


def real_frames() -> list[Path]:
    d = shared_data_dir()
    if d is None:
        return []
    return sorted(p for p in (d / "thermal").glob("*.png"))


def real_frame(spec: str) -> Path | None:
    """The file a ``real[:N]`` scene reads, or None when there are no real frames (shared/data absent)."""
    frames = real_frames()
    if not frames:
        return None
    arg = spec.partition(":")[2]
    try:
        i = int(arg) if arg else 0
    except ValueError:
        raise ThermodError(f"--scene {spec!r}: expected real or real:N with N an integer") from None
    if not 0 <= i < len(frames):
        raise ThermodError(f"--scene {spec!r}: index out of range, {len(frames)} real frames "
                           f"(0–{len(frames) - 1})")
    return frames[i]


def scene_source(spec: str) -> str:
    """What `load_scene(spec)` draws from, to key caches of rendered scenes: the image file (with its
    size and modification time) for ``real[:N]`` and paths, ``texture`` where ``real`` falls back to
    it, and the spec itself for the procedural scenes."""
    name = spec.partition(":")[0]
    if name in ("bars", "points", "texture"):
        return spec
    path = real_frame(spec) if name == "real" else Path(spec)
    if path is None:
        return "texture (no real frames)"
    try:
        st = path.stat()
    except OSError:
        return f"{path} (missing)"
    return f"{path.resolve()} ({st.st_size} B, mtime {st.st_mtime_ns})"


def load_scene(spec: str | os.PathLike | np.ndarray, shape: tuple[int, int] = (960, 1280),
               seed: int = 0) -> np.ndarray:
    """Scene texture (float32 counts, at least `shape` = (rows, cols)) from a spec (see module doc).

    Real or file scenes smaller than `shape` are mirror-padded; procedural ones are drawn at `shape`.
    "real" falls back to "texture" when shared/data is absent, and logs a warning saying so.
    """
    h, w = int(shape[0]), int(shape[1])
    if h < 8 or w < 8:
        raise ThermodError(f"--scene: shape {shape} too small (need ≥ 8×8)")
    if isinstance(spec, np.ndarray):
        img = _validated(spec, "scene array")
        return _pad_to(img, h, w)
    s = str(spec)
    name, _, arg = s.partition(":")
    if name == "bars":
        return bars(h, w, seed)
    if name == "points":
        return points(h, w, seed)
    if name == "texture":
        return texture(h, w, seed)
    if name == "real":
        frame = real_frame(s)
        if frame is None:
            log.warning("scene %r: no real frames (shared/data not found; set THERMOD_SHARED_DATA), "
                        "using the procedural 'texture' scene instead", s)
            return texture(h, w, seed)
        return _pad_to(read_image(frame), h, w)
    p = Path(s)
    if p.suffix.lower() in (".png", ".tif", ".tiff", ".pgm") or p.exists():
        return _pad_to(read_image(p), h, w)
    raise ThermodError(f"--scene {s!r}: unknown scene; expected bars, points, texture, real[:N] "
                       "or an image path")


def read_image(path: str | os.PathLike) -> np.ndarray:
    path = Path(path)
    if not path.exists():
        raise ThermodError(f"--scene {path}: file does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ThermodError(f"--scene {path}: not a readable image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint8:     # 8-bit picture: map to a plausible thermal span around the background
        img = BACKGROUND + (img.astype(np.float32) - 128.0) * 16.0
    return _validated(img, str(path))


def _validated(img, what) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ThermodError(f"{what}: expected a 2-D image of at least 8×8, got shape {img.shape}")
    img = img.astype(np.float32)
    if not np.all(np.isfinite(img)):
        raise ThermodError(f"{what}: contains NaN or infinite values")
    return img


def _pad_to(img: np.ndarray, h: int, w: int) -> np.ndarray:
    ph, pw = max(0, h - img.shape[0]), max(0, w - img.shape[1])
    if ph or pw:
        img = cv2.copyMakeBorder(img, ph // 2, ph - ph // 2, pw // 2, pw - pw // 2, cv2.BORDER_REFLECT_101)
    return np.ascontiguousarray(img, dtype=np.float32)


def _box(img, y0, y1, x0, x1, val):
    """Add `val` over [y0, y1) × [x0, x1) with exact fractional (area) coverage at the edges."""
    h, w = img.shape
    r0, r1 = max(0, int(np.floor(y0))), min(h, int(np.ceil(y1)))
    c0, c1 = max(0, int(np.floor(x0))), min(w, int(np.ceil(x1)))
    if r1 <= r0 or c1 <= c0:
        return
    ys, xs = np.arange(r0, r1), np.arange(c0, c1)
    cy = np.clip(np.minimum(ys + 1, y1) - np.maximum(ys, y0), 0, 1)
    cx = np.clip(np.minimum(xs + 1, x1) - np.maximum(xs, x0), 0, 1)
    img[r0:r1, c0:c1] += val * np.outer(cy, cx).astype(np.float32)


def bars(h: int, w: int, seed: int = 0, delta_k: float = 5.0, cell: int = 96) -> np.ndarray:
    """Collimator 4-bar targets tiled over the scene: one group of 4 hot bars (1:1 duty, length
    5× the bar width) per `cell`×`cell` px, bar widths cycling through 2, 3, 4, 6, 8 px and the
    orientation alternating vertical/horizontal, on a uniform background (exact area coverage at
    sub-pixel edges). Anywhere the camera looks it sees every width in both orientations."""
    img = np.full((h, w), BACKGROUND, np.float32)
    val = delta_k * COUNTS_PER_K
    widths = [2, 3, 4, 6, 8]
    for i, yc in enumerate(np.arange(cell / 2, h - cell / 4, cell)):
        for j, xc in enumerate(np.arange(cell / 2, w - cell / 4, cell)):
            bw = widths[(i + 2 * j) % len(widths)]
            vertical = (i + j) % 2 == 0
            length, span = 5 * bw, 7 * bw                 # 4 bars + 3 gaps
            for b in range(4):
                o = -span / 2 + 2 * b * bw
                if vertical:
                    _box(img, yc - length / 2, yc + length / 2, xc + o, xc + o + bw, val)
                else:
                    _box(img, yc + o, yc + o + bw, xc - length / 2, xc + length / 2, val)
    return img


def points(h: int, w: int, seed: int = 0, delta_k: float = 50.0, spacing: int = 96,
           sigma: float = 0.6) -> np.ndarray:
    """Point sources (pinholes behind a collimator): Gaussian spots σ = 0.6 px of peak `delta_k`
    kelvin on a jittered grid `spacing` px apart (sub-pixel positions, seeded)."""
    rng = np.random.default_rng([seed, 3])
    img = np.full((h, w), BACKGROUND, np.float32)
    amp = delta_k * COUNTS_PER_K
    r = int(np.ceil(4 * sigma))
    for yc in np.arange(spacing / 2, h - r - 1, spacing):
        for xc in np.arange(spacing / 2, w - r - 1, spacing):
            y, x = yc + rng.uniform(-0.5, 0.5), xc + rng.uniform(-0.5, 0.5)
            iy, ix = int(round(y)), int(round(x))
            yy, xx = np.mgrid[iy - r:iy + r + 1, ix - r:ix + r + 1]
            img[iy - r:iy + r + 1, ix - r:ix + r + 1] += amp * np.exp(
                -((yy - y) ** 2 + (xx - x) ** 2) / (2 * sigma**2)).astype(np.float32)
    return img


def texture(h: int, w: int, seed: int = 0, clutter_k: float = 2.0) -> np.ndarray:
    """Seeded procedural thermal scene: 1/f ("pink") clutter of `clutter_k` kelvin RMS plus warm
    and cool objects (discs and rectangles, 2–15 K) with sharp, anti-aliased edges."""
    rng = np.random.default_rng([seed, 4])
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    spec = (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape)) / f
    spec[0, 0] = 0
    clutter = np.fft.irfft2(spec, s=(h, w))
    clutter *= clutter_k * COUNTS_PER_K / clutter.std()
    img = (BACKGROUND + clutter).astype(np.float32)
    n_obj = max(8, int(h * w / 12000))
    ss = 4                                    # supersampled masks: anti-aliased edges
    for _ in range(n_obj):
        dk = rng.choice([-1, 1], p=[0.3, 0.7]) * rng.uniform(2, 15) * COUNTS_PER_K
        sz = rng.uniform(6, max(6.0, min(h, w) / 6))      # a small frame: 6 px objects (one draw either way)
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        y0, y1 = int(max(0, cy - sz)), int(min(h, cy + sz + 1))
        x0, x1 = int(max(0, cx - sz)), int(min(w, cx + sz + 1))
        if y1 <= y0 or x1 <= x0:
            continue
        yy, xx = np.mgrid[y0 * ss:y1 * ss, x0 * ss:x1 * ss]
        yy, xx = (yy + 0.5) / ss - 0.5, (xx + 0.5) / ss - 0.5
        if rng.random() < 0.5:
            m = (yy - cy) ** 2 + (xx - cx) ** 2 < sz**2
        else:
            a = rng.uniform(0, np.pi)
            u = (xx - cx) * np.cos(a) + (yy - cy) * np.sin(a)
            v = -(xx - cx) * np.sin(a) + (yy - cy) * np.cos(a)
            m = (np.abs(u) < sz) & (np.abs(v) < sz * rng.uniform(0.2, 1.0))
        cover = m.reshape(y1 - y0, ss, x1 - x0, ss).mean(axis=(1, 3))
        img[y0:y1, x0:x1] += (dk * cover).astype(np.float32)
    return img
