"""`thermod deblur` end to end on simulated recordings (the simulator's truth is the reference)."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

from thermod.cli import main
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.sim import synth
from thermod.sim.gyro_model import GyroErrorModel


def psnr8(est, truth):
    """PSNR on the 8-bit scale: the truth's 0.5–99.5 % range mapped to 0–255."""
    lo, hi = np.percentile(truth, (0.5, 99.5))
    a = np.clip((est.astype(np.float64) - lo) * 255 / (hi - lo), 0, 255)
    b = np.clip((truth.astype(np.float64) - lo) * 255 / (hi - lo), 0, 255)
    return 10 * np.log10(255 ** 2 / np.mean((a - b) ** 2))


@pytest.fixture(scope="module")
def pan50(tmp_path_factory):
    """640×480 SBTI camera panning at 50 °/s over a real scene, paper gyro, NETD 30 mK."""
    rec = synth.simulate("real:0", "pan:50", seconds=0.08, seed=3, effects={"netd": 0.03},
                         gyro=GyroErrorModel.paper())
    path = tmp_path_factory.mktemp("rec") / "pan50.h5"
    recording.write(path, rec)
    return path


@pytest.fixture(scope="module")
def roll(tmp_path_factory):
    """A smaller camera rolling at 90 °/s: the blur grows from the centre to the corners."""
    calib = Calibration(width=320, height=240, cx=159.5, cy=119.5)
    rec = synth.simulate("real:6", "roll:90", seconds=0.06, calib=calib, seed=4, effects={"netd": 0.03},
                         gyro=GyroErrorModel.paper())
    path = tmp_path_factory.mktemp("rec") / "roll.h5"
    recording.write(path, rec)
    return path


def deblur(capsys, *argv):
    rc = main(["deblur", *map(str, argv)])
    out, err = capsys.readouterr()
    return rc, out, err


def gains(path):
    rec = recording.read(path)
    truth = rec.extras["truth/frames"]
    return np.array([psnr8(rec.deblurred[i], truth[i]) - psnr8(rec.frames[i].astype(np.float32), truth[i])
                     for i in range(rec.n_frames)])


def test_single_file_raises_psnr_by_8_db_and_keeps_everything(pan50, tmp_path, capsys):
    out = tmp_path / "out.h5"
    rc, text, _ = deblur(capsys, pan50, "-o", out)
    assert rc == 0
    src, res = recording.read(pan50), recording.read(out)
    assert res.deblurred.dtype == np.float32 and res.deblurred.shape == src.frames.shape
    np.testing.assert_array_equal(res.frames, src.frames)
    np.testing.assert_array_equal(res.gyro_rate, src.gyro_rate)
    np.testing.assert_array_equal(res.deblurred_t, src.t)
    np.testing.assert_array_equal(res.extras["truth/frames"], src.extras["truth/frames"])
    g = gains(out)
    assert g.min() >= 8.0, g                      # measured ≈ +16 dB
    # counts in the input's scale and never clipped to the blurry frame's range
    assert abs(np.median(res.deblurred) - np.median(src.frames)) < 20
    assert res.deblurred.max() > src.frames.max() or res.deblurred.min() < src.frames.min()
    with h5py.File(out) as f:
        assert f["deblurred/deblurred"][()].all()
        assert f["deblurred"].attrs["kernel"] == "thermal"
    assert f"{src.n_frames} deblurred, 0 passed through" in text and "ms/frame" in text


def test_thermal_kernel_beats_photon_kernel(pan50, tmp_path, capsys):
    assert deblur(capsys, pan50, "-o", tmp_path / "t.h5", "--uniform")[0] == 0
    assert deblur(capsys, pan50, "-o", tmp_path / "p.h5", "--uniform", "--kernel", "photon")[0] == 0
    gt, gp = gains(tmp_path / "t.h5"), gains(tmp_path / "p.h5")
    assert gt.mean() > gp.mean() + 4.0, (gt, gp)


@pytest.mark.parametrize("opts,gain", [(["--alpha", "1"], 8.0), (["--alpha", "0.6667"], 8.0),
                                       (["--method", "wiener"], 6.0)])
