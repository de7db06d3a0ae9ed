"""`thermod import` of damaged and malformed MCAP files: bytes flipped or overwritten anywhere, a chunk
whose CRC or compressed data is wrong, a summary section damaged, schemas that do not parse or do not
match their messages, messages of another encoding, images whose geometry disagrees with their data,
and a `thermod` calibration record that is not a calibration. Each is refused with exit status 2 and
an error naming the file, or imported exactly (never a frame or sample the file did not hold)."""

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer
from mcap_ros2._dynamic import serialize_dynamic

from thermod import cli
from thermod.io import mcap, recording
from thermod.physics.calibration import Calibration

H, W, N, PER = 6, 8, 5, 10          # frame size, frames, gyro samples per frame
CALIB = Calibration(width=W, height=H, cx=3.5, cy=2.5, fx=20.0, fy=20.0, tau_s=0.01)
ENCODE = {name: serialize_dynamic(name, text)[name] for name, text in mcap.MSGDEFS.items()}


def frame(i: int) -> np.ndarray:
    return ((np.arange(H * W).reshape(H, W) * 7 + 1009 * i) % 60000).astype(np.uint16)


def thermod_file(path, compress: bool):
    """N frames (frame(i) at 1 + 0.02 i s) and N·PER gyro samples (rate 0.1 k rad/s), thermod's writer."""
    w = mcap.McapWriter(path, compress=compress)
    for i in range(N):
        t = 1.0 + 0.02 * i
        w.raw(frame(i), t, i)
        w.camera_info(CALIB, t, i)
        w.gyro(t - 0.02 + np.arange(PER) * 2e-3, np.full((PER, 3), 0.1 * i), PER * i)
    w.metadata(CALIB)
    w.commit()
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("damage")
    return {c: thermod_file(d / f"{c}.mcap", c == "lz4").read_bytes() for c in ("none", "lz4")}


def run_import(tmp_path, data: bytes, capsys, name="in.mcap", *extra) -> tuple[int, str, object]:
    """(exit status, stderr, the imported recording or None); 2 names the file and leaves nothing."""
    src, out = tmp_path / name, tmp_path / "out.h5"
    src.write_bytes(data)
    out.unlink(missing_ok=True)
    capsys.readouterr()
    rc = cli.main(["import", str(src), "-o", str(out), *extra])
    err = capsys.readouterr().err
    assert rc in (0, 2), err
    assert "Traceback" not in err and "internal error" not in err, err
    if rc == 2:
        assert f"{src}: " in err and not out.exists(), err
        assert not (tmp_path / "out.h5.part").exists(), err
        return rc, err, None
    return rc, err, recording.read(out)


def assert_exact(rec) -> None:
    """Every imported frame and gyro sample is one the file was written with, at its time."""
    for t, f in zip(rec.t, rec.frames, strict=True):
        i = int(round((t - 1.0) / 0.02))
        assert 0 <= i < N and abs(t - (1.0 + 0.02 * i)) < 1e-9 and np.array_equal(f, frame(i))
    k = np.floor((rec.gyro_t - 0.98) / 0.02 + 1e-6).astype(int)
    assert np.all((0 <= k) & (k < N)) and np.allclose(rec.gyro_rate, 0.1 * k[:, None], atol=1e-6)


def chunk_at(data: bytes) -> list[int]:
    """Where each Chunk record of `data` starts."""
    out, pos = [], len(mcap.MAGIC)
    while pos < len(data) - len(mcap.MAGIC):
        if data[pos] == 0x06:
            out.append(pos)
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    return out


# ------------------------------------------------------------------------------- damaged bytes
damage = st.lists(st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
    st.tuples(st.just("region"), st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=64)),
), min_size=1, max_size=4)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["none", "lz4"]), changes=damage)
@example(kind="lz4", changes=[("flip", 0.25, 0), ("region", 0.00390625, b"\x01")])   # LZ4F RuntimeError
def test_damaged_bytes_are_refused_or_imported_exactly(files, tmp_path, capsys, kind, changes):
    """Bytes flipped or overwritten anywhere: a chunk's records no longer match their CRC (refused),
    the summary section is damaged (the data section is read instead), or a field nothing depends on
    changed; whatever is imported is what was written."""
    b = bytearray(files[kind])
    for what, at, v in changes:
        i = int(at * len(b))
        if what == "flip":
            b[i] = v
        else:
            b[i:i + len(v)] = v[:len(b) - i]
    rc, err, rec = run_import(tmp_path, bytes(b), capsys)
    event(f"exit {rc}")
    if rc == 0:
        assert_exact(rec)


@pytest.mark.parametrize("kind", ["none", "lz4"])
def test_a_chunk_whose_crc_does_not_match_is_refused(files, tmp_path, capsys, kind):
    b = bytearray(files[kind])
    at = chunk_at(b)[0]
    struct.pack_into("<I", b, at + 9 + 24, 0x12345678)     # after start, end time, uncompressed size
    rc, err, _ = run_import(tmp_path, bytes(b), capsys)
    assert rc == 2 and "CRC-32" in err and "not the 0x12345678 it stores" in err, err


