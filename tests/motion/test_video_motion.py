"""No gyro: the camera's rotation estimated from the pictures (`thermod.motion.track`) and written as
the recording's gyro (`thermod.ingest.video_only`, `thermod import VIDEO` without --gyro), on small
simulated AGC'd H.264 flights whose true rate is known."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from thermod.ingest.video_only import VideoImportError, import_video
from thermod.io import recording, video
from thermod.motion.track import TrackError, estimate_track
from thermod.physics.calibration import Calibration
from thermod.sim.flight_video import simulate_flight
from thermod.sync.gyro import cumulative_rotation

pytestmark = pytest.mark.heavy(1)

WIDTH, HEIGHT, FPS, TAU = 160, 128, 30.0, 0.008
# RMS error of the interval rates over the true rates' RMS: measured 0.029 (0.034 with a logo; 0.096 with
# the logo not masked, 0.106 with the blur's lag not modelled)
RATE_TOL = 0.06


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("clip")
    sim = simulate_flight(d, seconds=2.0, log_seconds=5.0, width=WIDTH, height=HEIGHT, fps=FPS, tau_s=TAU,
                          formats=("gcsv",), seed=4, mount=0, video_start_s=1.0,
                          body_rms_deg_s=(30.0, 25.0, 12.0))
    vf = video.read_video(sim.video_path)
    c = sim.recording.calibration
    cam = Calibration().replace(width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
                                frame_rate_hz=FPS, tau_s=TAU)
    return sim, vf, cam


def true_interval_rate(sim, t: np.ndarray, lag_s: float) -> np.ndarray:
    """The true camera-frame mean rate over each interval of `t` − lag (rad/s)."""
    tv = sim.body_t_log - sim.log_offset_s
    G = cumulative_rotation(tv, sim.body_rate @ sim.camera_from_body.T)
    Gf = np.stack([np.interp(t - lag_s, tv, G[:, a]) for a in range(3)], axis=1)
    return np.diff(Gf, axis=0) / np.diff(t)[:, None]


def rel_error(est: np.ndarray, true: np.ndarray) -> float:
    ok = np.all(np.isfinite(est), axis=1)
    return float(np.sqrt(np.mean((est[ok] - true[ok]) ** 2)) / np.sqrt(np.mean(true[ok] ** 2)))


def with_logo(frames: np.ndarray) -> np.ndarray:
    """A burnt-in logo (white text in a white frame on black), static, top-left, drawn after the AGC."""
    out = frames.copy()
    for f in out:
        cv2.rectangle(f, (4, 4), (70, 26), 0, -1)
        cv2.rectangle(f, (4, 4), (70, 26), 255, 1)
        cv2.putText(f, "THRM", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, 255, 1, cv2.LINE_AA)
    return out


def test_estimated_rate_matches_the_truth(clip):
    sim, vf, cam = clip
    track = estimate_track(vf.frames, vf.t, cam.intrinsics, tau_s=TAU)
    true = true_interval_rate(sim, vf.t, track.lag_s)
    assert track.known.all() and track.overlay is None
    err = rel_error(track.rate_at_frames(), true)
    assert err < RATE_TOL, f"rate error {err:.3f} of the true RMS"
    # the registered positions lag the read times by the blur's centroid: unshifted truth fits worse
    assert rel_error(track.rate_at_frames(), true_interval_rate(sim, vf.t, 0.0)) > 2 * err
    # the gyro it writes: its integral over each interval is the interval's rotation
    gt, gr, gs = track.gyro(1000.0, lead_s=0.05, tail_s=0.02)
    assert np.all(np.diff(gt) > 0) and np.all(gs > 0)
    G = cumulative_rotation(gt, gr)
    k = np.arange(1, len(vf.t) - 2)
    at = np.stack([np.interp(vf.t[k] - track.lag_s, gt, G[:, a]) for a in range(3)], axis=1)
    np.testing.assert_allclose(np.diff(at, axis=0), track.rotvec[k[:-1]], atol=2e-4)


def written_interval_rate(gt, gr, t: np.ndarray, lag_s: float) -> np.ndarray:
    """A written gyro's mean rate over each interval of `t` − lag (rad/s)."""
    G = cumulative_rotation(gt, gr.astype(np.float64))
    Gf = np.stack([np.interp(t - lag_s, gt, G[:, a]) for a in range(3)], axis=1)
    return np.diff(Gf, axis=0) / np.diff(t)[:, None]