def test_methods_and_alphas_work(pan50, tmp_path, capsys, opts, gain):
    rc, text, _ = deblur(capsys, pan50, "-o", tmp_path / "o.h5", "--uniform", *opts)
    assert rc == 0
    assert gains(tmp_path / "o.h5").min() >= gain


def test_spatially_varying_default_beats_uniform_under_roll(roll, tmp_path, capsys):
    assert deblur(capsys, roll, "-o", tmp_path / "v.h5")[0] == 0
    assert deblur(capsys, roll, "-o", tmp_path / "u.h5", "--uniform")[0] == 0
    gv, gu = gains(tmp_path / "v.h5"), gains(tmp_path / "u.h5")
    assert gv.mean() > gu.mean() + 1.0 and gv.min() > 3.0, (gv, gu)


def test_uncovered_frame_is_passed_through_not_dropped(pan50, tmp_path, capsys):
    rec = recording.read(pan50)
    keep = rec.gyro_t > rec.t[0] - 0.015          # frame 0 needs 5τ = 40 ms of history
    rec.gyro_t, rec.gyro_rate = rec.gyro_t[keep], rec.gyro_rate[keep]
    src = tmp_path / "cut.h5"
    recording.write(src, rec)
    rc, text, _ = deblur(capsys, src, "-o", tmp_path / "cut_out.h5")
    assert rc == 0
    res = recording.read(tmp_path / "cut_out.h5")
    np.testing.assert_array_equal(res.deblurred[0], rec.frames[0].astype(np.float32))
    assert not np.array_equal(res.deblurred[1], rec.frames[1].astype(np.float32))
    with h5py.File(tmp_path / "cut_out.h5") as f:
        assert f["deblurred/deblurred"][()].tolist() == [False] + [True] * (rec.n_frames - 1)
    assert f"{rec.n_frames - 1} deblurred, 1 passed through" in text
    assert "frame 0 passed through: gyro_incomplete: gyro coverage" in text


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """160×120, panning at 30 °/s over a real scene, NETD 60 mK: a noisy recording of 8 frames."""
    calib = Calibration(width=160, height=120, cx=79.5, cy=59.5)
    rec = synth.simulate("real:0", "pan:30", seconds=8 / calib.frame_rate_hz, calib=calib, seed=5,
                         effects={"netd": 0.06}, gyro=GyroErrorModel.paper())
    path = tmp_path_factory.mktemp("rec") / "noisy.h5"
    recording.write(path, rec)
    return path


def test_temporal_default_beats_single_frame_on_a_noisy_recording(noisy, tmp_path, capsys):
    rc, text, _ = deblur(capsys, noisy, "-o", tmp_path / "t.h5")
    assert rc == 0 and "temporal 6 views" in text
    rc, text, _ = deblur(capsys, noisy, "-o", tmp_path / "s.h5", "--single-frame")
    assert rc == 0 and "single-frame" in text
    src = recording.read(noisy)
    n = src.n_frames
    for name, solver, views in (("t.h5", "temporal", 6), ("s.h5", "single-frame", 1)):
        res = recording.read(tmp_path / name)
        assert res.deblurred.shape == src.frames.shape          # every frame written
        np.testing.assert_array_equal(res.deblurred_t, src.t)
        with h5py.File(tmp_path / name) as f:
            assert f["deblurred/deblurred"][()].all()
            assert f["deblurred"].attrs["solver"] == solver
            assert f["deblurred"].attrs["temporal_views"] == views
            used = f["deblurred/views"][()]
        if views == 1:
            assert used.tolist() == [1] * n
        else:   # frame i has i predecessors, up to 5; all agree on a static scene
            assert used.tolist() == [min(i + 1, views) for i in range(n)]
    gt, gs = gains(tmp_path / "t.h5"), gains(tmp_path / "s.h5")
    assert gt[0] == pytest.approx(gs[0], abs=1e-6)      # no history yet: the single-frame solve
    assert np.median(gt[3:] - gs[3:]) > 0.4, (gt, gs)      # measured ≈ +0.7 dB with 4–6 views
    assert (gt[1:] > gs[1:]).all(), (gt, gs)


