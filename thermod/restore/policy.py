"""The one per-frame policy, live and offline: deblur a frame (`Plan`) or pass it through
(`PassThrough`, with a reason from `thermod.io.wire.REASONS`).

A frame read at t_k is passed through, in this order, when

- deblurring is off → ``disabled``;
- the camera flags a flat-field correction, or the detector is settling after one → ``ffc`` (the
  caller knows the camera's state and says so);
- the gyro window (t_k − m·τ − readout, t_k] holds a gap: a lost sample (FIFO overflow, clock
  jump: the caller's ``gap``) or a step longer than `MAX_STEP_PERIODS` sample periods → ``gyro_gap``;
- it holds fewer than two samples → ``gyro_incomplete`` (``gyro_offline`` when the gyro is down);
- the kernel cannot be rendered → ``kernel_error``;
- the kernel keeps less than ``min_coverage`` of its weight → ``gyro_incomplete``, except at the
  start of the gyro stream, where a kernel keeping `START_COVERAGE` (only its oldest tail precedes
  the first sample) is deblurred (``Plan.start_partial``).

The daemon's pipeline and `thermod deblur` (`thermod.batch`) both decide through these rules:
offline `plan_frame` applies them at once; the daemon's scheduler applies those before the kernel
(`order_kernel`) and the worker that solves the frame renders it and applies the rest
(`render_order`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from thermod.errors import ThermodError
from thermod.physics.calibration import Calibration
from thermod.physics.kernels.grids import MAX_STEP_PERIODS, has_hole  # noqa: F401 - the rule's names here too
from thermod.restore.plan import grids_within, kernel_window, render
from thermod.restore.settings import DeblurConfig

START_COVERAGE = 0.9      # a kernel at the start of the gyro stream keeping this much is deblurred


@dataclass(frozen=True)
class Plan:
    """A frame to deblur: its kernel (or grid), the render's info, and the settings it was made with."""

    kernel: object
    info: dict
    deblur: DeblurConfig
    start_partial: bool = False      # the gyro stream began inside the window (`START_COVERAGE`)


@dataclass(frozen=True)
class PassThrough:
    """A frame to publish raw, and why."""

    reason: str                      # one of `thermod.io.wire.REASONS`
    info: dict = dataclasses.field(default_factory=dict)
    detail: str = ""
    kernel: object = None            # the kernel, when one was rendered (a coverage short of the rule)

    def __str__(self) -> str:
        return self.reason + (f": {self.detail}" if self.detail else "")


def gyro_span(calib: Calibration, deblur: DeblurConfig, t_frame: float) -> tuple[float, float, float]:
    """(g0, g1, margin): the gyro-clock span of the frame's kernel window and the margin around it that
    the render reads (the DLPF inverse and the clipped-run continuation)."""
    t0_cam, t1_cam = kernel_window(calib, deblur, t_frame)
    g0, g1 = (float(x) for x in calib.camera_time_to_gyro(np.array([t0_cam, t1_cam])))   # clock drift
    return g0, g1, 2.0 / calib.rate_hz + calib.gyro_condition_margin_s


def refused_early(deblur: DeblurConfig, ffc: bool) -> PassThrough | None:
    """The rules that need no gyro (a caller need not wait for the gyro to apply them)."""
    if not deblur.enabled:
        return PassThrough("disabled")
    if ffc:
        return PassThrough("ffc", detail="flat-field correction")
    return None


def plan_frame(t_frame: float, gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration,
               deblur: DeblurConfig, *, gap: bool = False, ffc: bool = False, online: bool = True,
               first_gyro_t: float | None = None, choose: Callable[[tuple, tuple], tuple] | None = None,
               renderer=render) -> Plan | PassThrough:
    """Plan the frame read at `t_frame` (camera clock, last row) from raw gyro samples (a window
    around it or a whole recording's; only the frame's span counts), per the module's rules:
    `order_kernel`, then `render_order`.

    `first_gyro_t`: the first sample of the gyro stream (default: the first given). `choose(needed,
    floor)`: the grid to render, given the grid the roll needs and the coarsest the governor may keep
    (`grids_within`); without it an adaptive ``deblur.mode`` renders the needed grid. `renderer`:
    `thermod.restore.plan.render` or a stand-in with its signature."""
    order = order_kernel(t_frame, gyro_t, gyro_rate, calib, deblur, gap=gap, ffc=ffc, online=online,
                         first_gyro_t=first_gyro_t, choose=choose)
    return order if isinstance(order, PassThrough) else render_order(order, calib, renderer)