def test_a_rolling_readout_places_each_band_at_its_own_time(tmp_path):
    readout = 0.025
    sim = simulate_flight(tmp_path, seconds=2.0, log_seconds=5.0, width=WIDTH, height=HEIGHT, fps=FPS,
                          tau_s=TAU, formats=("gcsv",), seed=4, mount=0, video_start_s=1.0,
                          body_rms_deg_s=(30.0, 25.0, 12.0), effects={"rolling_readout": readout})
    vf = video.read_video(sim.video_path)
    c = sim.recording.calibration
    track = estimate_track(vf.frames, vf.t, c.intrinsics, tau_s=TAU, readout_s=readout)
    assert track.lag_s == pytest.approx(TAU + 0.5 * readout) and len(track.bands["t0"]) > 2 * len(vf.t)
    gt, gr, _ = track.gyro(1000.0, lead_s=0.06, tail_s=0.03)
    t = vf.t[2:-2]          # away from the held ends
    err = rel_error(written_interval_rate(gt, gr, t, track.lag_s), true_interval_rate(sim, t, track.lag_s))
    assert err < RATE_TOL, err
    # measured 0.035; one rotation per frame at one mean lag (the whole frame's corners): 0.13
    one_lag = rel_error(track.rate_at_frames(), true_interval_rate(sim, vf.t, track.lag_s))
    assert one_lag > 2 * err, (one_lag, err)
    # a cut two frames in leaves a stretch too short for the banded fit: its frame rotations serve
    frames = vf.frames.copy()
    frames[2:] = np.roll(frames[2:, ::-1, ::-1], WIDTH // 2, axis=2)
    cut = estimate_track(frames, vf.t, c.intrinsics, tau_s=TAU, readout_s=readout)
    assert cut.flagged()["cut"] + cut.flagged()["untracked"] == [2]
    gt, gr, _ = cut.gyro(1000.0, lead_s=0.06, tail_s=0.03)
    assert np.all(np.isfinite(gr)) and not ((gt > vf.t[1] + 0.03) & (gt < vf.t[2] - cut.lag_s - 0.005)).any()


def test_a_static_logo_does_not_pull_the_estimate_to_zero(clip):
    sim, vf, cam = clip
    frames = with_logo(vf.frames)
    track = estimate_track(frames, vf.t, cam.intrinsics, tau_s=TAU)
    assert track.overlay is not None
    ys, xs = np.nonzero(track.overlay)
    s = track.work_scale
    # found where it was drawn (working pixels), and nowhere else
    assert xs.min() / s >= 0 and xs.max() / s <= 80 and ys.max() / s <= 34, (xs.max() / s, ys.max() / s)
    true = true_interval_rate(sim, vf.t, track.lag_s)
    assert rel_error(track.rate_at_frames(), true) < RATE_TOL
    # the motion is measured, not zero: the estimate's RMS is the truth's within the tolerance
    ratio = np.sqrt(np.nanmean(track.rate_at_frames() ** 2) / np.mean(true ** 2))
    assert abs(ratio - 1) < RATE_TOL


def test_the_import_writes_the_logo_mask_for_deblurring(clip, tmp_path):
    sim, vf, cam = clip
    path = video.write_video(tmp_path / "logo.mp4", with_logo(vf.frames), vf.t - vf.t[0], crf=18)
    out = import_video(path, tmp_path / "logo.h5", cam).path
    with recording.Reader(out) as r:
        mask = r.overlay()
    assert mask is not None and mask.shape == (HEIGHT, WIDTH)
    ys, xs = np.nonzero(mask)
    # the printed box (4..70, 4..26) and its halo, nothing else
    assert xs.max() <= 80 and ys.max() <= 34 and mask[4:27, 4:71].mean() > 0.3, (xs.max(), ys.max())


def test_a_duplicated_frame_and_a_scene_cut_are_flagged_and_invent_no_motion(clip):
    from thermod.restore.policy import PassThrough, plan_frame
    from thermod.restore.settings import DeblurConfig

    sim, vf, cam = clip
    frames = vf.frames.copy()
    dup, cut = 20, 40
    frames[dup] = frames[dup - 1]
    # after the cut another scene: the same clip turned upside down and shifted by half a frame
    frames[cut:] = np.roll(frames[cut:, ::-1, ::-1], WIDTH // 2, axis=2)
    track = estimate_track(frames, vf.t, cam.intrinsics, tau_s=TAU)
    flags = track.flagged()
    assert flags["duplicate"] == [dup]
    assert flags["cut"] + flags["untracked"] == [cut]
    # across the duplicate the motion is interpolated from the frames around it, not a stop
    true = true_interval_rate(sim, vf.t, track.lag_s)
    rate = track.rate_at_frames()
    for k in (dup - 1, dup):
        assert np.linalg.norm(rate[k] - true[k]) < 0.25 * np.linalg.norm(true[k]) + math.radians(2)
    assert not np.isfinite(rate[cut - 1]).any()
    calib = cam.replace(rate_hz=1000.0)
    gt, gr, _ = track.gyro(1000.0, lead_s=0.06, tail_s=track.lag_s + 0.004)
    inside = (gt > vf.t[cut - 1] + 0.005) & (gt < vf.t[cut] - track.lag_s - 0.001)
    assert not inside.any(), "gyro samples inside the cut"
    cfg = DeblurConfig(mode="uniform", temporal_views=1)
    plans = {k: plan_frame(float(vf.t[k]), gt, gr, calib, cfg) for k in (cut - 3, cut, cut + 1, cut + 4)}
    assert isinstance(plans[cut], PassThrough) and plans[cut].reason == "gyro_gap"
    assert isinstance(plans[cut + 1], PassThrough) and plans[cut + 1].reason == "gyro_gap"
    assert not isinstance(plans[cut - 3], PassThrough) and not isinstance(plans[cut + 4], PassThrough)


def test_a_pair_whose_corners_disagree_is_measured_by_every_pixel_not_left_a_hole(clip, monkeypatch):
    # low texture and heavy smear: the bench's fastest pitch lost 4 of 45 frames to such pairs, 1 since
    from thermod.motion.picture import PairRegistrar

    sim, vf, cam = clip
    measure, calls = PairRegistrar.measure, []

    def corners_fail_on_pair_15(self, *a, **k):
        calls.append(1)
        return None if len(calls) == 15 else measure(self, *a, **k)

    monkeypatch.setattr(PairRegistrar, "measure", corners_fail_on_pair_15)
    track = estimate_track(vf.frames, vf.t, cam.intrinsics, tau_s=TAU)
    assert track.known.all() and not any(track.flagged().values())
    true = true_interval_rate(sim, vf.t, track.lag_s)
    rate = track.rate_at_frames()
    assert np.linalg.norm(rate[14] - true[14]) < 0.25 * np.linalg.norm(true[14]) + math.radians(2)
    assert rel_error(rate, true) < RATE_TOL


def test_frames_lost_or_a_clock_jump_leave_a_hole_not_a_guessed_rate(clip):
    """A slow pan whose clock jumps by 1 s, or which loses ten frames: only the net rotation across
    that interval is seen, and a spline through it once guessed the rate inside (no flag, samples
    all through it); now the interval is a `gap` and the frame after it passes through."""
    from thermod.restore.policy import PassThrough, plan_frame
    from thermod.restore.settings import DeblurConfig

    _, _, cam = clip
    rng = np.random.default_rng(5)
    scene = cv2.GaussianBlur(rng.uniform(0, 255, (HEIGHT + 8, WIDTH + 80)), (0, 0), 2.0)
    scene = cv2.normalize(scene, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    pan = np.stack([scene[4:4 + HEIGHT, k:k + WIDTH] for k in range(60)])     # 1 px per frame
    t60 = np.arange(60) / FPS
    keep = np.r_[0:30, 40:60]
    for frames, t in ((pan[:50], t60[:50] + (np.arange(50) >= 30)), (pan[keep], t60[keep])):
        track = estimate_track(frames, t, cam.intrinsics, tau_s=TAU)
        assert not np.isfinite(track.rate_at_frames()[29]).any(), "a rate guessed across the gap"
        assert track.flagged()["gap"] == [30] and track.known.sum() >= len(t) - 3
        gt, gr, _ = track.gyro(1000.0, lead_s=0.06, tail_s=track.lag_s + 0.004)
        assert not ((gt > t[29] + 0.05) & (gt < t[30] - 0.05)).any(), "gyro samples inside the gap"
        plan = plan_frame(float(t[30]), gt, gr, cam.replace(rate_hz=1000.0),
                          DeblurConfig(mode="uniform", temporal_views=1))
        assert isinstance(plan, PassThrough) and plan.reason == "gyro_gap"


def thermod(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).parents[2] / ".numba_cache"))
    return subprocess.run([sys.executable, "-m", "thermod.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=600)


def test_import_without_gyro_says_the_motion_came_from_the_video(clip, tmp_path):
    sim, vf, cam = clip
    toml = tmp_path / "camera.toml"
    hfov = math.degrees(2 * math.atan(0.5 * WIDTH / cam.fx))
    toml.write_text(f"[camera]\nwidth = {WIDTH}\nheight = {HEIGHT}\nhfov_deg = {hfov}\n"
                    f"frame_rate_hz = {FPS}\ntau_s = {TAU}\n")
    out = tmp_path / "rec.h5"
    r = thermod("import", sim.video_path, "-o", out, "--calibration", toml, "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    assert "estimated from the video" in r.stdout
    with h5py.File(out) as f:
        assert f["motion"].attrs["source"] == "video"
        assert f["import"].attrs["motion_source"] == "video"
        n = len(f["gyro/t"])
        sigma = f["motion/sigma_rad_s"][()]
        rate = f["gyro/rate"][()]
        gt = f["gyro/t"][()]
    assert len(sigma) == n and np.all(sigma > 0) and np.all(np.isfinite(sigma))
    assert np.median(np.diff(gt)) == pytest.approx(1e-3, rel=1e-6)
    assert gt[0] < vf.t[0] - 5 * TAU and gt[-1] > vf.t[-1]          # the first and last kernels covered
    report = json.loads((tmp_path / "rep" / "track.json").read_text())
    assert report["motion_source"] == "video" and (tmp_path / "rep" / "track.png").stat().st_size > 0
    # the rate it wrote, averaged over each interval, is the truth's
    G = cumulative_rotation(gt, rate.astype(np.float64))
    lag = float(report["track"]["lag_s"])
    Gf = np.stack([np.interp(vf.t - lag, gt, G[:, a]) for a in range(3)], axis=1)
    written = np.diff(Gf, axis=0) / np.diff(vf.t)[:, None]
    assert rel_error(written, true_interval_rate(sim, vf.t, lag)) < RATE_TOL
    deb = tmp_path / "deb.h5"
    r = thermod("deblur", out, "-o", deb, "--uniform", "--single-frame", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    assert "motion from the video" in r.stdout
    with h5py.File(deb) as f:
        assert f["deblurred"].attrs["motion_source"] == "video"
        assert f["deblurred/deblurred"][()].mean() > 0.9
    r = thermod("export", out, "--gcsv", tmp_path / "motion.gcsv")
    assert r.returncode == 0 and "motion estimated from the video" in r.stdout, r.stderr
    assert "motion_source,video" in (tmp_path / "motion.gcsv").read_text()


def test_a_video_too_short_or_without_texture_is_refused(clip, tmp_path):
    sim, vf, cam = clip
    short = video.write_video(tmp_path / "short.mp4", vf.frames[:3], vf.t[:3] - vf.t[0])
    with pytest.raises(VideoImportError, match=r"short\.mp4: 3 frame\(s\).*≥ 4"):
        import_video(short, tmp_path / "a.h5", cam)
    flat = np.full((30, HEIGHT, WIDTH), 120, np.uint8)           # an overcast sky, say
    path = video.write_video(tmp_path / "flat.mp4", flat, np.arange(30) / FPS)
    with pytest.raises(VideoImportError, match=r"flat\.mp4: .*measured between only 0 of 29.*too little "
                                               r"texture"):
        import_video(path, tmp_path / "b.h5", cam)
    # sensor noise alone (each frame its own): nothing in it follows from one frame to the next
    noise = np.random.default_rng(0).normal(1000, 20, (30, HEIGHT, WIDTH)).astype(np.uint16)
    with pytest.raises(TrackError, match=r"noise: .*too little texture"):
        estimate_track(noise, np.arange(30) / FPS, cam.intrinsics, tau_s=TAU, name="noise")
    assert not (tmp_path / "a.h5").exists() and not (tmp_path / "b.h5").exists()


def test_frames_hours_apart_are_refused_not_sampled_at_1_khz_between():
    """A clip whose times are 10⁵ × too long (a wrong time base: the real clip's frames 72 min apart)
    imported as a gyro sampled at 1 kHz across every interval: 10⁸ samples, a 2.4 GB recording from
    24 frames. Frames over MAX_PERIOD_S apart are now refused, naming the clip."""
    from thermod.physics.geometry import Intrinsics

    rng = np.random.default_rng(6)
    scene = cv2.GaussianBlur(rng.uniform(0, 255, (72, 120)), (0, 0), 2.0).astype(np.float32)
    frames = np.stack([scene[4:68, k:k + 80] for k in range(8)])
    intr = Intrinsics(80, 64, 100.0, 100.0, 39.5, 31.5)
    with pytest.raises(TrackError, match=r"slow: the frames are 3600 s apart .*expected at least 0\.5 fps"):
        estimate_track(frames, np.arange(8) * 3600.0, intr, tau_s=TAU, name="slow")
    track = estimate_track(frames, np.arange(8) * 1.0, intr, tau_s=TAU)          # 1 fps: still tracked
    assert len(track.gyro(1000.0)[0]) < 8000


def test_a_strip_too_thin_for_the_working_image_is_refused_naming_the_clip():
    """A line-scan-like 4096×8 video shrinks to 160×0 working pixels: OpenCV's resize asserted (an
    internal error); now a TrackError naming the clip and the working size."""
    from thermod.physics.geometry import Intrinsics

    frames = np.random.default_rng(7).integers(0, 256, (6, 8, 4096), dtype=np.uint8)
    intr = Intrinsics(4096, 8, 2000.0, 2000.0, 2047.5, 3.5)
    with pytest.raises(TrackError, match=r"strip: 4096×8 px frames are 160×0 px .*≥ 8 px per side"):
        estimate_track(frames, np.arange(6) / FPS, intr, tau_s=TAU, name="strip")


def test_the_real_drone_clip_finds_its_logo_and_its_repeated_frames(shared_data, require):
    """The real ICI clip (shared/data/video, SOURCES.md: a logo burnt into the top-left corner, no
    gyro): the overlay is found there by itself, and the frames flagged as repeats are those whose
    pixels barely differ from their predecessor's."""
    path = shared_data / "video" / "ici_drone_640x512.mp4"
    require(path.exists(), f"{path}")
    vf = video.read_video(path, duration_s=3.0)
    h, w = vf.frames.shape[1:]
    f = 1.0 / math.tan(math.radians(25.0)) * w / 2           # 50° HFOV, a guess: the overlay needs none
    cam = Calibration().replace(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2,
                                frame_rate_hz=23.1, tau_s=0.01)
    track = estimate_track(vf.frames, vf.t, cam.intrinsics, tau_s=0.01)
    assert track.overlay is not None
    ys, xs = np.nonzero(track.overlay)
    s = track.work_scale
    assert xs.max() / s < 0.25 * w and ys.max() / s < 0.2 * h, (xs.max() / s, ys.max() / s)
    assert track.overlay.mean() > 0.01
    diff = np.array([np.mean(np.abs(vf.frames[k].astype(float) - vf.frames[k - 1]))
                     for k in range(1, len(vf.t))])
    dup = np.array(track.flagged()["duplicate"])
    assert len(dup) >= 3
    # a repeat differs by the codec's requantisation only: under 0.6 of a code on average, where new
    # views differ by ~2 codes (the median)
    assert diff[dup - 1].max() < 0.6 and np.median(diff) > 1.5, (diff[dup - 1], np.median(diff))
    assert track.known.all()


def test_a_fit_off_its_neighbours_is_left_out_and_a_fast_smooth_turn_is_not():
    from thermod.motion.track import _outliers

    t = np.arange(46) / FPS
    mid = 0.5 * (t[1:] + t[:-1])
    # the real flight's hardest stretch: ±200 °/s at 1.5 Hz, sampled per frame interval
    rate = np.zeros((45, 3))
    rate[:, 0] = math.radians(200.0) * np.sin(2 * np.pi * 1.5 * mid)
    rate[:, 2] = math.radians(5.0) * np.cos(2 * np.pi * 0.7 * mid)
    ok = np.ones(45, bool)
    assert not _outliers(rate / FPS, t, ok).any()
    bad = rate.copy()
    bad[20, 2] += math.radians(60.0)          # a roll the pictures' fit made up (seen at 200 °/s)
    assert np.flatnonzero(_outliers(bad / FPS, t, ok)).tolist() == [20]
