"""Temporal deconvolution (thermod.physics.deconv.temporal) on simulated 160×120 recordings with
known truth: the gyro warp, the gain where frames agree, and no loss or ghost where they do not
(a moving hot object, parallax, an FFC step, a gyro gap, new scene at the borders)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support.streams import assert_no_ghost, pan, psnr
from tests.support.streams import stream as stream_of
from thermod.errors import ThermodError
from thermod.physics import kernels
from thermod.physics.calibration import Calibration
from thermod.physics.deconv import DeconvError, Deconvolver
from thermod.physics.deconv.temporal import PastFrame, TemporalDeconvolver, warp, warp_maps, warped_support
from thermod.sim.movers import HotObject

SMALL = Calibration(width=160, height=120, cx=79.5, cy=59.5)
N = 6


def record(motion, calib=SMALL, netd=0.03, seed=3, movers=(), **effects):
    return stream_of(motion, N, calib, netd, seed, movers, **effects)


def run_all(rec, td, gyro=None, offset=False):
    """Restore every frame; returns [(single, temporal, truth)] per frame (`offset`: the truth moved
    by the single estimate's median offset, for a frame after an FFC step)."""
    out = []
    for i in range(len(rec.frames)):
        t = float(rec.t[i])
        gt, gr = gyro(i, t) if gyro else (rec.gyro_t, rec.gyro_rate)
        k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, rec.calibration, t)
        x = td.run(rec.frames[i], k, t, gt, gr)
        truth = rec.extras["truth/frames"][i]
        if offset:
            truth = truth + float(np.median(td.last_single - truth))
        out.append((td.last_single, x, truth))
    return out


def test_gyro_warp_maps_the_previous_truth_onto_the_current_one():
    cal = SMALL.replace(readout_s=0.012)
    rec = record(pan(40), calib=cal, netd=0.0)
    rolling = rec.extras["truth/frames_rolling"]
    t1, t0 = float(rec.t[4]), float(rec.t[2])
    maps = warp_maps(cal, rec.gyro_t, rec.gyro_rate, t1, t0)
    sup = warped_support(maps, rolling[0].shape, inset=4) > 0
    moved = warp(rolling[2], maps)
    err = np.abs(moved - rolling[4])[sup].mean()
    before = np.abs(rolling[2] - rolling[4])[sup].mean()
    assert sup.mean() > 0.4
    assert err < 0.15 * before
    # a global-shutter map of the same pair is worse: the rolling readout is modelled
    g = warp_maps(cal.replace(readout_s=0.0), rec.gyro_t, rec.gyro_rate, t1, t0)
    assert np.abs(warp(rolling[2], g) - rolling[4])[sup].mean() > 1.3 * err


def test_rolling_readout_frames_gain_and_a_wrong_readout_costs_nothing():
    cal = SMALL.replace(readout_s=0.015)
    rec = record(pan(40), calib=cal, seed=12)
    rolling = rec.extras["truth/frames_rolling"]      # each row's sharp view at its read time
    for readout, least in ((0.015, 0.6), (0.0, -0.05)):
        td = TemporalDeconvolver(cal.replace(readout_s=readout), views=4)
        for i in range(N):
            t = float(rec.t[i])
            k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, cal, t)
            x = td.run(rec.frames[i], k, t, rec.gyro_t, rec.gyro_rate)
        gain = psnr(x, rolling[-1]) - psnr(td.last_single, rolling[-1])
        assert gain > least, (readout, gain)
    assert td.last_views == 1       # a global-shutter warp of rolling frames disagrees: every view dropped


def test_agreeing_frames_gain_over_the_single_frame_solve():
    rec = record(pan(25))
    td = TemporalDeconvolver(SMALL, views=4)
    res = run_all(rec, td)
    gains = [psnr(x, t) - psnr(s, t) for s, x, t in res[3:]]
    assert td.last_views == 4
    assert min(gains) > 0.8, gains
    single = Deconvolver()
    k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, SMALL, float(rec.t[-1]))
    np.testing.assert_allclose(res[-1][0], single.run(rec.frames[-1], k), atol=1e-3)


def test_one_view_is_the_single_frame_solve():
    rec = record(pan(25))
    td = TemporalDeconvolver(SMALL, views=1)
    for s, x, _ in run_all(rec, td):
        assert x is s
    assert td.last_views == 1 and not td.history


def _object_track(obj, rec, i, view=N - 1):
    """Where the disc was at frame i's time, in frame `view`'s pixels (world = the first frame's camera)."""
    R = rec.extras["truth/frame_R"][view]
    return obj.at(float(rec.t[0])).centre_px(R, rec.calibration.K, float(rec.t[i]))


def test_a_moving_hot_object_leaves_no_ghost():
    obj = HotObject((40, 40), (700, 300), 5.0, 8.0)    # ~11 px per frame across the panning view
    rec = record(pan(20), movers=(obj,), seed=5)
    td = TemporalDeconvolver(SMALL, views=4)
    res = run_all(rec, td)
    s, x, truth = res[-1]
    assert psnr(x, truth) > psnr(s, truth) - 0.1
    assert_no_ghost(x, s, truth, obj.radius_px, lambda j: _object_track(obj, rec, j), N - 1)


