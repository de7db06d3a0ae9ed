"""`thermod sim` end to end (argument parsing, errors, the written file) and the looping playback."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thermod.cli import main
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.sim import detector, motion, playback, synth

DEG = math.pi / 180


def test_sim_writes_a_recording_with_hidden_truth(tmp_path, capsys):
    out = tmp_path / "rec.h5"
    rc = main(["sim", "-o", str(out), "--scene", "bars", "--motion", "static:0.04+pan:50", "--seconds", "0.1",
               "--width", "128", "--height", "96", "--fps", "100", "--tau", "0.01", "--seed", "3",
               "--effect", "time_offset=0.004", "--effect", "gyro_bias=0.001,0,-0.002",
               "--effect", "rolling_readout=0.005", "--gyro", "paper", "--no-progress"])
    assert rc == 0
    assert "10 frames 128×96 at 100 Hz" in capsys.readouterr().out
    rec = recording.read(out)
    c = rec.calibration
    assert (c.width, c.height, c.frame_rate_hz, c.tau_s) == (128, 96, 100, 0.01)
    assert (c.readout_s, c.time_offset_s) == (0, 0)                   # the nominal model knows neither
    assert (c.cx, c.cy) == (63.5, 47.5)
    true = synth.truth_calibration(rec)
    assert true.time_offset_s == pytest.approx(0.004) and true.readout_s == pytest.approx(0.005)
    assert true.bias_rad_s == pytest.approx((0.001, 0.0, -0.002))
    assert rec.extra_attrs["truth"]["motion"] == "static:0.04+pan:50"
    # the first 4 frames are static (blurry = sharp through the optics' PSF), the pan then blurs
    tf, bn = rec.extras["truth/frames"], rec.extras["truth/blurry_noiseless"]
    psf = true.psf_sigma_px
    assert np.abs(bn[1] - detector.gaussian_psf(tf[1], psf)).max() < 0.05
    assert np.abs(bn[-1] - detector.gaussian_psf(tf[-1], psf)).max() > 50.0
    # the paper gyro is noisy but unbiased apart from the hidden bias: mean over the static part
    t_cam, w = true.gyro_to_camera(rec.gyro_t, rec.gyro_rate)
    static = (t_cam > rec.t[0] - 0.05) & (t_cam < rec.t[0] + 0.03)
    assert np.abs(w[static].mean(axis=0)).max() < 0.2 * DEG


@pytest.mark.parametrize("argv, needle", [
    (["--motion", "wobble"], "--motion 'wobble'"),
    (["--scene", "nope"], "--scene 'nope'"),
    (["--effect", "time_offset"], "--effect 'time_offset'"),
    (["--effect", "speed=3"], "--effect speed"),
    (["--effect", "gyro_bias=1,2"], "--effect gyro_bias"),
    (["--width", "3"], "--width"),
    (["--seconds", "0"], "--seconds"),
    (["-o", "/nonexistent-dir/x.h5"], "-o /nonexistent-dir/x.h5"),
])
def test_bad_options_name_the_option(tmp_path, capsys, argv, needle):
    base = ["sim", "-o", str(tmp_path / "x.h5"), "--seconds", "0.02", "--width", "64", "--height", "48",
            "--no-progress"]
    rc = main(base + argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "x.h5").exists()


def test_console_script_runs(tmp_path):
    exe = Path(sys.executable).with_name("thermod")
    out = tmp_path / "cs.h5"
    p = subprocess.run([str(exe), "sim", "-o", str(out), "--scene", "points", "--motion", "roll:30",
                        "--seconds", "0.04", "--width", "96", "--height", "64"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert recording.read(out).n_frames == 2


def test_real_scene_and_log_motion(tmp_path, shared_data, require):
    require((shared_data / "thermal").is_dir() and (shared_data / "gyro").is_dir(), "shared/data")
    rec = synth.simulate("real:1", "log:12", 0.06, Calibration(width=160, height=128, cx=79.5, cy=63.5))
    sharp = rec.extras["truth/frames"][0]
    assert 17000 < np.median(sharp) < 19000                       # real DJI counts
    np.testing.assert_allclose(rec.extras["truth/gyro_omega_camera"],
                               motion.parse("log:12").omega(rec.extras["truth/gyro_t_camera"] - rec.t[0]),
                               atol=1e-5)


def test_playback_loops_seamlessly_and_caches(tmp_path, monkeypatch):
    monkeypatch.setenv("THERMOD_CACHE", str(tmp_path))
    cal = Calibration(width=96, height=72, cx=47.5, cy=35.5)
    spec = playback.PlaybackSpec(scene="texture", motion="sway:3:0.3", seconds=0.4, calib=cal)
    pb = playback.load(spec)
    files = list(tmp_path.glob("playback-*.h5"))
    assert len(files) == 1 and pb.frames.shape == (20, 72, 96)
    assert pb.period_s == pytest.approx(0.4)
    assert pb.index_at(0.0) == 0 and pb.index_at(0.419) == 0 and pb.index_at(0.02) == 1
    # the orientation comes back after the loop (sway period snapped to 0.4/1 s)
    traj = motion.Trajectory(pb.motion, 0.0, -0.01, 0.41)
    assert np.abs(traj.R(0.4)[0] - np.eye(3)).max() < 1e-7
    # … so the frame after the last one is the first one again (noiseless render one frame longer)
    longer = synth.simulate("texture", pb.motion, 0.42, cal)
    bn = longer.extras["truth/blurry_noiseless"]
    # equal up to the renderer's discretisation (other step grid and canvas: bilinear at 1/32 px)
    d = bn[20] - bn[0]
    assert np.abs(d).max() < 1.0 and np.sqrt(np.mean(d**2)) < 0.2
    np.testing.assert_array_equal(longer.frames[:20], pb.frames)
    # gyro samples: the true calibration maps them back to the camera rate
    t = np.linspace(0, 1.0, 101)
    np.testing.assert_allclose(cal.gyro_to_camera(t, pb.rate_gyro(t))[1], pb.omega_camera(t), atol=1e-12)
    np.testing.assert_allclose(pb.omega_camera(t + 0.4), pb.omega_camera(t), atol=1e-12)
    # second load: from the cache, same frames, file untouched
    mtime = files[0].stat().st_mtime_ns
    again = playback.load(spec)
    np.testing.assert_array_equal(again.frames, pb.frames)
    assert files[0].stat().st_mtime_ns == mtime
    with pytest.raises(Exception, match="not periodic"):
        playback.load(playback.PlaybackSpec(motion="pan:50", seconds=0.1, calib=cal))


def test_sim_time_compression_option(tmp_path):
    out = tmp_path / "tc.h5"
    rc = main(["sim", "-o", str(out), "--scene", "points", "--motion", "pan:40", "--seconds", "0.04",
               "--width", "96", "--height", "64", "--time-compression", "20", "--slow-fps", "50",
               "--no-progress"])
    assert rc == 0
    truth = recording.read(out).extra_attrs["truth"]
    assert truth["method"] == "time_compression" and truth["compression"] == 20.0
    # views 1 ms apart at 40 °/s: 1.0 px per view, the Eq. 12 limit
    assert truth["max_step_px"] == pytest.approx(Calibration().fx * 40 * DEG / 1000, rel=0.02)
