"""The frame's kernel window is one rule (`thermod.physics.kernels.grids.kernel_span_s`): the daemon's
and offline deblurring's `kernel_window`, the flight import's gyro cut and calibration all read it."""

import pytest

from thermod.physics.calibration import Calibration
from thermod.physics.kernels.grids import kernel_span_s
from thermod.restore.plan import kernel_window
from thermod.restore.settings import DeblurConfig


def test_thermal_window_is_m_tau_plus_readout_everywhere():
    calib = Calibration(tau_s=0.012, readout_s=0.015)
    assert kernel_span_s(calib) == pytest.approx(5 * 0.012 + 0.015)
    assert kernel_window(calib, DeblurConfig(), 2.0) == pytest.approx((2.0 - 0.075, 2.0))
    assert kernel_window(calib, DeblurConfig(m=3.0), 2.0)[0] == pytest.approx(2.0 - 0.036 - 0.015)


def test_photon_window_is_the_exposure_plus_readout():
    calib = Calibration(frame_rate_hz=50.0, readout_s=0.01)
    assert kernel_span_s(calib, kind="photon", exposure_s=0.005) == pytest.approx(0.015)
    d = DeblurConfig(kernel="photon")
    t0, t1 = kernel_window(calib, d, 1.0)
    assert t1 == 1.0 and 1.0 - t0 == pytest.approx(kernel_span_s(calib, kind="photon"))