def test_multi_file_mode_writes_a_directory(pan50, roll, tmp_path, capsys):
    outdir = tmp_path / "outdir"
    rc, text, _ = deblur(capsys, pan50, roll, "-o", f"{outdir}/", "--uniform", "--method", "wiener")
    assert rc == 0
    for name in ("pan50.h5", "roll.h5"):
        res = recording.read(outdir / name)
        assert res.deblurred is not None and res.deblurred.dtype == np.float32
    assert "2 file(s)" in text


def test_bad_input_file_gives_recording_error_and_exit_2(tmp_path):
    bad = tmp_path / "notes.h5"
    bad.write_text("not an HDF5 file")
    cmd = [sys.executable, "-m", "thermod.cli", "deblur", str(bad), "-o", str(tmp_path / "o.h5")]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert f"{bad}: file: not a readable HDF5 file" in p.stderr
    assert "Traceback" not in p.stderr and not (tmp_path / "o.h5").exists()


def test_wrong_format_attribute_in_multi_file_mode_keeps_the_good_file(pan50, tmp_path, capsys):
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f.attrs["format"] = "something-else"
    outdir = tmp_path / "o"
    rc, text, err = deblur(capsys, wrong, pan50, "-o", outdir, "--method", "wiener", "--uniform")
    assert rc == 2
    assert "wrong.h5: /.attrs['format']: expected 'thermod-recording'" in err
    assert recording.read(outdir / "pan50.h5").deblurred is not None
    assert not (outdir / "wrong.h5").exists()


def test_unwritable_output_is_a_one_line_error(pan50, tmp_path, capsys):
    rc, _, err = deblur(capsys, pan50, "-o", tmp_path / "missing-dir" / "o.h5", "--uniform")
    assert rc == 2 and "missing-dir/o.h5: cannot write the output" in err


def test_refuses_to_overwrite_its_input(pan50, tmp_path, capsys):
    rc, _, err = deblur(capsys, pan50, "-o", pan50)
    assert rc == 2 and "would overwrite the input" in err


@pytest.mark.parametrize("opts,match", [(["--grid", "0", "3"], "--grid"), (["--grid", "20", "3"], "--grid"),
                                        (["--min-coverage", "2"], "--min-coverage"),
                                        (["--alpha", "0.5"], "--alpha"), (["--views", "40"], "--views"),
                                        (["--uniform", "--adaptive"], "--adaptive"),
                                        (["--lambda", "-5"], "lam"), (["--alpha", "3"], "alpha")])
def test_bad_options_exit_2(pan50, tmp_path, capsys, opts, match):
    rc, _, err = deblur(capsys, pan50, "-o", tmp_path / "x.h5", *opts)
    assert rc == 2 and match in err


def test_config_calibration_fixes_a_hidden_time_offset(tmp_path, capsys):
    """A recording whose gyro is 6 ms late: deblurring with the corrected model.toml beats the nominal."""
    calib = Calibration(width=320, height=240, cx=159.5, cy=119.5)
    rec = synth.simulate("real:1", "shake:20", seconds=0.12, calib=calib, seed=5,
                         effects={"time_offset": 0.006, "netd": 0.03})
    src = tmp_path / "late.h5"
    recording.write(src, rec)
    model = tmp_path / "model.toml"
    model.write_text("[calibration]\ntime_offset_s = 0.006\n")   # only what changed; the rest stays
    assert deblur(capsys, src, "-o", tmp_path / "nominal.h5", "--uniform")[0] == 0
    assert deblur(capsys, src, "-o", tmp_path / "fixed.h5", "--uniform", "--config", model)[0] == 0
    nominal, fixed = gains(tmp_path / "nominal.h5"), gains(tmp_path / "fixed.h5")
    assert np.median(fixed) > np.median(nominal) + 1.0, (fixed, nominal)
    out = recording.read(tmp_path / "fixed.h5").calibration
    assert out.time_offset_s == pytest.approx(0.006) and (out.width, out.fx) == (320, calib.fx)


