"""The settings of one frame's restoration: which kernel, which solver, which grid.

`DeblurConfig` is plain frozen data, shared by the daemon (``[deblur]`` in its TOML) and offline
deblurring (`thermod deblur`, `thermod.batch`); its defaults are the one set of defaults both use, and
`DEBLUR` is the one schema (keys, ranges, choices, the α rule) that checks a configuration file's
table (`read_deblur`) and a command line's options (`deblur_settings`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from thermod.io.toml_tables import Key, Problems, Section, with_defaults


@dataclass(frozen=True)
class DeblurConfig:
    enabled: bool = True
    method: str = "kf"               # kf | wiener
    lam: float | None = None         # data weight (K&F convention); None = thermod.physics.deconv default
    alpha: float = 1.0               # prior exponent: 1 (TV, default) or 2/3 (hyper-Laplacian)
    kernel: str = "thermal"          # thermal (Eq. 18) | photon (Eq. 17, baseline)
    exposure_s: float | None = None  # photon kernel exposure; None = 1 / frame rate
    psf: bool = True                 # optical PSF refinement (Eq. 19)
    mode: str = "adaptive"           # adaptive (grid from the roll, `plan.grid_needed`) | uniform | grid
    grid: tuple[int, int] = (6, 8)   # rows × cols (adaptive: the finest grid): near-square cells on 4:3
    grid_tol_px: float = 0.5         # adaptive: kernel shift allowed across a cell (px) before it is split
    temporal_tol_px: float = 2.0     # governor: a rung coarsens its grid to this kernel shift (px), the floor
    kf_iterations: int | None = None  # K&F β steps (None: K&F's six); the governor's faster rung uses 3
    temporal_views: int = 6          # frames per solve, the frame itself included (1: single-frame solve)
    governor: bool = True            # degrade the method, not the share of frames (`runtime.governor`)
    max_solve_s: float = 0.030       # governor: longest solve wanted per frame, for latency (s)
    headroom: float = 0.15           # governor: share of the budget kept free for jitter
    latency_p99_s: float = 0.060     # governor: the published frames' p99 latency it holds (s)
    m: float = 5.0                   # kernel window = m·τ
    min_coverage: float = 0.99       # gyro coverage below this → pass through
    ffc_settle_s: float | None = None  # after a flat-field correction: pass through this long (None: m·τ)

    def within_frame(self, width: int, height: int) -> DeblurConfig:
        """These settings with the grid capped at one cell per pixel row and column of a frame."""
        rows, cols = self.grid
        if rows <= height and cols <= width:
            return self
        return dataclasses.replace(self, grid=(max(1, min(rows, height)), max(1, min(cols, width))))


#: ``[deblur]`` → DeblurConfig: the keys, ranges and rules a configuration file and a command line share.
DEBLUR = with_defaults(DeblurConfig, {
    "enabled": Key(bool),
    "method": Key(str, choices=("kf", "wiener"), doc="single-frame solver; the daemon's temporal rung "
                  "(temporal_views > 1) always solves by Wiener, so kf needs temporal_views = 1 there"),
    "lambda": Key(float, lo=0.0, lo_open=True, hi=1e9, attr="lam", doc="data weight; absent = the solver's"),
    "alpha": Key(float, rule=lambda a: None if abs(a - 1.0) < 1e-9 or abs(a - 2.0 / 3.0) < 1e-3 else
                 "1 or 2/3 (0.667) — the exponents with a closed-form w-step", doc="prior exponent",
                 accepts="1 (TV) or 2/3 (hyper-Laplacian)"),
    "kernel": Key(str, choices=("thermal", "photon")),
    "exposure_s": Key(float, lo=0.0, lo_open=True, hi=1.0, doc="photon kernel exposure; absent: 1/fps"),
    "psf": Key(bool),
    "mode": Key(str, choices=("adaptive", "uniform", "grid")),
    "grid": Key(tuple, length=(2,), item=int, lo=1, hi=16, doc="[rows, cols]"),
    "grid_tol_px": Key(float, lo=0.05, hi=100.0, doc="adaptive: kernel shift allowed across a cell (px)"),
    "temporal_tol_px": Key(float, lo=0.05, hi=100.0, doc="governor: kernel shift across a cell (px) up to "
                           "which a rung coarsens its grid while the workers keep up (the floor)"),
    "kf_iterations": Key(int, lo=1, hi=12, doc="K&F β steps; absent: K&F's six"),
    "temporal_views": Key(int, lo=1, hi=16, doc="offline: frames per temporal solve, the frame itself "
                          "included; daemon: > 1 puts the recursive temporal rungs on the governor's "
                          "ladder (1: single-frame solves everywhere)"),
    "governor": Key(bool, doc="degrade the method under load, not the share of frames deblurred"),
    "max_solve_s": Key(float, lo=0.0, lo_open=True, hi=10.0, doc="governor: longest solve wanted per frame"),
    "headroom": Key(float, lo=0.0, hi=0.9, doc="governor: share of the budget kept free"),
    "latency_p99_s": Key(float, lo=0.001, hi=60.0, doc="governor: the p99 latency (read to published) "
                         "it scales its budget to hold (with a video gyro source: plus one frame period)"),
    "m": Key(float, lo=1.0, hi=20.0, doc="kernel window = m·τ"),
    "min_coverage": Key(float, lo=0.0, hi=1.0, doc="gyro coverage below this → pass through"),
    "ffc_settle_s": Key(float, lo=0.0, hi=60.0, doc="pass through this long after an FFC; absent: m·τ"),
})


def read_deblur(problems: Problems, table: Any) -> DeblurConfig:
    """The ``[deblur]`` table as a DeblurConfig; a bad key is recorded in `problems` and keeps its default."""
    s = Section(problems, "deblur", table)
    kw = s.read(DEBLUR)
    kw["alpha"] = 1.0 if abs(kw["alpha"] - 1.0) < 1e-9 else 2.0 / 3.0
    s.done()
    return DeblurConfig(**kw)


def deblur_settings(values: dict, origins: Mapping[str, str]) -> DeblurConfig:
    """``[deblur]`` keys given elsewhere (a command line's), checked by the same schema as a
    configuration file's; `origins` maps each key to where it came from (e.g. ``{"grid": "--grid"}``).
    One ConfigError naming every bad one."""
    problems = Problems("command line", {f"deblur.{k}": v for k, v in origins.items()})
    cfg = read_deblur(problems, {k: v for k, v in values.items() if v is not None})
    problems.raise_if_any()
    return cfg
