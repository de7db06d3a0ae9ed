"""Property-based fuzzing of the wire-v1 decoder: whatever arrives, only MessageError escapes."""

import json

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod.io.wire import GYRO_LAYOUT_DTYPES, MessageError, decode, encode_header, pack_gyro

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _valid_frame(h=3, w=4):
    head = {"v": 1, "seq": 0, "t": 1.0, "published": 1.0, "deblurred": True, "shape": [h, w], "dtype": "<f4"}
    return [b"frame", encode_header(head), np.arange(h * w, dtype="<f4").tobytes()]


def _valid_gyro(n=3):
    fields, payload = pack_gyro(np.arange(n, dtype=float), np.ones((n, 3)))
    head = {"v": 1, "seq": 4, "t": 2.0, "published": 2.0, "deblurred": False, "sample_seq": 0, **fields}
    return [b"gyro", encode_header(head), payload]


def _decode_or_message_error(frames):
    try:
        topic, header, array = decode(frames)
    except MessageError as e:
        assert e.kind in {"framing", "topic", "header_size", "json", "version", "header", "dtype", "shape",
                          "layout", "payload_size"}
        return None
    # what passes is consistent: the header describes the array it came with
    assert isinstance(header, dict) and not array.flags.writeable
    if header["dtype"] == "packed":
        assert topic == "gyro" and array.shape == (header["shape"][0],)
        assert set(array.dtype.names) == set(GYRO_LAYOUT_DTYPES)
    else:
        assert list(array.shape) == header["shape"] and array.dtype.str == header["dtype"]
    return topic


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=5),
    max_leaves=20)
header_keys = st.sampled_from(["v", "seq", "t", "published", "deblurred", "shape", "dtype", "layout", "n"])


@FUZZ
@given(st.lists(st.binary(max_size=96), max_size=5))
def test_random_frames(frames):
    _decode_or_message_error(frames)


@FUZZ
@given(st.sampled_from(["frame", "gyro"]), st.dictionaries(header_keys, json_values, max_size=4),
       st.lists(header_keys, max_size=3), st.integers(-8, 8))
def test_mutated_headers(which, replace, delete, payload_delta):
    """A valid message whose header fields are replaced by arbitrary JSON, deleted, and whose payload
    is cut or padded."""
    topic, raw_header, payload = _valid_frame() if which == "frame" else _valid_gyro()
    head = json.loads(raw_header)
    head.update(replace)
    for k in delete:
        head.pop(k, None)
    payload = payload[:payload_delta] if payload_delta < 0 else payload + bytes(payload_delta)
    text = json.dumps(head, allow_nan=True)          # NaN/Infinity literals are part of the fuzz
    _decode_or_message_error([topic, text.encode(), payload])


@FUZZ
@given(st.sampled_from(["frame", "gyro"]), st.data())
def test_byte_flips_and_truncations(which, data):
    frames = _valid_frame() if which == "frame" else _valid_gyro()
    part = data.draw(st.integers(0, 2))
    buf = bytearray(frames[part])
    if buf and data.draw(st.booleans()):
        for _ in range(data.draw(st.integers(1, 4))):
            i = data.draw(st.integers(0, len(buf) - 1))
            buf[i] = data.draw(st.integers(0, 255))
    else:
        buf = buf[:data.draw(st.integers(0, len(buf)))]
    frames[part] = bytes(buf)
    _decode_or_message_error(frames)


@FUZZ
@given(st.lists(st.one_of(st.binary(max_size=16), st.integers(), st.none(), st.text(max_size=4),
                          st.lists(st.integers(0, 255), max_size=3)), min_size=3, max_size=3))
def test_frames_of_the_wrong_type(frames):
    """Not bytes at all (a caller's bug or a foreign transport): still only MessageError."""
    _decode_or_message_error(frames)


def test_the_fuzz_targets_accept_valid_messages():
    """The mutations start from messages that decode; otherwise the fuzzing above tests nothing."""
    assert _decode_or_message_error(_valid_frame()) == "frame"
    assert _decode_or_message_error(_valid_gyro()) == "gyro"


def test_the_codec_imports_no_transport():
    import subprocess
    import sys
    code = "import sys, thermod.io.wire; print(sorted(m for m in sys.modules if m.split('.')[0] == 'zmq'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