def test_config_of_another_camera_is_refused(pan50, tmp_path, capsys):
    model = tmp_path / "model.toml"
    model.write_text("[calibration]\nwidth = 320\nheight = 240\n")
    rc, _, err = deblur(capsys, pan50, "-o", tmp_path / "o.h5", "--config", model)
    assert rc == 2 and "model.toml" in err and "320×240" in err and "640×480" in err
    model.write_text("[calibration]\ntau_s = -1\n")
    rc, _, err = deblur(capsys, pan50, "-o", tmp_path / "o.h5", "--config", model)
    assert rc == 2 and "calibration.tau_s" in err


# ------------------------------------------------------------------------ batches and bad inputs
def tiny(path, n=6, seed=0, **calib_changes):
    """A 64×48 recording with a 1 kHz gyro turning at 20 °/s about y: fast to deblur."""
    rng = np.random.default_rng(seed)
    calib = Calibration(width=64, height=48, cx=31.5, cy=23.5).replace(**calib_changes)
    gyro_t = np.arange(0.0, 0.02 * (n + 3), 0.001)
    rate = np.zeros((len(gyro_t), 3), np.float32)
    rate[:, 1] = np.deg2rad(20.0)
    rec = recording.Recording(rng.integers(1000, 3000, (n, 48, 64), dtype=np.uint16),
                              0.05 + 0.02 * np.arange(n), gyro_t, rate, calib)
    recording.write(path, rec)
    return path


def test_batch_reports_every_failure_and_goes_on(tmp_path, capsys, monkeypatch):
    good = [tiny(tmp_path / f"good{i}.h5", seed=i) for i in range(2)]
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(200))
    zero_scale = tiny(tmp_path / "zero_scale.h5")
    with h5py.File(zero_scale, "a") as f:
        f["gyro"].attrs["scale"] = np.zeros(3)
    strings = tiny(tmp_path / "strings.h5")
    with h5py.File(strings, "a") as f:
        del f["camera/t"]
        f["camera/t"] = np.array([b"x"] * 6)
    damaged = tiny(tmp_path / "damaged.h5")
    with h5py.File(damaged, "a") as f:                         # gzip frames, frame 2's chunk damaged
        frames = f["camera/frames"][()]
        del f["camera/frames"]
        f.create_dataset("camera/frames", data=frames, chunks=(1, 48, 64), compression="gzip")
        offset = f["camera/frames"].id.get_chunk_info(2).byte_offset
    with open(damaged, "r+b") as fh:
        fh.seek(offset)
        fh.write(b"\xff" * 4)
    blocked, buggy = tiny(tmp_path / "blocked.h5"), tiny(tmp_path / "buggy.h5")
    out = tmp_path / "out"
    (out / "blocked.h5").mkdir(parents=True)                    # a directory in the way
    (out / "zero_scale.h5").write_bytes(b"an earlier result")   # must survive the failure
    real_frame = recording.Reader.frame

    def frame(self, i):                                         # a bug that only one file meets
        if self.path.name == "buggy.h5" and i == 3:
            raise ZeroDivisionError("division by zero")
        return real_frame(self, i)
    monkeypatch.setattr(recording.Reader, "frame", frame)
    inputs = [good[0], garbage, zero_scale, strings, damaged, blocked, buggy, good[1]]
    # --jobs 1: in this process, where the patched reader is (the pool's processes would not see it)
    rc, text, err = deblur(capsys, *inputs, "-o", out, "--uniform", "--method", "wiener", "--jobs", "1")
    assert rc == 2
    assert f"{garbage}: file: not a readable HDF5 file" in err
    assert f"{zero_scale}: gyro.attrs['scale']: expected 1 or 3 numbers in (0, 100]" in err
    assert f"{strings}: camera/t: expected" in err and "dtype |S1" in err
    assert f"{damaged}: camera/frames: frame 2: cannot be read" in err
    assert f"{out / 'blocked.h5'}: cannot write the output (a directory is in the way)" in err
    assert f"{buggy}: unexpected ZeroDivisionError: division by zero" in err
    assert "Traceback" not in err
    failed = ", ".join(map(str, (garbage, zero_scale, strings, damaged, blocked, buggy)))
    assert err.strip().splitlines()[-1] == f"thermod deblur: 6 of 8 file(s) failed: {failed}"
    for g in good:                                              # before and after the failures
        res = recording.read(out / g.name)
        assert res.deblurred.shape == (6, 48, 64) and "2 file(s)" in text
    assert (out / "zero_scale.h5").read_bytes() == b"an earlier result"
    assert (out / "blocked.h5").is_dir() and not (out / "buggy.h5").exists()
    assert not (out / "damaged.h5").exists()
    assert sorted(p.name for p in out.iterdir()) == ["blocked.h5", "good0.h5", "good1.h5", "zero_scale.h5"]


