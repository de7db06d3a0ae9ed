"""`thermod import` of bags written by writers thermod does not own — rosbags' ROS 1 and rosbag2
(sqlite3, mcap) writers and mcap-ros2-support's — as a payload's ROS drivers fill them: each is
imported, or refused naming the file, the topic or field and what was expected."""

import shutil

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from thermod import cli
from thermod.io import mcap, recording

H, W = 12, 16
WRITERS = ("ros1", "sqlite3", "mcap-storage", "mcap_ros2")
ROS1, ROS2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)
COMPRESSED_DEF = "std_msgs/Header header\nstring format\nuint8[] data\n" + mcap._SEP + mcap._HEADER


def _hdr(t):
    ns = round(t * 1e9)
    return {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "cam"}


def frame(t, enc="mono16", *, h=H, w=W, pad=0, big=False, stamp=None):
    """(counts, Image fields): a mono16 frame as a driver writes it (rows padded by `pad` bytes)."""
    f = (np.arange(h * w).reshape(h, w) * 97 + round(t * 1000)).astype(np.uint16)
    bpp = {"mono16": 2, "16UC1": 2, "mono8": 1, "8UC1": 1, "32FC1": 4}.get(enc, 3)
    if bpp == 2:
        rows = f.astype(">u2" if big else "<u2").view(np.uint8).reshape(h, 2 * w)
    else:
        f = (f % 256).astype(np.uint8)
        rows = np.repeat(f, bpp, axis=1)
    data = np.ascontiguousarray(np.pad(rows, ((0, 0), (0, pad)))).ravel()
    return f, {"header": _hdr(t if stamp is None else stamp), "height": h, "width": w, "encoding": enc,
               "is_bigendian": int(big), "step": bpp * w + pad, "data": data}


def imu(t, rate=(0.1, -0.2, 0.3), stamp=None):
    return {"header": _hdr(t if stamp is None else stamp),
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": np.r_[-1.0, np.zeros(8)],      # no orientation estimate
            "angular_velocity": dict(zip("xyz", rate, strict=True)),
            "angular_velocity_covariance": np.zeros(9),
            "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 9.8},
            "linear_acceleration_covariance": np.zeros(9)}