def test_a_pixel_flipped_inside_an_uncompressed_chunk_is_refused(files, tmp_path, capsys):
    """The library does not check chunk CRCs by default: the flipped pixel was imported as it was."""
    b = bytearray(files["none"])
    at = bytes(b).index(frame(2).tobytes())
    b[at + 5] ^= 0x40
    rc, err, _ = run_import(tmp_path, bytes(b), capsys)
    assert rc == 2 and "damaged" in err, err


def test_lz4_data_that_does_not_decompress_is_refused(files, tmp_path, capsys):
    b = bytearray(files["lz4"])
    at = chunk_at(b)[0]
    b[at + 80:at + 96] = bytes(range(16))
    rc, err, _ = run_import(tmp_path, bytes(b), capsys)
    assert rc == 2 and "the chunk ending at byte" in err, err


def test_a_damaged_summary_is_passed_over_for_the_data_section(files, tmp_path, capsys, caplog):
    """The summary repeats the schemas and channels: one of them damaged (here a schema's text, which
    then did not parse, an internal error) is detected by the footer's CRC and the data read instead."""
    b = bytearray(files["lz4"])
    footer_at = len(b) - len(mcap.MAGIC) - 29
    start = struct.unpack_from("<Q", b, footer_at + 9)[0]
    at = bytes(b).index(b"uint32 height", start)
    b[at:at + 6] = b"uint3 "
    rc, err, rec = run_import(tmp_path, bytes(b), capsys)
    assert rc == 0 and "summary section is damaged" in caplog.text, err
    assert rec.n_frames == N and len(rec.gyro_t) == N * PER
    assert_exact(rec)


# ------------------------------------------------------------------------ malformed, undamaged files
def image(t: float, h=H, w=W, encoding="16UC1", step=None, data=None) -> dict:
    return {"header": {"stamp": mcap.stamp(t), "frame_id": "cam"}, "height": h, "width": w,
            "encoding": encoding, "is_bigendian": 0, "step": 2 * w if step is None else step,
            "data": frame(int(round((t - 1) / 0.02))).tobytes() if data is None else data}


def imu(t: float, rate=(0.1, 0.2, 0.3)) -> dict:
    return {"header": {"stamp": mcap.stamp(t), "frame_id": "gyro"},
            "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
            "orientation_covariance": [0.0] * 9, "angular_velocity": dict(zip("xyz", rate, strict=True)),
            "angular_velocity_covariance": [0.0] * 9, "linear_acceleration": {"x": 0, "y": 0, "z": 0},
            "linear_acceleration_covariance": [0.0] * 9}


def bag_bytes(path, images=None, *, schemas=None, encodings=None, meta=None, huge=0) -> bytes:
    """An MCAP written by the mcap library (not thermod): raw frames and gyro samples, the schema
    texts (`schemas`: type → text) and message encodings (`encodings`: topic → name) as given; the
    first `huge` gyro samples 1e300 rad/s about x."""
    images = [image(1.0 + 0.02 * i) for i in range(N)] if images is None else images
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile=Profile.ROS2, library="test")
        ids = {name: w.register_schema(name, SchemaEncoding.ROS2, (schemas or {}).get(name, text).encode())
               for name, text in mcap.MSGDEFS.items()}
        ch = {topic: w.register_channel(topic, (encodings or {}).get(topic, MessageEncoding.CDR), ids[kind])
              for topic, kind in ((mcap.RAW_TOPIC, mcap.IMAGE), (mcap.IMU_TOPIC, mcap.IMU))}
        msgs = [(m, mcap.RAW_TOPIC, mcap.IMAGE) for m in images]
        msgs += [(imu(0.99 + 0.002 * k, (1e300 if k < huge else 0.1, 0.2, 0.3)), mcap.IMU_TOPIC, mcap.IMU)
                 for k in range(N * PER)]
        msgs.sort(key=lambda m: (m[0]["header"]["stamp"]["sec"], m[0]["header"]["stamp"]["nanosec"]))
        for seq, (m, topic, kind) in enumerate(msgs):
            ns = m["header"]["stamp"]["sec"] * 10**9 + m["header"]["stamp"]["nanosec"]
            w.add_message(ch[topic], log_time=ns, data=ENCODE[kind](m), publish_time=ns, sequence=seq)
        meta = {"calibration": json.dumps(CALIB.as_dict())} if meta is None else meta
        w.add_metadata(mcap.METADATA_NAME, meta)
        w.finish()
    return path.read_bytes()


