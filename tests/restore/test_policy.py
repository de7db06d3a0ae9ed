"""thermod.restore.policy: the one per-frame rule set, each rule on its own."""

import dataclasses

import numpy as np
import pytest

from thermod.physics.calibration import Calibration
from thermod.restore.policy import START_COVERAGE, PassThrough, Plan, plan_frame
from thermod.restore.settings import DeblurConfig

CAL = Calibration(width=160, height=120, fx=183.0, fy=183.0, cx=79.5, cy=59.5)
DEB = DeblurConfig(mode="uniform")
T = 1.0


def gyro(t0=0.5, t1=1.5, rate_hz=1000.0):
    t = np.arange(t0, t1, 1.0 / rate_hz)
    r = np.zeros((len(t), 3), np.float32)
    r[:, 1] = np.deg2rad(40.0)
    return t, r


def test_a_covered_frame_is_planned():
    t, r = gyro()
    p = plan_frame(T, t, r, CAL, DEB)
    assert isinstance(p, Plan) and not p.start_partial and p.info["coverage"] >= DEB.min_coverage
    assert p.kernel.weights.shape == p.info["kernel_size"]


@pytest.mark.parametrize("kw, reason", [
    ({"deblur": dataclasses.replace(DEB, enabled=False)}, "disabled"),
    ({"ffc": True}, "ffc"),
    ({"gap": True}, "gyro_gap"),
])
def test_rules_that_need_no_kernel(kw, reason):
    t, r = gyro()
    deblur = kw.pop("deblur", DEB)
    p = plan_frame(T, t, r, CAL, deblur, **kw)
    assert isinstance(p, PassThrough) and p.reason == reason and p.kernel is None


def test_a_hole_in_the_window_is_a_gap_and_one_outside_is_not():
    t, r = gyro()
    inside = (t > T - 0.02) & (t < T - 0.01)                 # 10 ms missing within 5τ of the frame
    assert plan_frame(T, t[~inside], r[~inside], CAL, DEB).reason == "gyro_gap"
    outside = (t > T - 0.3) & (t < T - 0.2)
    assert isinstance(plan_frame(T, t[~outside], r[~outside], CAL, DEB), Plan)


def test_no_samples_is_incomplete_online_and_offline_when_the_gyro_is_down():
    t, r = gyro(t1=0.9)                                       # all before the window
    assert plan_frame(T, t, r, CAL, DEB).reason == "gyro_incomplete"
    assert plan_frame(T, t, r, CAL, DEB, online=False).reason == "gyro_offline"


def test_a_short_window_passes_through_with_its_kernel_unless_the_stream_just_began():
    t, r = gyro()
    late = t < T - 0.003                                      # the newest 3 ms missing
    p = plan_frame(T, t[late], r[late], CAL, DEB)
    assert isinstance(p, PassThrough) and p.reason == "gyro_incomplete" and p.kernel is not None
    assert "gyro coverage" in str(p) and p.info["coverage"] < DEB.min_coverage
    # the stream began 25 ms before the frame: the comet's oldest tail is missing (e^−25/8: 4 %)
    start = t >= T - 0.025
    p = plan_frame(T, t[start], r[start], CAL, DEB)
    assert isinstance(p, Plan) and p.start_partial and START_COVERAGE <= p.info["coverage"] < 0.99
    # 10 ms before: 29 % missing, beyond the start rule
    start = t >= T - 0.010
    assert plan_frame(T, t[start], r[start], CAL, DEB).reason == "gyro_incomplete"


def test_a_kernel_that_cannot_be_rendered_is_a_kernel_error():
    t, r = gyro()

    def broken(*a):
        raise FloatingPointError("overflow in the path")

    p = plan_frame(T, t, r, CAL, DEB, renderer=broken)
    assert p.reason == "kernel_error" and "FloatingPointError: overflow in the path" in p.detail


def test_choose_gets_the_needed_grid_and_the_floor_and_is_rendered():
    t, r = gyro()
    r[:, 2] = np.deg2rad(200.0)                               # a fast roll: a grid is needed
    asked = []
    p = plan_frame(T, t, r, CAL, DeblurConfig(), choose=lambda needed, floor: asked.append((needed, floor))
                   or (2, 3))
    (needed, floor), = asked
    assert needed[0] * needed[1] > 1 and floor[0] * floor[1] <= needed[0] * needed[1]
    assert isinstance(p, Plan) and p.deblur.mode == "grid" and tuple(p.kernel.grid) == (2, 3)
