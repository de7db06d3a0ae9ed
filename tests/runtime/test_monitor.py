"""The live calibration monitor on the simulated payload (daemon in-process, 160×120 frames) with a gyro
bias and a time offset that drift during the run: the estimate converges to the truth, health carries
it, and apply = true moves the calibration in force towards the truth without raising the residual;
with a camera whose τ is not the configuration's, the τ estimate converges to the camera's."""

import time

import numpy as np
import pytest

from tests.support.endpoints import private_endpoint
from thermod.calib.live import TAU_MAX_REL_SIGMA
from thermod.runtime import config
from thermod.runtime.daemon import Daemon
from thermod.sim.gyro_model import GyroDrift

pytestmark = pytest.mark.slow

DRIFT = GyroDrift(bias_0=(0.01, -0.01, 0.0), bias_rate=(0.002, 0.002, 0.0), offset_0=0.003,
                  offset_rate=0.0005, ramp_s=5.0)
# rad/s on the x, y axes (the roll axis is weakly seen: its σ is reported). The estimate's stated σ
# understates its error here: over 17 runs on 2026-11-28 the x, y errors had RMS 4.5 and 2.7 mrad/s
# against a stated σ of 1–4 (a window-dependent model error the jackknife cannot see; open), so the
# bound is the measured spread, not 4σ alone
BIAS_TOL = 0.007
# rad/s: an estimate this uncertain on x, y is of no use (σ holds the offset's model delay error as it
# drags the bias: 2.6–3.3 mrad/s measured beside the suite's other worker)
BIAS_SIGMA_MAX = 0.004
OFFSET_TOL = 0.0012       # s
# The simulated stream repeats every loop_s; within the monitor's windows (4 s motion, 12 s τ) a loop
# of 2 s shows each pair up to 6 times, so the block jackknife's blocks share pairs and σ comes out low.
LOOP_S = 12.0
FULL_WINDOW = 0.9         # of the monitor's motion window (4 s)
TAU_PATCHES = 48          # the τ test waits for this many patch pairs (quiet host: 70–100 in 12 s)



def _estimate(d):
    return d.health()["calibration"]["estimate"]


@pytest.fixture(autouse=True)
def monitor_niceness(monkeypatch):
    """The niceness the monitor thread asks for, recorded, not applied: these tests check what the
    estimator finds, and at nice 19 beside two busy loops it measured no τ pair in 36 s (its priority
    is a deployment property, asserted as a request here). Its `cpu_share` cap still applies."""
    asked = []
    monkeypatch.setattr("thermod.runtime.monitor.os.setpriority",
                        lambda which, who, prio: asked.append((which, who, prio)))
    # likewise its pause while the pipeline drops frames for overload (`Pipeline.short_of_cpu`, tested
    # in test_cpu_meter): on a loaded test host it would starve the estimator these tests check
    monkeypatch.setattr("thermod.runtime.pipeline.Pipeline.short_of_cpu", lambda self, hold_s=0.0: False)
    return asked


def run(apply: bool, seconds: float, drift=DRIFT, until=None, **extra):
    """The daemon for `seconds`, then on until `until(daemon)` holds (checked each second), for at most
    3 × `seconds` in all: a monitor starved by a loaded host (it runs at nice 19, within 10 % of a
    core) takes longer, and what it finds is what the tests check, not how fast."""
    opts = {"publish.endpoint": private_endpoint(), "deblur.method": "wiener",
            "calibration.width": 160, "calibration.height": 120, "calibration.fx": 366.0,
            "calibration.fy": 366.0, "monitor.apply": apply, "pipeline.workers": 1, "sim.loop_s": LOOP_S,
            "monitor.cpu_share": 0.10, **extra}
    d = Daemon(config.load(None, opts))
    d.payload.drift = drift
    d.start()
    t0 = last_check = time.monotonic()
    try:
        while True:
            d.tick()
            time.sleep(0.05)
            now = time.monotonic()
            if now - t0 >= 3 * seconds:
                break
            if now - t0 >= seconds and now - last_check >= 1.0:
                last_check = now
                if until is None or until(d):
                    break
        h = d.health()
        truth = d.payload.true_calibration(time.monotonic() - 2.0)
    finally:
        d.stop()
    return d, h, truth


def _usable(d):
    """An estimate from a full motion window (at least `FULL_WINDOW` of the monitor's window spanned)
    whose x, y bias σ is below BIAS_SIGMA_MAX (a starved monitor fits fewer pairs per window: at NETD
    50 mK σ was 1.8–2.1 mrad/s on a quiet host, up to 3.4 beside a busy loop). The wait is on the window
    first: stopping at the first σ that happens to be small, from a part-filled window, picks the fits
    whose σ came out too small (an 8-block jackknife's σ has 7 degrees of freedom)."""
    e, est = _estimate(d), d.monitor.estimator
    span = est.span()
    return (e is not None and span is not None and span[1] - span[0] >= FULL_WINDOW * est.window_s
            and max(e["gyro_bias_rad_s_sigma"][:2]) < BIAS_SIGMA_MAX)


def _tau_fed(d):
    """An estimate with τ from at least `TAU_PATCHES` patch pairs (a starved monitor measures fewer per
    second). The wait is on the count, never on σ: stopping at the first σ that happens to be small
    would pick the estimates whose σ is too small."""
    e = _estimate(d) or {}
    return e.get("tau_s") is not None and e["n_tau_patches"] >= TAU_PATCHES


