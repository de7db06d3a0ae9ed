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
    with h5py.File(rec_path) as f:  # layout of docs/design.md §3
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
    (lambda f: _replace(f, "gyro/rate", np.full((50, 3), np.nan, np.float32)), "gyro/rate",
     "nan at sample 0"),
    # finite float64 beyond float32: was called "NaN or infinite" after a cast that numpy warned about
    (lambda f: _replace(f, "gyro/rate", np.r_[np.zeros((7, 3)), np.full((43, 3), -1e300)]), "gyro/rate",
     "value -1e+300 at sample 7: expected finite rad/s within float32's range"),
])
@pytest.mark.filterwarnings("error")            # nothing numpy or h5py warns about on the way
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


@pytest.mark.parametrize("group, key, value, expected", [
    ("gyro", "R_cam_gyro", np.zeros((3, 3)), "rotation matrix"),
    ("gyro", "scale", np.zeros(3), "(0, 100]"),
    ("camera", "frame_rate_hz", 0.0, "(0, 10000] Hz"),
    ("camera", "pixel_pitch_um", 0.0, "(0, 1000] µm"),
    ("camera", "psf_beta", 0.0, "(0, 1]"),
    ("camera", "width", 64.7, "integer"),
    ("camera", "fx", "abc", "number"),
    ("gyro", "rate_hz", np.nan, "finite"),
])
def test_attributes_are_range_checked_like_a_config(rec_path, group, key, value, expected):
    _damage(rec_path, lambda f: f[group].attrs.__setitem__(key, value))
    with pytest.raises(RecordingError) as e:
        recording.read(rec_path)
    assert e.value.field == f"{group}.attrs['{key}']" and expected in e.value.problem
    assert str(e.value).startswith(f"{rec_path}: {group}.attrs['{key}']: expected")


def test_declared_shape_is_checked_before_anything_is_allocated(tmp_path):
    """10×100000×100000 uint16 (186 GiB) declared in a file of a few kB: refused from the metadata."""
    p = tmp_path / "huge.h5"
    recording.write(p, small_recording())
    with h5py.File(p, "a") as f:
        del f["camera/frames"]
        f.create_dataset("camera/frames", (10, 100000, 100000), np.uint16, chunks=(1, 64, 64))
        f["camera"].attrs["width"] = 100000
        f["camera"].attrs["height"] = 100000
    with pytest.raises(RecordingError, match=r"camera\.attrs\['width'\]: expected an integer in \[1, 16384"):
        recording.read(p)
    with h5py.File(p, "a") as f:       # attributes in range, shape declared beyond them
        f["camera"].attrs["width"], f["camera"].attrs["height"] = 8, 6
    with pytest.raises(RecordingError, match=r"camera/frames: expected uint16 .* = \[N, 6, 8"):
        recording.read(p)
    with h5py.File(p, "a") as f:       # shape consistent, data never written: 4 GB of nothing
        del f["camera/frames"], f["camera/t"]
        f.create_dataset("camera/frames", (100000, 6, 8), np.uint16, chunks=(1, 6, 8))
        f["camera/t"] = np.arange(1, 100001) * 0.02
    with pytest.raises(RecordingError, match=r"frames: declares shape \(100000, 6, 8\).*holds 0 bytes"):
        recording.read(p)


def test_times_stored_as_strings_name_the_dataset(rec_path):
    _damage(rec_path, lambda f: _replace(f, "camera/t", np.array([b"a", b"b", b"c", b"d"])))
    with pytest.raises(RecordingError, match=r"camera/t: expected .*got dtype \|S1"):
        recording.read(rec_path)


def _flip_bytes_of_frame(path, i):
    """Corrupt frame `i`'s chunk on disk (as a failing card would): the file stays readable HDF5."""
    with h5py.File(path, "r") as f:
        ds = f["camera/frames"]
        offset = ds.id.get_chunk_info(i).byte_offset
    with open(path, "r+b") as fh:
        fh.seek(offset)
        fh.write(b"\xff" * 4)


def test_reader_iterates_frames_one_at_a_time(rec_path):
    src = small_recording()
    with recording.Reader(rec_path) as r:
        assert len(r) == 4 and r.frame_shape == (6, 8) and r.calibration == src.calibration
        frames = list(r)
        assert all(fr.shape == (6, 8) and fr.dtype == np.uint16 for fr in frames)
        np.testing.assert_array_equal(np.stack(frames), src.frames)
        np.testing.assert_array_equal(r.gyro_rate, src.gyro_rate)
        assert sorted(r.names()) == ["camera/frame_id", "truth/frames"]


def test_compressed_frame_damage_names_the_frame(tmp_path):
    p = tmp_path / "gz.h5"
    recording.write(p, small_recording())
    with h5py.File(p, "a") as f:       # a gzip-compressed stack, as other writers may produce
        frames = f["camera/frames"][()]
        del f["camera/frames"]
        f.create_dataset("camera/frames", data=frames, chunks=(1, 6, 8), compression="gzip")
    _flip_bytes_of_frame(p, 2)
    with recording.Reader(p) as r:
        r.frame(1)
        with pytest.raises(RecordingError, match=r"gz\.h5: camera/frames: frame 2: cannot be read"):
            r.frame(2)
    with pytest.raises(RecordingError, match="frame 2"):
        recording.read(p)


def test_writer_appends_sorts_and_renames_only_when_complete(tmp_path):
    p = tmp_path / "w.h5"
    p.write_bytes(b"an earlier recording")
    src = small_recording()
    w = recording.Writer(p)
    w.reserve("camera/frames", 10, (6, 8), np.uint16)        # more room than used: trimmed
    for i in (2, 0, 1, 1, 3):                                # out of order, and one repeat
        w.append_frame(src.frames[i], src.t[i])
        w.append("camera/id", i, np.int64)                   # kept in step with the frames
    w.put("gyro/t", src.gyro_t)
    w.put("gyro/rate", src.gyro_rate)
    assert p.read_bytes() == b"an earlier recording"        # untouched until commit
    assert w.sort_frames() == 1
    w.commit(src.calibration)
    back = recording.read(p)
    np.testing.assert_array_equal(back.frames, src.frames)
    np.testing.assert_array_equal(back.t, src.t)
    assert back.extras["camera/id"].tolist() == [0, 1, 2, 3]
    assert not w.part.exists()
    with recording.Writer(tmp_path / "x.h5") as w2:          # an error before commit: nothing left
        w2.append_frame(src.frames[0], 1.0)
    assert not any(q.name.startswith("x.h5") for q in tmp_path.iterdir())


def test_writer_refuses_frames_of_another_camera(tmp_path):
    src = small_recording()
    w = recording.Writer(tmp_path / "w.h5")
    w.append_frame(src.frames[0], 0.1)
    w.put("gyro/t", src.gyro_t)
    w.put("gyro/rate", src.gyro_rate)
    with pytest.raises(RecordingError, match=r"w\.h5: camera/frames: frame shape \(6, 8\) does not match"):
        w.commit(Calibration(width=16, height=12, cx=7.5, cy=5.5))
    w.abort(keep=True)
    assert w.part.exists() and not (tmp_path / "w.h5").exists()