def info(t, k=(20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1), h=H, w=W, model="plumb_bob", d=(0.0,) * 5):
    return {"header": _hdr(t), "height": h, "width": w, "distortion_model": model, "d": np.array(d, float),
            "k": np.array(k, float), "r": np.eye(3).ravel(), "p": np.zeros(12),
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


def scene(*, frame_fn=None, imu_fn=None, n=5, gyro_hz=500.0, extra=()):
    """Messages (topic, type, log time s, fields) of a short take: `n` frames at 30 Hz, the IMU
    at `gyro_hz`, one CameraInfo; and the frames' counts."""
    t = 100.0 + np.arange(n) / 30.0
    msgs, frames = [], []
    for i, ti in enumerate(100.0 - 0.02 + np.arange(int((n / 30 + 0.04) * gyro_hz)) / gyro_hz):
        msgs.append(("/imu/data", "sensor_msgs/msg/Imu", ti, imu(ti) if imu_fn is None else imu_fn(i, ti)))
    for i, ti in enumerate(t):
        f, m = frame(ti) if frame_fn is None else frame_fn(i, ti)
        frames.append(f)
        msgs.append(("/thermal/image_raw", m.pop("_type", "sensor_msgs/msg/Image"), ti, m))
    msgs.append(("/thermal/camera_info", "sensor_msgs/msg/CameraInfo", t[0], info(t[0])))
    return sorted([*msgs, *extra], key=lambda m: m[2]), frames


def _typed(store, name, d, ros1):
    kw = {}
    for field, (kind, desc) in store.fielddefs[name][1]:
        if ros1 and field == "seq":
            kw[field] = 0
            continue
        v = d[field] if field in d else d[field.lower()]       # ROS 1 CameraInfo: D, K, R, P
        kw[field] = _typed(store, desc, v, ros1) if int(kind) == 2 else v   # 2: a nested message
    return store.types[name](**kw)


def _plain(d):
    if isinstance(d, dict):
        return {k: bytes(v) if k == "data" else _plain(v) for k, v in d.items()}
    return d.tolist() if isinstance(d, np.ndarray) else d


def write_bag(path_stem, writer, msgs):
    """The bag of `msgs` written by `writer` (one of WRITERS); its path."""
    types = dict((m[0], m[1]) for m in msgs)
    if writer == "mcap_ros2":
        from mcap_ros2.writer import Writer

        path = path_stem.with_suffix(".mcap")
        defs = {**mcap.MSGDEFS, "sensor_msgs/msg/CompressedImage": COMPRESSED_DEF}
        with open(path, "wb") as f:
            w = Writer(f)
            schemas = {t: w.register_msgdef(t, defs[t]) for t in set(types.values())}
            for topic, typ, ts, d in msgs:
                w.write_message(topic, schemas[typ], _plain(d), log_time=round(ts * 1e9))
            w.finish()
        return path
    if writer == "ros1":
        from rosbags.rosbag1 import Writer

        path, store, w = path_stem.with_suffix(".bag"), ROS1, Writer(path_stem.with_suffix(".bag"))
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.SQLITE3 if writer == "sqlite3" else StoragePlugin.MCAP
        path, store, w = path_stem, ROS2, Writer(path_stem, version=9, storage_plugin=plugin)
    with w:
        conns = {t: w.add_connection(t, typ, typestore=store) for t, typ in types.items()}
        for topic, typ, ts, d in msgs:
            m = _typed(store, typ, d, writer == "ros1")
            data = store.serialize_ros1(m, typ) if writer == "ros1" else store.serialize_cdr(m, typ)
            w.write(conns[topic], round(ts * 1e9), data)
    return path


@pytest.fixture
def run(tmp_path, capsys, caplog):
    """run(bag, *args) → (exit status, stderr and warnings); a failed import leaves nothing at its
    output."""
    def go(bag, *args):
        out = tmp_path / "out.h5"
        out.unlink(missing_ok=True)
        caplog.clear()
        with caplog.at_level("WARNING"):
            status = cli.main(["import", str(bag), "-o", str(out), *map(str, args)])
        err = capsys.readouterr().err + caplog.text
        if status != 0:
            assert not out.exists() and not out.with_name("out.h5.part").exists()
        return status, err
    return go


# ------------------------------------------------------------------------------------------ frames
@pytest.mark.parametrize("writer", WRITERS)
def test_driver_layouts_of_counts_are_read_exactly(tmp_path, run, writer):
    """mono16 big-endian with padded rows, 16UC1, mono8 (widened): the counts, not the padding."""
    for name, fn in (("pad", lambda i, t: frame(t, pad=6, big=True)),
                     ("u16", lambda i, t: frame(t, "16UC1", pad=3)),
                     ("mono8", lambda i, t: frame(t, "mono8", pad=5))):
        msgs, frames = scene(frame_fn=fn)
        assert run(write_bag(tmp_path / name, writer, msgs), "--tau", 0.01)[0] == 0, name
        rec = recording.read(tmp_path / "out.h5")
        assert rec.frames.dtype == np.uint16 and np.array_equal(rec.frames, frames), name


@pytest.mark.parametrize("enc, kind", [("rgb8", "a colour image"), ("bgr8", "a colour image"),
                                       ("32FC1", "float values"), ("bayer_rggb8", "a Bayer colour mosaic"),
                                       ("yuv422", "a YUV colour image")])
def test_frames_that_are_not_counts_are_refused_by_encoding(tmp_path, run, enc, kind):
    msgs, _ = scene(frame_fn=lambda i, t: frame(t, enc))
    status, err = run(write_bag(tmp_path / "b", "mcap_ros2", msgs), "--tau", 0.01)
    assert status == 2 and f"/thermal/image_raw: image encoding '{enc}': {kind}" in err
    assert "mono16, 16UC1, mono8, 8UC1 expected" in err


@pytest.mark.parametrize("writer", ["ros1", "mcap_ros2"])
def test_image_geometry_that_cannot_hold_the_frame_is_named(tmp_path, run, writer):
    cases = {
        "step": (lambda i, t: (None, {**frame(t)[1], "step": W}),
                 f"image {W}×{H} mono16: step {W} is less than a row's {2 * W} bytes"),
        "h0": (lambda i, t: (None, {**frame(t)[1], "height": 0, "data": np.zeros(0, np.uint8)}),
               f"image {W}×0 mono16: height and width must be positive"),
        "w0": (lambda i, t: (None, {**frame(t)[1], "width": 0, "step": 0}),
               f"image 0×{H} mono16: height and width must be positive"),
        "short": (lambda i, t: (None, {**frame(t)[1], "data": np.zeros(7, np.uint8)}),
                  f"image {W}×{H} mono16: data holds 7 bytes, height × step = {H} × {2 * W} = "
                  f"{2 * H * W} expected"),
    }
    for name, (fn, says) in cases.items():
        status, err = run(write_bag(tmp_path / name, writer, scene(frame_fn=fn)[0]), "--tau", 0.01)
        assert status == 2 and f"/thermal/image_raw: {says}" in err, (name, err)


def test_frames_that_change_depth_or_size_midway_are_refused(tmp_path, run):
    """A driver switched from 16-bit to 8-bit output (or to another size) while recording."""
    for name, fn, says in (
        ("depth", lambda i, t: frame(t, "mono8" if i >= 2 else "mono16"), f"{W}×{H} mono16 to {W}×{H} mono8"),
        ("size", lambda i, t: frame(t, h=H // 2 if i >= 3 else H), f"{W}×{H} mono16 to {W}×{H // 2} mono16"),
    ):
        status, err = run(write_bag(tmp_path / name, "sqlite3", scene(frame_fn=fn)[0]), "--tau", 0.01)
        assert status == 2 and f"/thermal/image_raw: frames change from {says}" in err, (name, err)


@pytest.mark.parametrize("writer", ["ros1", "mcap_ros2"])
def test_compressed_image_topics_are_named(tmp_path, run, writer):
    """A driver publishing PNG (16-bit) or JPEG through image_transport: not decoded, and said so."""
    png = bytes.fromhex("89504e470d0a1a0a")
    msgs, _ = scene(frame_fn=lambda i, t: (None, {
        "_type": "sensor_msgs/msg/CompressedImage", "header": _hdr(t), "format": "mono16; png compressed ",
        "data": np.frombuffer(png, np.uint8)}))
    bag = write_bag(tmp_path / "b", writer, msgs)
    status, err = run(bag, "--tau", 0.01)
    assert status == 2 and "no sensor_msgs/msg/Image topic" in err
    assert "/thermal/image_raw: sensor_msgs/msg/CompressedImage (PNG or JPEG frames" in err
    status, err = run(bag, "--tau", 0.01, "--image-topic", "/thermal/image_raw")
    assert status == 2 and "expected sensor_msgs/msg/Image (PNG or JPEG frames" in err


def test_several_image_or_imu_topics(tmp_path, run):
    """raw + colourised topics: the usual raw name is taken, else the choice is the user's; two IMUs,
    the same."""
    colour = [("/thermal/image_color", "sensor_msgs/msg/Image", t, frame(t, "rgb8")[1])
              for t in 100.0 + np.arange(5) / 30]
    second = [("/px4/imu", "sensor_msgs/msg/Imu", 99.99 + i / 200, imu(99.99 + i / 200)) for i in range(30)]
    msgs = scene(extra=colour + second)[0]
    assert run(write_bag(tmp_path / "usual", "ros1", msgs), "--tau", 0.01)[0] == 0
    attrs = recording.read(tmp_path / "out.h5").extra_attrs["record"]
    assert (attrs["image_topic"], attrs["imu_topic"]) == ("/thermal/image_raw", "/imu/data")
    renamed = {"/thermal/image_raw": "/boson/image_raw", "/imu/data": "/vn100/imu"}
    bag = write_bag(tmp_path / "odd", "ros1", [(renamed.get(m[0], m[0]), *m[1:]) for m in msgs])
    status, err = run(bag, "--tau", 0.01)
    assert status == 2 and "Image topics ['/boson/image_raw', '/thermal/image_color']: choose one" in err
    status, err = run(bag, "--tau", 0.01, "--image-topic", "/boson/image_raw")
    assert status == 2 and "several sensor_msgs/msg/Imu topics ['/px4/imu', '/vn100/imu']" in err


# --------------------------------------------------------------------------------------------- clocks
@pytest.mark.parametrize("writer", WRITERS)
def test_unstamped_messages_take_the_log_time_and_say_so(tmp_path, run, writer):
    """Drivers that leave header stamps 0: every sample kept on the bag's log times (it kept one)."""
    msgs, frames = scene(frame_fn=lambda i, t: frame(t, stamp=0.0), imu_fn=lambda i, t: imu(t, stamp=0.0))
    status, err = run(write_bag(tmp_path / "b", writer, msgs), "--tau", 0.01)
    assert status == 0, err
    for topic in ("/thermal/image_raw", "/imu/data"):
        assert f"{topic}: header stamp 0 (the driver does not stamp its messages): the bag's log times" in err
    rec = recording.read(tmp_path / "out.h5")
    log_t = sorted(m[2] for m in msgs if m[0] == "/imu/data")
    assert np.array_equal(rec.frames, frames) and np.allclose(rec.t, 100.0 + np.arange(5) / 30, atol=1e-9)
    assert np.allclose(rec.gyro_t, log_t, atol=1e-9) and rec.calibration.rate_hz == pytest.approx(500.0)
    assert rec.extra_attrs["record"]["image_clock"] == rec.extra_attrs["record"]["imu_clock"] == "log time"


def test_zero_and_backward_stamps_among_stamped_ones_are_counted(tmp_path, run):
    def fn(i, t):
        return imu(t, stamp=0.0 if i in (10, 11) else t - 0.5 if i == 30 else t)
    msgs, _ = scene(imu_fn=fn)
    status, err = run(write_bag(tmp_path / "b", "mcap-storage", msgs), "--tau", 0.01)
    assert status == 0, err
    assert "/imu/data: 2 messages with header stamp 0 among stamped ones dropped" in err
    assert "/imu/data: 1 header stamps not after the one before (the first: message 31 at 99.540000 s" in err
    rec = recording.read(tmp_path / "out.h5")
    assert len(rec.gyro_t) == sum(m[0] == "/imu/data" for m in msgs) - 2 and np.all(np.diff(rec.gyro_t) > 0)
    assert rec.extra_attrs["record"]["imu_clock"] == "header stamp"


# ---------------------------------------------------------------------------------------- CameraInfo
@pytest.mark.parametrize("writer", ["ros1", "sqlite3"])
def test_camera_info_that_cannot_be_the_camera_model(tmp_path, run, writer):
    toml = tmp_path / "k.toml"
    toml.write_text("[calibration]\nfx = 30.0\nfy = 31.0\ntau_s = 0.01\n")
    for name, kw, says in (("zero", {"k": (0.0,) * 9}, "K is all zeros (what an uncalibrated camera driver"),
                           ("size", {"h": 480, "w": 640},
                            f"CameraInfo is for 640×480 images, the frames are {W}×{H}")):
        msgs, frames = scene()
        msgs = [(*m[:3], info(m[2], **kw)) if m[0] == "/thermal/camera_info" else m for m in msgs]
        bag = write_bag(tmp_path / name, writer, msgs)
        status, err = run(bag, "--tau", 0.01)
        assert status == 2 and f"/thermal/camera_info: {says}" in err and "give --calibration" in err, err
        status, err = run(bag, "--calibration", toml)       # the intrinsics given: imported with them
        assert status == 0 and f"/thermal/camera_info: {says}" in err, err
        c = recording.read(tmp_path / "out.h5").calibration
        assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (W, H, 30.0, 31.0, (W - 1) / 2, (H - 1) / 2)


def test_calibration_file_must_give_what_no_camera_info_gives(tmp_path, run):
    """No CameraInfo topic: a TOML without fx, fy (or without τ, no --tau) would import the default
    camera's as this one's."""
    msgs = [m for m in scene()[0] if m[0] != "/thermal/camera_info"]
    bag = write_bag(tmp_path / "b", "mcap_ros2", msgs)
    toml = tmp_path / "c.toml"
    toml.write_text("[calibration]\ntime_offset_s = 0.001\n")
    status, err = run(bag, "--calibration", toml, "--tau", 0.01)
    assert status == 2 and "no sensor_msgs/msg/CameraInfo topic to take the camera intrinsics from" in err
    assert f"{toml} gives no fx nor fy" in err
    toml.write_text("[calibration]\nfx = 30.0\nfy = 30.0\n")
    status, err = run(bag, "--calibration", toml)
    assert status == 2 and f"{toml} gives no tau_s: add them to its [calibration] table (τ: or give" in err
    assert run(bag, "--calibration", toml, "--tau", 0.01)[0] == 0


def test_distortion_model_is_named_when_ignored(tmp_path, run):
    msgs, _ = scene()
    fisheye = {"model": "equidistant", "d": (0.1, 0.0, 0.0, 0.0)}
    msgs = [(*m[:3], info(m[2], **fisheye)) if m[0] == "/thermal/camera_info" else m for m in msgs]
    status, err = run(write_bag(tmp_path / "b", "mcap_ros2", msgs), "--tau", 0.01)
    assert status == 0 and "/thermal/camera_info declares lens distortion (equidistant)" in err


# ------------------------------------------------------------------------------------- damaged bags
@pytest.mark.parametrize("damage", ["missing", "garbage", "empty"])
def test_rosbag2_without_a_readable_metadata_yaml(tmp_path, run, damage):
    """`ros2 bag record` writes metadata.yaml last: a killed one leaves none. mcap storage: its one
    .mcap is read on its own; sqlite3: refused, naming the fix."""
    msgs, frames = scene()
    for writer in ("mcap-storage", "sqlite3"):
        bag = write_bag(tmp_path / writer, writer, msgs)
        meta = bag / "metadata.yaml"
        if damage == "missing":
            meta.unlink()
        else:
            meta.write_bytes(b"{{{: ][\n\x00" if damage == "garbage" else b"")
        status, err = run(bag, "--tau", 0.01)
        if writer == "mcap-storage":
            assert status == 0 and f"reading {writer}.mcap on its own" in err, err
            assert np.array_equal(recording.read(tmp_path / "out.h5").frames, frames)
        else:
            assert status == 2 and f"`ros2 bag reindex {bag}` rebuilds metadata.yaml from sqlite3.db3" in err
            assert "\n" not in err.strip()
            assert (damage == "missing") == ("metadata.yaml is missing" in err)
    shutil.rmtree(tmp_path / "sqlite3")
    (tmp_path / "sqlite3").mkdir()
    status, err = run(tmp_path / "sqlite3", "--tau", 0.01)
    assert status == 2 and "not a readable rosbag: no .db3 or .mcap file in it" in err


def test_a_db3_file_is_sent_to_its_directory(tmp_path, run):
    bag = write_bag(tmp_path / "b", "sqlite3", scene()[0])
    status, err = run(bag / "b.db3", "--tau", 0.01)
    assert status == 2 and f"a rosbag2 .db3 file is read through its directory: give {bag}" in err


@pytest.mark.parametrize("cut", [0.3, 0.9, None])
def test_unindexed_ros1_bag_says_so(tmp_path, run, cut):
    """A killed `rosbag record` leaves no index (written last): cut short, or index_pos 0."""
    bag = write_bag(tmp_path / "b", "ros1", scene()[0])
    data = bytearray(bag.read_bytes())
    if cut is None:
        i = data.find(b"index_pos=") + len(b"index_pos=")
        data[i:i + 8] = bytes(8)
    else:
        data = data[: int(len(data) * cut)]
    bag.write_bytes(bytes(data))
    status, err = run(bag, "--tau", 0.01)
    assert status == 2 and "b.bag: file: ROS 1 bag without a usable index: a recording killed" in err
    assert "`rosbag reindex b.bag` rebuilds it" in err