@dataclass(frozen=True)
class KernelOrder:
    """A frame the rules before its kernel accept: what the kernel is rendered from. The daemon's
    scheduler makes it and the worker that solves the frame renders it (`render_order`), so the
    render runs beside the solve, not in the scheduler."""

    t_frame: float
    gyro_t: np.ndarray               # the samples of the kernel window (and its margin)
    gyro_rate: np.ndarray
    deblur: DeblurConfig             # with the grid chosen (mode uniform or grid)
    online: bool = True
    started_inside: bool = False     # the gyro stream began inside the window (`START_COVERAGE`)

    @property
    def info(self) -> dict:
        return {"n_samples": len(self.gyro_t)}


def order_kernel(t_frame: float, gyro_t: np.ndarray, gyro_rate: np.ndarray, calib: Calibration,
                 deblur: DeblurConfig, *, gap: bool = False, ffc: bool = False, online: bool = True,
                 first_gyro_t: float | None = None,
                 choose: Callable[[tuple, tuple], tuple] | None = None) -> KernelOrder | PassThrough:
    """The rules before the kernel (disabled, ffc, gyro_gap, no samples) and the grid choice: the
    frame's `KernelOrder`, or why it passes through. Arguments as `plan_frame`."""
    early = refused_early(deblur, ffc)
    if early is not None:
        return early
    deblur = deblur.within_frame(calib.width, calib.height)
    g0, g1, margin = gyro_span(calib, deblur, t_frame)
    gyro_t = np.asarray(gyro_t, np.float64)
    i0, i1 = np.searchsorted(gyro_t, [g0 - margin, g1 + margin])
    i0, i1 = max(0, int(i0) - 2), min(len(gyro_t), int(i1) + 2)   # two beyond each end, as the ring pads
    t, rate = gyro_t[i0:i1], np.asarray(gyro_rate)[i0:i1]
    if gap or has_hole(t, calib.rate_hz):
        return PassThrough("gyro_gap", {"n_samples": len(t)}, "samples lost inside the kernel window")
    if len(t) < 2:
        return PassThrough(_short_of_gyro(online), {"coverage": 0.0, "n_samples": len(t)},
                           "no gyro samples in the window")
    try:
        if choose is not None:
            needed, floor = grids_within(t, rate, calib, t_frame, deblur,
                                         (deblur.grid_tol_px, deblur.temporal_tol_px))
            g = tuple(choose(needed, floor))
            deblur = dataclasses.replace(deblur, mode="uniform" if g == (1, 1) else "grid", grid=g)
    except Exception as e:  # noqa: BLE001 - a kernel that cannot be made costs its frame, never the stream
        return _kernel_error(e, len(t))
    first = float(gyro_t[0]) if first_gyro_t is None and len(gyro_t) else first_gyro_t
    started = first is not None and math.isfinite(first) and first > g0
    return KernelOrder(float(t_frame), t, rate, deblur, online, started)


def render_order(order: KernelOrder, calib: Calibration, renderer=render) -> Plan | PassThrough:
    """The ordered kernel rendered, and the coverage rule applied: a `Plan`, or why the frame
    passes through (``kernel_error``, ``gyro_incomplete`` / ``gyro_offline`` with the kernel)."""
    deblur = order.deblur
    try:
        kernel, info = renderer(order.gyro_t, order.gyro_rate, calib, order.t_frame, deblur)
    except Exception as e:  # noqa: BLE001 - a kernel that cannot be made costs its frame, never the stream
        return _kernel_error(e, len(order.gyro_t))
    if info["coverage"] >= deblur.min_coverage:
        return Plan(kernel, info, deblur)
    if order.started_inside and info["coverage"] >= START_COVERAGE:
        return Plan(kernel, info, deblur, start_partial=True)
    return PassThrough(_short_of_gyro(order.online), info,
                       f"gyro coverage {info['coverage']:.3f} < {deblur.min_coverage}", kernel)


def _short_of_gyro(online: bool) -> str:
    """The reason of a frame whose window the gyro does not cover: late samples, or a gyro that is down."""
    return "gyro_incomplete" if online else "gyro_offline"


def _kernel_error(e: Exception, n_samples: int) -> PassThrough:
    what = str(e) if isinstance(e, ThermodError) else f"{type(e).__name__}: {e}"
    return PassThrough("kernel_error", {"n_samples": n_samples}, f"the kernel could not be rendered: {what}")