def test_parallax_costs_nothing():
    rec = record(pan(20), parallax=(15.0, 4.0), seed=7)
    td = TemporalDeconvolver(SMALL, views=4)
    for s, x, t in run_all(rec, td)[2:]:
        assert psnr(x, t) > psnr(s, t) - 0.1


def test_an_ffc_step_costs_nothing():
    rec = record(pan(20), ffc_event=(0.05, 0.001, 40.0), fpn=0.03, seed=8)
    frozen = rec.extras["truth/ffc_frozen"]
    td = TemporalDeconvolver(SMALL, views=4)
    res = run_all(rec, td, offset=True)
    after = [i for i in range(N) if rec.t[i] - rec.t[0] > 0.05 and not frozen[i]]
    assert after
    for i in after:
        s, x, t = res[i]
        assert psnr(x, t) > psnr(s, t) - 0.1


def test_a_frame_without_gyro_coverage_is_left_out():
    rec = record(pan(25), seed=9)
    td = TemporalDeconvolver(SMALL, views=4)

    def gyro(i, t):   # the last frame's call gets only 30 ms of gyro: the frames before t − 30 ms drop
        if i < N - 1:
            return rec.gyro_t, rec.gyro_rate
        sel = rec.gyro_t > t - 0.03
        return rec.gyro_t[sel], rec.gyro_rate[sel]

    res = run_all(rec, td, gyro)
    assert td.last_views == 2
    s, x, t = res[-1]
    assert psnr(x, t) > psnr(s, t) - 0.1


def test_new_scene_at_the_borders_comes_from_the_frame_alone():
    rec = record(pan(100, angle=0.0), seed=4)      # pure pitch/yaw mix: ~50 px per frame at 100 °/s
    td = TemporalDeconvolver(SMALL, views=4)
    s, x, t = run_all(rec, td)[-1]
    maps = warp_maps(SMALL, rec.gyro_t, rec.gyro_rate, float(rec.t[-1]), float(rec.t[-2]))
    new = warped_support(maps, t.shape) == 0
    assert 0.05 < new.mean() < 0.6
    assert psnr(x, t, new) > psnr(s, t, new) - 0.1
    assert psnr(x, t) > psnr(s, t) - 0.1


def test_solve_with_an_outside_ring_equals_run():
    rec = record(pan(25), seed=6)
    a, b = TemporalDeconvolver(SMALL, views=3), TemporalDeconvolver(SMALL, views=3)
    ring = []
    for i in range(4):
        t = float(rec.t[i])
        k = kernels.render_thermal_kernel(rec.gyro_t, rec.gyro_rate, SMALL, t)
        x = a.run(rec.frames[i], k, t, rec.gyro_t, rec.gyro_rate)
        y = b.solve(rec.frames[i], k, t, rec.gyro_t, rec.gyro_rate, ring[::-1])   # any order
        ring.append(PastFrame(rec.frames[i].astype(np.float32), k, t))
        np.testing.assert_array_equal(x, y)
    assert a.last_views == 3 and len(a.history) == 2 and not b.history
    with pytest.raises(DeconvError, match="read order"):
        a.push(rec.frames[0], k, float(rec.t[0]))


def test_bad_arguments_are_named():
    with pytest.raises(DeconvError, match="views"):
        TemporalDeconvolver(SMALL, views=0)
    with pytest.raises(DeconvError, match="lam_scale"):
        TemporalDeconvolver(SMALL, lam_scale=-1)
    td = TemporalDeconvolver(SMALL)
    k = kernels.Kernel(np.ones((1, 1), np.float32), (0, 0))
    with pytest.raises(DeconvError, match="frame"):
        td.run(np.zeros((50, 60), np.float32), k, 0.0, np.arange(3.0), np.zeros((3, 3)))


def test_a_hot_object_is_drawn_where_its_track_says():
    obj = HotObject((50, 60), (400, -200), 4.0, 5.0)
    plain = record(pan(10), netd=0.0, seed=2)
    rec = record(pan(10), netd=0.0, seed=2, movers=(obj,))
    for i in (0, N - 1):
        d = rec.extras["truth/frames"][i] - plain.extras["truth/frames"][i]
        yy, xx = np.mgrid[:d.shape[0], :d.shape[1]]
        cx, cy = (d * xx).sum() / d.sum(), (d * yy).sum() / d.sum()
        ex, ey = _object_track(obj, rec, i, view=i)
        assert math.hypot(cx - ex, cy - ey) < 0.3
        assert d.sum() == pytest.approx(math.pi * obj.radius_px ** 2 * obj.delta_k * 40.0, rel=0.03)
    # the blurry frames carry it too, smeared along its path (the blur keeps its total)
    blur = rec.extras["truth/blurry_noiseless"][N - 1] - plain.extras["truth/blurry_noiseless"][N - 1]
    assert blur.sum() == pytest.approx(d.sum(), rel=0.05)
    assert blur.max() < 0.99 * d.max()
    with pytest.raises(ThermodError, match="radius"):
        HotObject((0, 0), (0, 0), radius_px=0.1)