def test_celsius_batch_converts_each_recording_with_its_own_model(tmp_path, capsys):
    """--celsius in a batch: each recording's /radiometry model, a passed-through frame's raw counts
    converted; a recording without a model fails alone, before any output of it is written."""
    from thermod.physics.radiometry import RECORDING_GROUP, Linear

    models = [Linear(gain=0.01, offset=-5.0), Linear(gain=-0.002, offset=40.0)]
    tagged = []
    for i, model in enumerate(models):
        rec = recording.read(tiny(tmp_path / f"plain{i}.h5", seed=i))
        rec.extra_attrs = {RECORDING_GROUP: model.as_dict()}
        # gyro from 10 ms before frame 0: its kernel keeps 71 % of its weight, below the start rule's
        # 90 % (`restore.policy.START_COVERAGE`, the daemon's); frame 1's keeps 98 %: deblurred
        if i == 1:
            keep = rec.gyro_t > rec.t[0] - 0.010
            rec.gyro_t, rec.gyro_rate = rec.gyro_t[keep], rec.gyro_rate[keep]
        tagged.append(tmp_path / f"t{i}.h5")
        recording.write(tagged[-1], rec)
    bare = tiny(tmp_path / "bare.h5", seed=7)
    out = tmp_path / "out"
    rc, _, err = deblur(capsys, tagged[0], bare, tagged[1], "-o", out, "--celsius", "--uniform",
                        "--method", "wiener")
    assert rc == 2
    assert f"{bare}: /radiometry: no attributes, and --celsius needs a radiometric model" in err
    assert err.strip().splitlines()[-1] == f"thermod deblur: 1 of 3 file(s) failed: {bare}"
    assert sorted(p.name for p in out.iterdir()) == ["t0.h5", "t1.h5"]
    for src, model, expect_ok in zip(tagged, models, ([True] * 6, [False] + [True] * 5), strict=True):
        with h5py.File(out / src.name) as f:
            raw, deb = f["camera/frames"][()], f["deblurred/frames"][()]
            ok, c = f["deblurred/deblurred"][()], f["deblurred/celsius"][()]
            attrs = dict(f["deblurred/celsius"].attrs)
            assert dict(f[RECORDING_GROUP].attrs) == model.as_dict()      # the input's, kept
        assert ok.tolist() == expect_ok
        assert c.dtype == np.float32 and c.shape == raw.shape == (6, 48, 64)
        np.testing.assert_array_equal(c, model.to_celsius(deb))
        np.testing.assert_array_equal(c[~ok], model.to_celsius(raw[~ok]))
        assert not np.allclose(c[ok], model.to_celsius(raw[ok]), atol=1e-3)  # deblurred, then converted
        assert attrs.pop("units") == "degC" and attrs == model.as_dict()


def test_failed_single_file_keeps_the_previous_output(tmp_path, capsys):
    src = tiny(tmp_path / "a.h5")
    with h5py.File(src, "a") as f:
        f["camera"].attrs["frame_rate_hz"] = 0.0
    (tmp_path / "o.h5").write_bytes(b"previous")
    rc, _, err = deblur(capsys, src, "-o", tmp_path / "o.h5")
    assert rc == 2 and f"{src}: camera.attrs['frame_rate_hz']: expected a value in (0, 10000] Hz" in err
    assert (tmp_path / "o.h5").read_bytes() == b"previous" and not (tmp_path / "o.h5.part").exists()