@pytest.mark.parametrize(("schemas", "expect"), [
    ({mcap.IMAGE: "this is ::: not a definition\n"}, "not a valid ros2msg definition"),
    ({mcap.IMU: mcap.MSGDEFS[mcap.IMAGE]}, "/imu/data"),          # named Imu, defines an Image
    ({mcap.IMU: ""}, "/imu/data"),
    ({mcap.IMAGE: mcap.MSGDEFS[mcap.CAMERA_INFO]}, "/thermal/image_raw"),
    ({mcap.IMAGE: "uint64 extra\n" + mcap.MSGDEFS[mcap.IMAGE]}, "/thermal/image_raw"),
])
def test_a_schema_that_does_not_match_its_messages_is_refused(tmp_path, capsys, schemas, expect):
    """A schema that does not parse was an internal error (the vendored rosidl parser's exceptions and
    prints to stderr); one that parses into another type, an AttributeError for a missing field."""
    rc, err, _ = run_import(tmp_path, bag_bytes(tmp_path / "b.mcap", schemas=schemas), capsys)
    assert rc == 2 and expect in err, err
    assert "Error with" not in err and "Error processing" not in err, err


@pytest.mark.parametrize("encoding", ["json", "protobuf", "ros1"])
def test_messages_of_another_encoding_are_refused(tmp_path, capsys, encoding):
    data = bag_bytes(tmp_path / "b.mcap", encodings={mcap.IMU_TOPIC: encoding})
    rc, err, _ = run_import(tmp_path, data, capsys)
    assert rc == 2 and encoding in err, err


@pytest.mark.parametrize(("kw", "expect"), [
    ({"step": 0}, "step 0 is less than a row"), ({"step": W}, "step 8 is less than a row"),
    ({"step": 10**9}, "height × step"), ({"h": 0, "data": b""}, "must be positive"),
    ({"h": 2**31, "data": b"\0" * 100}, "height × step"), ({"data": b"\0" * 10}, "data holds 10 bytes"),
    ({"encoding": "rgb8"}, "a colour image"),
    ({"h": W, "w": H, "step": 2 * H}, "6×8"),                     # the calibration's 8×6 turned round
    ({"h": 2000, "w": 1, "step": 2, "data": b"\0" * 4000}, "1×2000"),
])
def test_an_image_whose_geometry_disagrees_is_refused(tmp_path, capsys, kw, expect):
    """Geometry that does not fit its data, or frames of another size than the calibration's: the
    latter was reported against the output file and its .part (which was removed)."""
    images = [image(1.0 + 0.02 * i, **kw) for i in range(N)]
    rc, err, _ = run_import(tmp_path, bag_bytes(tmp_path / "b.mcap", images), capsys)
    assert rc == 2 and expect in err and "/thermal/image_raw" in err, err
    assert ".part" not in err, err


@pytest.mark.parametrize(("text", "expect"), [
    ("{not json", "unusable"), ("[1, 2]", "expected a JSON object"), ('"x"', "expected a JSON object"),
    ("[" * 100000 + "]" * 100000, "unusable"),
    (json.dumps({**CALIB.as_dict(), "width": 10**400}), "width"),
    (json.dumps({**CALIB.as_dict(), "fx": float("nan")}), "fx"),
    (json.dumps({**CALIB.as_dict(), "width": 9}), "8×6"),
])
def test_a_thermod_calibration_record_that_is_not_one_is_refused(tmp_path, capsys, text, expect):
    """A list, a deep nesting or a huge integer were a silent default calibration, a RecursionError
    and an OverflowError; a width not the frames' was reported against the output's .part."""
    data = bag_bytes(tmp_path / "b.mcap", meta={"calibration": text})
    rc, err, _ = run_import(tmp_path, data, capsys)
    assert rc == 2 and expect in err and ".part" not in err, err


def test_what_is_reported_is_what_was_written(tmp_path, capsys):
    """Gyro samples beyond float32 are dropped as non-finite (with a numpy overflow warning before) and
    frames of a repeated time once: the summary counted what was received, not what was written."""
    images = [image(1.0 + 0.02 * min(i, 3)) for i in range(N)]       # the last two repeat a time
    data = bag_bytes(tmp_path / "b.mcap", images, huge=7)
    rc, err, rec = run_import(tmp_path, data, capsys)
    out = capsys.readouterr().out
    assert rc == 0 and "RuntimeWarning" not in err, err
    assert rec.n_frames == 4 and len(rec.gyro_t) == N * PER - 7
    assert cli.main(["import", str(tmp_path / "in.mcap"), "-o", str(tmp_path / "again.h5")]) == 0
    out = capsys.readouterr().out
    assert f"4 frames from {mcap.RAW_TOPIC}, {N * PER - 7} gyro samples" in out, out


def test_an_imu_topic_with_no_finite_rate_is_refused(tmp_path, capsys):
    """Every sample beyond float32 (or NaN): the import used to write a recording with no gyro at
    all, with a warning, that every later command could only pass through."""
    rc, err, _ = run_import(tmp_path, bag_bytes(tmp_path / "b.mcap", huge=N * PER), capsys)
    assert rc == 2 and mcap.IMU_TOPIC in err and "finite angular_velocity" in err, err
    assert not (tmp_path / "out.h5").exists() and ".part" not in err, err
