"""The settings of one frame's restoration: which kernel, which solver, which grid.

`DeblurConfig` is plain frozen data, shared by the daemon (``[deblur]`` in its TOML, validated by
`thermod.runtime.config`) and offline deblurring (`thermod deblur`, `thermod.batch`); its defaults are
the one set of defaults both use.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    m: float = 5.0                   # kernel window = m·τ
    min_coverage: float = 0.99       # gyro coverage below this → pass through
    ffc_settle_s: float | None = None  # after a flat-field correction: pass through this long (None: m·τ)