def test_estimate_converges_to_the_drifting_truth():
    d, h, truth = run(apply=False, seconds=12.0, until=_usable)
    cal = h["calibration"]
    e = cal["estimate"]
    assert e is not None, cal["monitor"]
    assert cal["source"] == "config" and cal["applied"] == d.cfg.calibration.as_dict()
    b, b_true = np.array(e["gyro_bias_rad_s"]), np.array(truth.bias_rad_s)
    sigma = np.array(e["gyro_bias_rad_s_sigma"])[:2]
    # A starved monitor (low priority on a loaded host) fits fewer pairs and says so in σ: the error is
    # held to the stated uncertainty (a 7-dof jackknife: 4σ), never looser than BIAS_TOL (OFFSET_TOL:
    # a bare clone's suite beside other work missed 1.2 ms by 0.06 at a stated σ of 0.45 ms).
    assert np.all(sigma < BIAS_SIGMA_MAX), e
    assert np.all(np.abs(b - b_true)[:2] < np.maximum(BIAS_TOL, 4.0 * sigma)), (b, b_true, e)
    assert abs(e["time_offset_s"] - truth.time_offset_s) < max(OFFSET_TOL, 4.0 * e["time_offset_s_sigma"]), \
        (e, truth.time_offset_s)
    assert all(s > 0 for s in e["gyro_bias_rad_s_sigma"]) and e["time_offset_s_sigma"] > 0
    # τ's σ is a 16-block jackknife (15 dof): beyond 3σ 0.9 % of the time, one CI run in a hundred
    assert e["tau_s"] is None or abs(e["tau_s"] - truth.tau_s) < 4 * e["tau_s_sigma"], e
    assert d.pipeline.calib == d.cfg.calibration                 # apply = false: nothing changed
    share = cal["monitor"]["cpu_share"]
    assert share is not None and share <= 0.10 * 1.5               # the budget, with scheduling slack


def _bias_moved(d) -> bool:
    """A change that moved the bias (a first change may move only the offset: each part changes only
    where it is significant, and a starved monitor's bias σ reaches that later)."""
    return any("bias_rad_s" in c and c["bias_rad_s"][0] != c["bias_rad_s"][1] for c in d.monitor.changes)


def test_apply_moves_the_calibration_towards_the_truth():
    d, h, truth = run(apply=True, seconds=12.0, until=_bias_moved)
    assert d.monitor.changes, h["calibration"]["monitor"]
    for c in d.monitor.changes:                                    # never a change that raised the residual
        assert "residual_px" in c or "tau_misfit" in c, c
        assert "residual_px" not in c or c["residual_px"][1] < c["residual_px"][0]
        assert "tau_misfit" not in c or c["tau_misfit"][1] < c["tau_misfit"][0]
    applied = d.pipeline.calib
    assert h["calibration"]["source"] == "monitor"
    before = abs(d.cfg.calibration.time_offset_s - truth.time_offset_s)
    assert abs(applied.time_offset_s - truth.time_offset_s) < before
    err_after = np.linalg.norm((np.array(applied.bias_rad_s) - truth.bias_rad_s)[:2])
    err_before = np.linalg.norm((np.array(d.cfg.calibration.bias_rad_s) - truth.bias_rad_s)[:2])
    assert err_after < err_before, (applied.bias_rad_s, truth.bias_rad_s)


def test_tau_estimate_converges_to_the_camera_s(monitor_niceness):
    """The simulated camera's τ is 12 ms, the configuration says 8 ms (``[sim] tau_s``): the monitor's
    τ estimate finds the camera's within its σ, on the camera's side of the configuration's."""
    # a quarter of a core: this test checks what the τ estimate finds, and on the 2-core CI host (plain
    # reference K&F 600–980 ms) the default share measured 0–10 of the 24 patch pairs it needs in 36 s
    d, h, truth = run(apply=False, seconds=12.0, drift=None, until=_tau_fed,
                      **{"sim.tau_s": 0.012, "monitor.cpu_share": 0.25})
    assert d.cfg.calibration.tau_s == 0.008 and truth.tau_s == pytest.approx(0.012)
    e = h["calibration"]["estimate"]
    assert e is not None, h["calibration"]["monitor"]
    assert e["tau_s"] is not None, e["notes"]
    tau, sigma = e["tau_s"], e["tau_s_sigma"]
    # the estimator withholds τ above TAU_MAX_REL_SIGMA (at NETD 50 mK: σ 7–25 % of τ in 12 s)
    assert 0 < sigma <= TAU_MAX_REL_SIGMA * tau, e
    # σ is a 16-block jackknife with a 5 % floor, and it does not track a run's own error: over 58 runs
    # of this test here (benchmarks/results/monitor.md, "τ's σ in this test") the error / σ had RMS
    # 0.92–1.21 and reached 2.93, and in CI 3.7 (τ 8.62 ± 0.92 ms), so the bound is 4σ, as in the
    # drifting-truth test above
    assert abs(tau - truth.tau_s) < 4 * sigma, e
    assert tau > d.cfg.calibration.tau_s, e                      # away from the configuration's
    assert e["n_tau_patches"] >= 24 and h["calibration"]["monitor"]["tau_patch_pairs"] > 0
    assert d.pipeline.calib == d.cfg.calibration                 # apply = false: nothing changed
    assert [prio for *_, prio in monitor_niceness] == [19]      # the thread asked for the lowest priority
