"""Recording format v1: round trip, and one clear error naming file and field for each kind of damage."""

import h5py
import numpy as np
import pytest

from thermod.errors import RecordingError
from thermod.io import recording
from thermod.physics.calibration import Calibration


def small_recording(n=4, h=6, w=8, m=50):
    calib = Calibration(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2, readout_s=0.01,
                        bias_rad_s=(0.001, 0.0, -0.002), time_offset_s=0.003)
    rng = np.random.default_rng(1)
    return recording.Recording(
        frames=rng.integers(0, 2**14, size=(n, h, w), dtype=np.uint16),
        t=0.02 * np.arange(1, n + 1),
        gyro_t=0.001 * np.arange(m),
        gyro_rate=rng.normal(size=(m, 3)).astype(np.float32),
        calibration=calib,
        extras={"truth/frames": np.zeros((n, h, w), np.float32), "camera/frame_id": np.arange(n)},
        extra_attrs={"truth": {"time_offset_s": 0.004}},
    )


@pytest.fixture
def rec_path(tmp_path):
    p = tmp_path / "rec.h5"
    recording.write(p, small_recording())
    return p


def test_roundtrip(rec_path):
    a, b = small_recording(), recording.read(rec_path)
    assert np.array_equal(a.frames, b.frames) and b.frames.dtype == np.uint16
    assert np.array_equal(a.t, b.t) and np.array_equal(a.gyro_t, b.gyro_t)
    assert np.array_equal(a.gyro_rate, b.gyro_rate) and b.gyro_rate.dtype == np.float32
    assert b.calibration == a.calibration
    assert np.array_equal(b.extras["camera/frame_id"], np.arange(4))  # optional datasets survive
    assert "truth/frames" in b.extras and b.extra_attrs["truth"]["time_offset_s"] == 0.004
    with h5py.File(rec_path) as f:  # layout of DESIGN.md §3
        assert f.attrs["format"] == "thermod-recording" and f.attrs["version"] == 1
        assert f["camera/frames"].chunks == (1, 6, 8)
        assert f["gyro"].attrs["R_cam_gyro"].shape == (3, 3)


def _damage(path, fn):
    with h5py.File(path, "a") as f:
        fn(f)


def _replace(f, name, data):
    del f[name]
    f[name] = data


@pytest.mark.parametrize("damage, field, expected", [
    (lambda f: f.attrs.__setitem__("format", "other"), "format", "thermod-recording"),
    (lambda f: f.attrs.__setitem__("version", 2), "version", "expected 1, got 2"),
    (lambda f: f.__delitem__("gyro/rate"), "gyro/rate", "missing"),
    (lambda f: f.__delitem__("camera/t"), "camera/t", "missing"),
    (lambda f: f["camera"].attrs.__delitem__("tau_s"), "tau_s", "missing"),
    (lambda f: _replace(f, "camera/frames", np.zeros((4, 6, 8), np.float32)), "camera/frames", "uint16"),
    (lambda f: _replace(f, "camera/frames", np.zeros((4, 5, 8), np.uint16)), "camera/frames", "height"),
    (lambda f: _replace(f, "camera/t", np.array([0.02, np.nan, 0.06, 0.08])), "camera/t", "NaN"),
    (lambda f: _replace(f, "camera/t", np.array([0.02, 0.04, 0.04, 0.08])), "camera/t", "increasing"),
    (lambda f: _replace(f, "camera/t", np.array([0.02, 0.04])), "camera/t", "one per frame"),
    (lambda f: _replace(f, "gyro/rate", np.zeros((50, 2), np.float32)), "gyro/rate", "(50, 3)"),
    (lambda f: f["gyro"].attrs.__setitem__("R_cam_gyro", np.eye(2)), "R_cam_gyro", "3×3"),
])
def test_damaged_file_gives_clear_error(rec_path, damage, field, expected):
    _damage(rec_path, damage)
    with pytest.raises(RecordingError) as e:
        recording.read(rec_path)
    msg = str(e.value)
    assert str(rec_path) in msg and field in msg and expected in msg


def test_not_hdf5_and_missing_file(tmp_path):
    p = tmp_path / "x.h5"
    p.write_text("not hdf5")
    with pytest.raises(RecordingError, match="not a readable HDF5"):
        recording.read(p)
    with pytest.raises(RecordingError, match="does not exist"):
        recording.read(tmp_path / "nope.h5")


def test_write_is_atomic_and_validates(tmp_path):
    rec = small_recording()
    rec.t = rec.t[::-1].copy()
    with pytest.raises(RecordingError, match="increasing"):
        recording.write(tmp_path / "bad.h5", rec)
    assert not any(tmp_path.iterdir())  # nothing half-written left behind