def test_defaults_are_deblur_configs():
    """One source for the offline defaults: DeblurConfig (the grid mode is the one offline choice)."""
    import argparse
    import dataclasses

    from thermod.cli import deblur as cmd
    from thermod.restore.settings import DeblurConfig

    p = argparse.ArgumentParser()
    cmd.add_arguments(p)
    cfg = cmd.deblur_config(p.parse_args(["x.h5", "-o", "y.h5"]))
    assert cfg == dataclasses.replace(DeblurConfig(), mode="grid")
    assert cmd.deblur_config(p.parse_args(["x.h5", "-o", "y.h5", "--uniform"])).mode == "uniform"
    assert cmd.deblur_config(p.parse_args(["x.h5", "-o", "y.h5", "--grid", "1", "1"])).mode == "uniform"


def test_memory_does_not_grow_with_the_recording(tmp_path, capsys):
    """Frames stream through: 8× the frames may not cost 8× the memory (tracemalloc sees numpy)."""
    import tracemalloc

    peaks = {}
    assert deblur(capsys, tiny(tmp_path / "warm.h5"), "-o", tmp_path / "w.h5", "--uniform", "--method",
                  "wiener")[0] == 0          # FFT plans and caches: allocated once, not per frame
    for n in (12, 96):
        src = tiny(tmp_path / f"n{n}.h5", n=n)
        tracemalloc.start()
        rc, _, _ = deblur(capsys, src, "-o", tmp_path / f"o{n}.h5", "--uniform", "--method", "wiener")
        peaks[n] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert rc == 0
    frames_bytes = 96 * 48 * 64 * (2 + 4)     # what holding the stack and its result would add
    assert peaks[96] - peaks[12] < 0.25 * frames_bytes, peaks


def test_one_input_and_an_output_ending_in_a_slash_writes_into_that_directory(tmp_path, capsys):
    """`-o DIR/` means a directory even for one input (argparse's Path() used to drop the slash)."""
    src = tiny(tmp_path / "one.h5")
    rc, _, _ = deblur(capsys, src, "-o", f"{tmp_path / 'new'}/", "--uniform", "--method", "wiener")
    assert rc == 0 and (tmp_path / "new").is_dir()
    assert recording.read(tmp_path / "new" / "one.h5").deblurred.shape == (6, 48, 64)


def test_offline_solver_comes_from_the_one_factory_and_honours_kf_iterations():
    from thermod.batch.job import deconvolver
    from thermod.restore.settings import DeblurConfig

    assert deconvolver(DeblurConfig(kf_iterations=3)).iterations == 3
    assert deconvolver(DeblurConfig()).iterations == 6
    d = deconvolver(DeblurConfig(method="wiener", kf_iterations=3))
    assert d.method == "wiener" and not d.realtime       # offline plans are measured, not estimated


def test_a_frame_smaller_than_the_grid_is_deblurred_over_a_grid_that_fits(tmp_path, capsys):
    """The default 6×8 grid on a 4×4 recording is capped at one cell per pixel row and column: its
    frames are deblurred, not passed through with a kernel error."""
    calib = Calibration(width=4, height=4, cx=1.5, cy=1.5, fx=20.0, fy=20.0)
    gyro_t = np.arange(0.0, 0.5, 0.001)
    rate = np.zeros((len(gyro_t), 3), np.float32)
    rate[:, 2] = 1.0
    frames = np.random.default_rng(0).integers(900, 1100, (5, 4, 4)).astype(np.uint16)
    src = tmp_path / "tiny.h5"
    recording.write(src, recording.Recording(frames, 0.2 + 0.02 * np.arange(5), gyro_t, rate, calib))
    out = tmp_path / "out.h5"
    assert main(["deblur", str(src), "-o", str(out)]) == 0
    res = recording.read(out)
    assert res.deblurred.shape == frames.shape and "kernel_error" not in capsys.readouterr().out
