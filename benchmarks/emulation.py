"""A slower (or faster) machine emulated on this one, for the daemon's benchmarks (`--like-yardstick MS`).

A machine whose yardstick (plain reference K&F, ms/frame) reads MS does each frame's work in MS / this
machine's. Slowing the world by s = this machine's yardstick / MS instead puts every solve here in the
same proportion to the frame period as there: the camera runs at fps / s, the latency goals are s
times the configured ones, and the latencies measured here are reported divided by s.

Two ways to slow the world:

- the simulated payload: its camera at fps / s (`bench_daemon.payload`);
- a recording: `stretched` scales its clock by s (times × s, rates ÷ s, τ × s, rates in Hz ÷ s), so the
  daemon meets a camera and a gyro that run s times slower and render the same kernels in pixels.

`daemon_sets` gives the daemon's overrides for either: its latency caps × s, and its windows of
seconds × s (the monitor's fit window and its stretch limit, the gyro history), so that they hold as
many frames as on the emulated machine. CPU shares stay as configured: a share of a core s times
slower, in a world s times slower, does the same work per frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np


def daemon_sets(scale: float, cfg=None) -> list[str]:
    """``KEY=VALUE`` overrides of the daemon's configuration (`cfg`: `config.load()`'s) for a world
    slowed `scale` times."""
    from thermod.runtime import config

    cfg = cfg or config.load()
    return [f"deblur.max_solve_s={cfg.deblur.max_solve_s * scale:.4f}",
            f"deblur.latency_p99_s={cfg.deblur.latency_p99_s * scale:.4f}",
            f"monitor.window_s={cfg.monitor.window_s * scale:.3f}",
            f"monitor.max_window_s={cfg.monitor.max_window_s * scale:.3f}",
            f"pipeline.gyro_ring_s={cfg.pipeline.gyro_ring_s * scale:.3f}"]


def stretched(rec, scale: float):
    """`rec` (a :class:`thermod.io.recording.Recording`) on a clock `scale` times slower: every time and
    time constant × scale, every rate (rad/s, Hz) ÷ scale. Each frame's kernel in pixels is unchanged
    (the thermal kernel of Eq. 18 is invariant under t → s·t, ω → ω/s, τ → s·τ). Its extras (the
    truth) are left out: they stay on the original's clock, where the scores read them."""
    c = rec.calibration
    cal = dataclasses.replace(
        c, tau_s=c.tau_s * scale, readout_s=c.readout_s * scale, time_offset_s=c.time_offset_s * scale,
        clock_epoch_s=c.clock_epoch_s * scale, frame_rate_hz=c.frame_rate_hz / scale,
        rate_hz=c.rate_hz / scale, bias_rad_s=tuple(b / scale for b in c.bias_rad_s),
        gyro_lowpass_hz=c.gyro_lowpass_hz / scale, gyro_range_rad_s=c.gyro_range_rad_s / scale)
    deblurred_t = None if rec.deblurred_t is None else np.asarray(rec.deblurred_t, np.float64) * scale
    return dataclasses.replace(rec, t=np.asarray(rec.t, np.float64) * scale,
                               gyro_t=np.asarray(rec.gyro_t, np.float64) * scale,
                               gyro_rate=(np.asarray(rec.gyro_rate, np.float64) / scale).astype(np.float32),
                               calibration=cal, deblurred_t=deblurred_t, extras={},
                               extra_attrs={})
