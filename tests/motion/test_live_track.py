"""No gyro, live: the camera's rotation measured frame by frame from the stream itself
(`thermod.motion.live.LiveTrack`, `drivers/video_gyro.py`), on simulated streams whose true rate is
known."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from thermod.drivers.video_gyro import VideoGyro
from thermod.motion.live import LEAD_SAMPLES, LiveTrack
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim import synth

pytestmark = pytest.mark.heavy(1)

CALIB = Calibration(width=160, height=128, fx=183.0, fy=183.0, cx=79.5, cy=63.5, frame_rate_hz=50.0,
                    tau_s=0.008, readout_s=0.006)
# the rates' RMS error over the true rates' RMS under a 1 Hz sway: measured 0.024
RATE_TOL = 0.06


@pytest.fixture(scope="module")
def swaying():
    motion = mo.Sway(amp=(4 * mo.DEG, 5 * mo.DEG, 2 * mo.DEG), period_s=1.0)
    rec = synth.simulate("texture", motion, seconds=1.0, calib=CALIB, effects={"netd": 0.03}, seed=5)
    return rec, motion


def run(track: LiveTrack, frames, times):
    out = [track.push(f, t) for f, t in zip(frames, times, strict=True)]
    return [s for s in out if s is not None]


def test_rates_follow_the_true_rotation_one_frame_behind(swaying):
    rec, motion = swaying
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, rec.frames, rec.t)
    assert tr.counts["measured"] == len(rec.frames) - 1 and tr.counts["untracked"] == tr.counts["cut"] == 0
    t = np.concatenate([s.t for s in got])
    w = np.concatenate([s.rate for s in got])
    assert np.all(np.diff(t) > 0) and not any(s.gap_before for s in got)
    np.testing.assert_allclose(np.diff(t), 1e-3, rtol=1e-6)          # one clock, evenly sampled
    # every frame but the newest has its samples through its read time (one frame of latency)
    assert t[-1] == pytest.approx(rec.t[-2] + LEAD_SAMPLES * 1e-3, abs=1e-3)
    truth = motion.omega(t - rec.t[0])
    keep = t > rec.t[2]
    err = math.sqrt(np.mean((w[keep] - truth[keep]) ** 2) / np.mean(truth[keep] ** 2))
    assert err < RATE_TOL
    assert math.isfinite(tr.last_sigma_rad_s) and tr.last_sigma_rad_s > 0
    assert tr.overlay.mask is None                                    # nothing static in this stream


def with_logo(frames) -> list[np.ndarray]:
    """A burnt-in logo (bright text in a frame on a dark box), static, top-left, as a camera draws it."""
    out = []
    for f in frames:
        f = np.asarray(f, np.float32).copy()
        lo, hi = (float(v) for v in np.percentile(f, (1, 99.5)))
        ink = np.zeros(f.shape, np.uint8)
        cv2.rectangle(ink, (4, 4), (70, 26), 255, 1)
        cv2.putText(ink, "THRM", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, 255, 1, cv2.LINE_AA)
        f[4:27, 4:71] = lo
        a = ink.astype(np.float32) / 255
        out.append(f * (1 - a) + hi * a)
    return out


def test_a_static_logo_is_found_and_left_out(swaying):
    # its strokes are the stream's strongest corners: taken, they pulled the rates' error from 0.024
    # to 0.29 of the rates' RMS (2 s of this sway); found and left out, 0.027
    rec, motion = swaying
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, with_logo(rec.frames), rec.t)
    mask = tr.overlay.mask
    assert mask is not None and 0 < tr.overlay.fraction < 0.1
    ys, xs = np.nonzero(mask)
    assert xs.max() <= 75 and ys.max() <= 31                     # where it was drawn, and nowhere else
    t = np.concatenate([s.t for s in got])
    w = np.concatenate([s.rate for s in got])
    truth = motion.omega(t - rec.t[0])
    keep = t > rec.t[2 + 5]                                      # found after its first look, 5 pairs in
    err = math.sqrt(np.mean((w[keep] - truth[keep]) ** 2) / np.mean(truth[keep] ** 2))
    assert err < RATE_TOL


def test_the_video_source_hands_the_logo_to_the_solve_at_the_frames_size(swaying):
    rec, _ = swaying
    src = VideoGyro(CALIB)
    src.start()
    assert src.overlay() is None
    for f, t in zip(with_logo(rec.frames[:20]), rec.t[:20], strict=True):
        src.offer(f, t)
        src.poll(0.1)
    src.stop()
    got = src.overlay()
    assert got is not None and src.overlay() is got                  # the same objects while it holds
    mask, filled = got
    assert mask.shape == filled.shape == (CALIB.height, CALIB.width) and mask.dtype == bool
    ys, xs = np.nonzero(mask)
    assert xs.max() <= 80 and ys.max() <= 34 and mask[4:27, 4:71].mean() > 0.3   # the logo's box
    assert np.all(filled[mask])                                       # the solve fills at least the mask


def test_a_frame_without_texture_leaves_a_flagged_hole_not_invented_motion(swaying):
    rec, _ = swaying
    frames = [np.asarray(f, np.float32) for f in rec.frames[:20]]
    frames[10] = np.full_like(frames[10], float(np.median(frames[10])))       # a lens cap, a blank frame
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, frames, rec.t[:20])
    assert tr.counts["untracked"] + tr.counts["cut"] == 2                 # into and out of the blank
    t = np.concatenate([s.t for s in got])
    gaps = [s for s in got if s.gap_before]
    assert len(gaps) == 1
    # no sample inside the frames the blank touches: from frame 9's lagged read to frame 11's
    inside = (t > rec.t[9] - CALIB.tau_s) & (t < rec.t[11] - CALIB.tau_s - CALIB.readout_s)
    assert not inside.any()


def test_a_repeated_frame_is_registered_across_not_read_as_a_stop(swaying):
    rec, motion = swaying
    frames = list(rec.frames[:16])
    times = list(rec.t[:16])
    frames[8] = frames[7]                    # the camera sent frame 7 again in frame 8's slot
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, frames, times)
    assert tr.counts["duplicate"] == 1 and tr.counts["untracked"] == 0
    t = np.concatenate([s.t for s in got])
    w = np.concatenate([s.rate for s in got])
    near = (t > times[7]) & (t < times[9])
    truth = motion.omega(t[near] - rec.t[0])
    # a stop would read ~0 here; across the repeat the rate stays the motion's
    assert np.sqrt(np.mean(np.sum(w[near] ** 2, 1))) > 0.6 * np.sqrt(np.mean(np.sum(truth ** 2, 1)))


def test_the_video_source_hands_the_daemon_camera_frame_rates(swaying):
    rec, _ = swaying
    calib = CALIB.replace(time_offset_s=0.003, bias_rad_s=(0.01, 0.0, 0.0), gyro_lowpass_hz=80.0)
    calib = VideoGyro(calib).calibration_for(calib)
    assert calib.time_offset_s == 0 and calib.bias_rad_s == (0.0, 0.0, 0.0) and calib.gyro_lowpass_hz == 0
    np.testing.assert_array_equal(calib.gyro_to_camera_matrix, np.eye(3))
    src = VideoGyro(calib)
    src.start()
    assert src.poll(0.01) is None                        # nothing offered yet: no samples, no block
    batches = []
    for f, t in zip(rec.frames[:6], rec.t[:6], strict=True):
        src.offer(f, t)
        b = src.poll(0.1)
        if b is not None:
            batches.append(b)
    src.stop()
    assert len(batches) == 5 and batches[0].seq == 0
    assert all(b2.seq == b1.seq + len(b1) for b1, b2 in zip(batches, batches[1:], strict=False))
    st = src.stats()
    assert st["motion_source"] == "video" and st["frames_offered"] == 6
    assert st["samples"] == sum(map(len, batches))
    # each frame offered and registered in turn: its delay is its own registration's, a few ms
    assert 0 < st["register_delay_ms_p50"] <= st["register_delay_ms_p99"] < 1000


def corners_failing(pairs: tuple[int, ...], dense: bool = False) -> LiveTrack:
    """A track whose corners fail on the `pairs`-th measured pairs (1-based: 10 is the pair into frame
    10), and every pixel with them unless `dense`."""
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    measure, calls = tr.reg.measure, []

    def failing(*a, **k):
        calls.append(1)
        return None if len(calls) in pairs else measure(*a, **k)

    tr.reg.measure = failing
    if not dense:
        tr.reg.measure_dense = lambda *a, **k: None
    return tr


def test_one_pair_that_cannot_be_registered_is_bridged_by_its_neighbours(swaying):
    rec, motion = swaying
    tr = corners_failing((10,))              # the pair into frame 10 cannot be registered
    got = run(tr, rec.frames[:20], rec.t[:20])
    assert tr.counts["untracked"] == 1 and tr.counts["bridged"] == 1
    assert not any(s.gap_before for s in got)
    t = np.concatenate([s.t for s in got])
    w = np.concatenate([s.rate for s in got])
    sig = np.concatenate([s.sigma for s in got])
    np.testing.assert_allclose(np.diff(t), 1e-3, rtol=1e-6)             # no sample missing, none twice
    # no samples for frame 9 until frame 11 came: the batch after the failure reaches frame 10's time
    assert len(got) == 18 and got[8].t[-1] < rec.t[9] < got[9].t[-1]
    inside = (t > rec.t[9] - CALIB.tau_s) & (t < rec.t[10] - CALIB.tau_s)
    truth = motion.omega(t[inside] - rec.t[0])
    err = math.sqrt(np.mean((w[inside] - truth) ** 2) / np.mean(truth ** 2))
    assert err < 3 * RATE_TOL
    assert np.median(sig[inside]) > np.median(sig[~inside])             # and it says it is less sure there


def test_a_pair_whose_corners_disagree_is_registered_by_every_pixel_without_a_wait(swaying):
    # the simulated payload's low-texture turns (80 °/s, 10 working px a frame) lost 2 % of their pairs
    # to the corners, each bridged a period late; every pixel (ECC) measured them to 0.4–1 px
    rec, motion = swaying
    tr = corners_failing((10,), dense=True)
    got = run(tr, rec.frames[:20], rec.t[:20])
    assert tr.counts["dense"] == 1 and tr.counts["untracked"] == tr.counts["bridged"] == 0
    # frame 9's samples come with frame 10, as with every pair: no period of waiting for frame 11
    assert len(got) == 19 and got[9].t[-1] == pytest.approx(rec.t[9] + LEAD_SAMPLES * 1e-3, abs=1e-3)
    t = np.concatenate([s.t for s in got])
    w = np.concatenate([s.rate for s in got])
    inside = (t > rec.t[9] - CALIB.tau_s) & (t < rec.t[10] - CALIB.tau_s)
    truth = motion.omega(t[inside] - rec.t[0])
    assert math.sqrt(np.mean((w[inside] - truth) ** 2) / np.mean(truth ** 2)) < 2 * RATE_TOL


def test_the_dense_fit_measures_a_rotation_and_refuses_a_blank_frame(swaying):
    rec, motion = swaying
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    reg = tr.reg
    a, b = tr.prepare(rec.frames[9]), tr.prepare(rec.frames[10])
    fit = reg.measure_dense(a, b)                               # from no prediction at all
    corners = reg.measure(a, b, bands=False)
    assert fit is not None and fit.n_features == 0 and np.all(np.isnan(fit.band_rotvec))
    np.testing.assert_allclose(fit.rotvec, corners.rotvec, atol=1.5 / reg.f_px)     # within 1.5 working px
    assert 0 < fit.noise_rad < 5 / reg.f_px
    blank = np.full_like(b, 128)
    assert reg.measure_dense(a, blank) is None


def test_two_pairs_in_a_row_leave_a_hole(swaying):
    rec, _ = swaying
    tr = corners_failing((10, 11))
    got = run(tr, rec.frames[:20], rec.t[:20])
    assert tr.counts["untracked"] == 2 and tr.counts["bridged"] == 0
    assert [s.gap_before for s in got].count(True) == 1


def test_lost_frames_leave_a_hole_one_lost_frame_does_not(swaying):
    rec, motion = swaying
    keep = [k for k in range(30) if not 10 <= k <= 13]        # four frames lost: an interval of 5 periods
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, [rec.frames[k] for k in keep], rec.t[keep])
    assert tr.counts["gap"] == 1 and [s.gap_before for s in got].count(True) == 1
    t = np.concatenate([s.t for s in got])
    assert not ((t > rec.t[9]) & (t < rec.t[14] - CALIB.tau_s - CALIB.readout_s)).any()
    one = [k for k in range(30) if k != 12]                   # one frame lost: measured across
    tr = LiveTrack(CALIB.intrinsics, tau_s=CALIB.tau_s, readout_s=CALIB.readout_s)
    got = run(tr, [rec.frames[k] for k in one], rec.t[one])
    assert tr.counts["gap"] == 0 and not any(s.gap_before for s in got)
    assert tr.counts["measured"] == len(one) - 1


@settings(max_examples=60, deadline=None)
@given(st.integers(8, 200), st.integers(8, 150), st.integers(0, 2**32 - 1),
       st.sampled_from(["noise", "flat", "same"]),
       st.sampled_from([None, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), (0.05, -0.02, 0.1), (1e6, 0.0, 0.0)]),
       st.sampled_from([None, "all", "none", "half"]))
@example(200, 8, 0, "same", None, None)           # a strip whose border leaves no row for the grid
def test_the_dense_fit_of_any_pair_is_a_finite_rotation_or_none(w, h, seed, kind, predicted, exclude):
    """Any working size, picture, prediction and overlay: a finite rotation with a finite noise, or
    None; never an exception or a numpy warning (a strip too thin for its grid, a flat pair, a warp to
    infinity)."""
    import warnings

    from thermod.motion.picture import PairRegistrar

    c = Calibration(width=w, height=h, fx=1.2 * w, fy=1.2 * w, cx=(w - 1) / 2, cy=(h - 1) / 2)
    reg = PairRegistrar(c.intrinsics, work_width=160)
    H, W = reg.work.height, reg.work.width
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 256, (H, W), dtype=np.uint8) if kind != "flat" else np.full((H, W), 128, np.uint8)
    b = a.copy() if kind != "noise" else rng.integers(0, 256, (H, W), dtype=np.uint8)
    mask = {None: None, "all": np.ones((H, W), bool), "none": np.zeros((H, W), bool),
            "half": np.arange(W)[None, :].repeat(H, 0) < W // 2}[exclude]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = reg.measure_dense(a, b, predicted=None if predicted is None else np.array(predicted),
                                exclude=mask)
    if fit is not None:
        assert np.all(np.isfinite(fit.rotvec)) and math.isfinite(fit.noise_rad) and fit.noise_rad > 0
