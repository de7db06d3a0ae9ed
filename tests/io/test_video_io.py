"""thermod.io.video against real FFmpeg (PyAV) files: round trips, variable frame rates, 16-bit
video and TIFF sequences, every error class, and fuzzed bytes."""

import re
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod.errors import ThermodError
from thermod.io.video import (
    PercentileAGC,
    VideoError,
    VideoTooLarge,
    VideoWriter,
    iter_video,
    probe_video,
    read_video,
    write_video,
)

TB = Fraction(1, 1000)


def _encode(path, codec, pix_fmt, frames, pts_ms, fmt="gray", options=None):
    """Write frames with PyAV at the given presentation times (ms) — the way a camera's muxer does."""
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=25)
        s.height, s.width = frames.shape[1:3]
        s.pix_fmt, s.time_base = pix_fmt, TB
        s.codec_context.time_base = TB
        if options:
            s.options = options
        for f, p in zip(frames, pts_ms, strict=True):
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format=fmt)
            vf.pts, vf.time_base = int(p), TB
            for pk in s.encode(vf):
                c.mux(pk)
        for pk in s.encode():
            c.mux(pk)
    return Path(path)


def _vfr_times(n, rng, t0=12.5):
    return t0 + np.cumsum(rng.uniform(0.008, 0.05, n))


def _texture(n, h=120, w=160, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    top = 255 if dtype == np.uint8 else 65535
    return rng.integers(0, top, (n, h, w), dtype=dtype)


# ------------------------------------------------------------------------------------- round trips
def test_h264_round_trip_keeps_frames_and_variable_frame_rate(tmp_path):
    rng = np.random.default_rng(1)
    frames, t = _texture(24), _vfr_times(24, rng)
    out = write_video(tmp_path / "out.mp4", frames, t, crf=0)
    got = read_video(out)
    assert got.info.codec == "h264" and got.info.bit_depth == 8 and got.info.luma_only
    assert got.frames.dtype == np.uint8 and got.frames.shape == frames.shape
    assert np.array_equal(got.frames, frames)                     # crf 0, full-range luma: exact
    np.testing.assert_allclose(np.diff(got.t), np.diff(t), atol=2 / 90000)
    assert np.ptp(np.diff(t)) > 0.02                              # the intervals really vary


def test_written_video_is_playable_yuv420p_high_profile(tmp_path):
    frames = _texture(10, seed=2)
    out = write_video(tmp_path / "play.mp4", frames, np.arange(10) / 30.0)     # default crf 18
    with av.open(str(out)) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == "h264" and s.codec_context.profile == "High"
        assert s.codec_context.pix_fmt in ("yuv420p", "yuvj420p")
    got = read_video(out)
    assert np.median(np.abs(got.frames.astype(int) - frames)) <= 16     # lossy but the same picture


def test_odd_sides_are_padded_by_one_edge_row_and_column(tmp_path):
    frames = _texture(3, h=121, w=161, seed=3)
    got = read_video(write_video(tmp_path / "odd.mp4", frames, [0, 0.1, 0.2], crf=0))
    assert got.frames.shape == (3, 122, 162)
    assert np.array_equal(got.frames[:, :121, :161], frames)
    assert np.array_equal(got.frames[:, 121, :161], frames[:, 120])


def test_16bit_grey_video_ffv1_mkv_keeps_every_count_and_vfr_times(tmp_path):
    rng = np.random.default_rng(4)
    frames = _texture(12, dtype=np.uint16, seed=4)
    pts = np.cumsum(rng.integers(8, 60, 12))
    path = _encode(tmp_path / "raw16.mkv", "ffv1", "gray16le", frames, pts, fmt="gray16le")
    got = read_video(path)
    assert got.info.bit_depth == 16 and not got.info.luma_only and got.info.pix_fmt == "gray16le"
    assert got.frames.dtype == np.uint16 and np.array_equal(got.frames, frames)
    np.testing.assert_allclose(got.t, pts / 1000.0, atol=1e-9)


def test_10_12_16bit_formats_come_out_as_coded_in_uint16(tmp_path):
    counts = np.random.default_rng(15).integers(0, 4096, (3, 16, 32), dtype=np.uint16)    # 12-bit
    g12 = read_video(_encode(tmp_path / "g12.mkv", "ffv1", "gray12le", counts << 4, [0, 40, 80],
                             fmt="gray16le"))
    assert g12.info.pix_fmt == "gray12le" and g12.info.bit_depth == 16 and not g12.info.luma_only
    assert np.abs(g12.frames.astype(int) - counts).max() <= 1          # 12-bit values, not rescaled
    be = read_video(_encode(tmp_path / "be.nut", "rawvideo", "gray16be", counts * 16, [0, 40, 80],
                            fmt="gray16le"))
    assert be.info.pix_fmt == "gray16be" and np.array_equal(be.frames, counts * 16)
    y10 = read_video(_encode(tmp_path / "y10.mkv", "libx265", "yuv420p10le", counts << 4, [0, 40, 80],
                             fmt="gray16le", options={"x265-params": "lossless=1:log-level=error"}))
    assert y10.info.luma_only and y10.frames.dtype == np.uint16
    # 10-bit limited-range luma (64–940 as coded) as a player shows it: the full 10-bit range
    assert not y10.info.full_range and y10.frames.min() < 64 and 940 < y10.frames.max() <= 1023
    assert np.corrcoef(y10.frames.ravel(), counts.ravel())[0, 1] > 0.999


def test_8bit_grey_and_colour_codecs_give_grey_frames(tmp_path):
    frames = _texture(4, seed=5)
    g8 = read_video(_encode(tmp_path / "g8.mkv", "ffv1", "gray", frames, [0, 40, 80, 120]))
    assert not g8.info.luma_only and np.array_equal(g8.frames, frames)
    mj = read_video(_encode(tmp_path / "mj.avi", "mjpeg", "yuvj420p", frames, [0, 40, 80, 120],
                            options={"q:v": "2"}))
    assert mj.info.codec == "mjpeg" and mj.info.luma_only and mj.frames.dtype == np.uint8
    assert np.corrcoef(mj.frames.ravel(), frames.ravel())[0, 1] > 0.8
    hevc = read_video(_encode(tmp_path / "h265.mkv", "libx265", "yuv420p", frames, [0, 40, 80, 120],
                              options={"x265-params": "log-level=error:lossless=1"}))
    assert hevc.info.codec == "hevc" and hevc.frames.shape == frames.shape
    np.testing.assert_allclose(hevc.t, [0, 0.04, 0.08, 0.12])
    # luma as coded: swscale's full→limited range (16 + 219/255 · x), which a colour pipeline codes
    expected = 16 + frames.astype(float) * 219 / 255
    assert np.corrcoef(hevc.frames.ravel(), expected.ravel())[0, 1] > 0.9
    assert np.mean(hevc.frames) == pytest.approx(np.mean(expected), abs=3)


def test_a_variable_rate_faster_than_the_nominal_one_is_read_whole(tmp_path):
    """20 frames 10 ms apart in a stream declared at 25 fps: the header's duration counts the last frame
    as 40 ms and its rate would size 7 frames; neither is taken for truncation or a limit."""
    frames = _texture(20, h=16, w=32, seed=16)
    got = read_video(_encode(tmp_path / "fast.mkv", "ffv1", "gray", frames, np.arange(20) * 10))
    assert probe_video(tmp_path / "fast.mkv").frame_rate_hz == 25.0
    assert np.array_equal(got.frames, frames)
    np.testing.assert_allclose(got.t, np.arange(20) * 0.01)


def test_iter_video_streams_one_frame_at_a_time(tmp_path):
    frames = _texture(6, seed=6)
    path = write_video(tmp_path / "s.mp4", frames, np.arange(6) * 0.02, crf=0)
    it = iter_video(path)
    t0, f0 = next(it)
    assert f0.shape == (120, 160) and np.array_equal(f0, frames[0])
    assert len(list(it)) == 5


# ---------------------------------------------------------------------------------- TIFF sequences
def _write_tiffs(folder, frames, names=None):
    folder.mkdir(exist_ok=True)
    names = names or [f"frame_{k}.tiff" for k in range(len(frames))]
    for f, n in zip(frames, names, strict=False):
        assert cv2.imwrite(str(folder / n), f)
    return folder


def test_16bit_tiff_sequence_folder_and_glob_in_natural_order(tmp_path):
    frames = _texture(12, h=64, w=80, dtype=np.uint16, seed=7)
    folder = _write_tiffs(tmp_path / "seq", frames)          # frame_2 must come before frame_10
    got = read_video(folder, fps=30.0, t0=5.0)
    assert got.info.kind == "tiff-sequence" and got.info.bit_depth == 16
    assert np.array_equal(got.frames, frames)
    np.testing.assert_allclose(got.t, 5.0 + np.arange(12) / 30.0)
    assert Path(got.files[2]).name == "frame_2.tiff" and Path(got.files[10]).name == "frame_10.tiff"
    globbed = read_video(str(folder / "frame_1*.tiff"), fps=10.0)
    assert [Path(f).name for f in globbed.files] == ["frame_1.tiff", "frame_10.tiff", "frame_11.tiff"]


def test_tiff_sequence_errors_name_the_file(tmp_path):
    frames = _texture(3, h=32, w=32, dtype=np.uint16, seed=8)
    folder = _write_tiffs(tmp_path / "seq", frames)
    with pytest.raises(VideoError, match="frame rate"):
        read_video(folder)                                      # no timestamps in a sequence
    cv2.imwrite(str(folder / "frame_3.tiff"), np.zeros((16, 32), np.uint16))
    with pytest.raises(VideoError, match=r"frame_3\.tiff.*expected 32×32"):
        read_video(folder, fps=10)
    (folder / "frame_3.tiff").write_bytes(b"II*\x00 not really a tiff")
    with pytest.raises(VideoError, match=r"frame_3\.tiff: not an image"):
        read_video(folder, fps=10)
    colour = _write_tiffs(tmp_path / "rgb", [np.zeros((8, 8, 3), np.uint16)])
    with pytest.raises(VideoError, match="single-channel"):
        read_video(colour, fps=10)
    wide = tmp_path / "wide"
    wide.mkdir()
    tifffile.imwrite(wide / "w.tif", np.zeros((2, 20000), np.uint16))     # refused from its header
    with pytest.raises(VideoError, match=r"w\.tif: image shape \(2, 20000\)"):
        read_video(wide, fps=10)
    (tmp_path / "no_tiffs").mkdir()
    with pytest.raises(VideoError, match="no .tif"):
        read_video(tmp_path / "no_tiffs", fps=10)
    with pytest.raises(VideoError, match="matches no files"):
        read_video(str(tmp_path / "absent_*.tif"), fps=10)


# ------------------------------------------------------------------------------------------ errors
def test_a_cut_video_keeps_its_decoded_frames_with_a_note_and_a_lost_header_is_refused(tmp_path):
    frames = _texture(20, seed=9)
    mp4 = write_video(tmp_path / "cut.mp4", frames, np.arange(20) / 25.0)
    data = mp4.read_bytes()
    mp4.write_bytes(data[: len(data) // 2])                       # moov at the end: header lost
    with pytest.raises(VideoError, match=r"cut\.mp4: not a video FFmpeg can read, or truncated"):
        read_video(mp4)
    with av.open(str(tmp_path / "fast.mp4"), "w", options={"movflags": "faststart"}) as c:   # moov first
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 160, 120, "yuv420p"
        for k, f in enumerate(frames):
            vf = av.VideoFrame.from_ndarray(f, format="gray").reformat(format="yuv420p")
            vf.pts, vf.time_base = k * 3600, Fraction(1, 90000)
            for pk in s.encode(vf):
                c.mux(pk)
        for pk in s.encode():
            c.mux(pk)
    data = (tmp_path / "fast.mp4").read_bytes()
    assert data[:64].find(b"moov") > 0
    (tmp_path / "fast.mp4").write_bytes(data[: len(data) * 7 // 10])
    kept = read_video(tmp_path / "fast.mp4")
    assert 5 <= len(kept.t) < 20 and np.allclose(kept.t, np.arange(len(kept.t)) / 25.0)
    assert kept.notes and re.match(r"(decoding stopped at frame \d+|truncated)", kept.notes[0])
    with pytest.raises(VideoError, match=r"fast\.mp4: (decoding stopped at frame \d+|truncated)"):
        list(iter_video(tmp_path / "fast.mp4"))                  # streamed without notes: refused at the end
    mkv = _encode(tmp_path / "cut.mkv", "ffv1", "gray", frames, np.arange(20) * 40)
    data = mkv.read_bytes()
    mkv.write_bytes(data[: len(data) * 2 // 3])                   # clusters lost, duration declared
    kept = read_video(mkv)
    assert 5 <= len(kept.t) < 20 and np.array_equal(kept.frames, frames[: len(kept.t)])
    assert re.match(r"truncated: the header declares 0\.8\d* s.* frames decoded before it are kept",
                    kept.notes[0])


def test_zero_frames_and_no_video_stream(tmp_path):
    with av.open(str(tmp_path / "empty.avi"), "w") as c:            # a header, a video stream, no frame
        s = c.add_stream("ffv1", rate=25)
        s.width, s.height, s.pix_fmt = 32, 16, "gray"
        c.start_encoding()
    with pytest.raises(VideoError, match=r"empty\.avi: the video stream holds zero decodable frames"):
        read_video(tmp_path / "empty.avi")
    with av.open(str(tmp_path / "sound.mka"), "w") as c:
        s = c.add_stream("pcm_s16le", rate=8000)
        f = av.AudioFrame.from_ndarray(np.zeros((1, 800), np.int16), format="s16", layout="mono")
        f.sample_rate, f.pts = 8000, 0
        for pk in s.encode(f):
            c.mux(pk)
        for pk in s.encode():
            c.mux(pk)
    with pytest.raises(VideoError, match=r"sound\.mka: contains no video stream"):
        read_video(tmp_path / "sound.mka")
    with pytest.raises(VideoError, match="no such file"):
        read_video(tmp_path / "absent.mp4")


def test_repeated_or_decreasing_timestamps_are_refused(tmp_path):
    frames = _texture(4, h=16, w=32, seed=11)
    eq = _encode(tmp_path / "eq.mkv", "ffv1", "gray", frames, [0, 40, 40, 80])
    with pytest.raises(VideoError, match=r"eq\.mkv: frame 2 has timestamp 0\.040000 s, not after"):
        read_video(eq)
    # packets muxed with increasing decode times but a presentation time that goes back
    src = _encode(tmp_path / "src.mkv", "ffv1", "gray", frames, [0, 40, 80, 120])
    with av.open(str(src)) as ci, av.open(str(tmp_path / "back.mkv"), "w") as co:
        so = co.add_stream_from_template(ci.streams.video[0])
        for k, pk in enumerate(p for p in ci.demux(ci.streams.video[0]) if p.size):
            pk.stream = so
            pk.dts, pk.pts = [0, 10, 15, 120][k], [0, 40, 20, 120][k]
            co.mux(pk)
    with pytest.raises(VideoError, match=r"back\.mkv: frame \d has timestamp .* not after"):
        read_video(tmp_path / "back.mkv")


def test_absurd_sizes_and_memory_limits(tmp_path):
    wide = _encode(tmp_path / "wide.nut", "rawvideo", "gray", np.zeros((1, 4, 20000), np.uint8), [0])
    with pytest.raises(VideoError, match=r"wide\.nut: frame size 20000×4: expected 1–16384 px"):
        read_video(wide)
    frames = _texture(10, seed=12)
    mp4 = write_video(tmp_path / "ten.mp4", frames, np.arange(10) / 25.0)
    one = 120 * 160
    with pytest.raises(VideoError, match=r"10 frames of 160×120 need .* over the"):
        read_video(mp4, max_bytes=5 * one)                         # refused from the declared count
    mkv = _encode(tmp_path / "ten.mkv", "ffv1", "gray", frames, np.arange(10) * 40)
    assert probe_video(mkv).n_frames is None                      # Matroska declares no count
    with pytest.raises(VideoTooLarge, match=r"more than 5 frames .* read a part of it"):
        read_video(mkv, max_bytes=5 * one)                         # stopped while decoding
    assert len(list(iter_video(mkv))) == 10
    part = read_video(mp4, max_bytes=5 * one, start_s=0.1, duration_s=0.15)   # a part fits
    assert np.allclose(part.t, [0.12, 0.16, 0.2, 0.24]) and part.frames.shape == (4, 120, 160)


def test_a_stack_the_memory_refuses_is_a_video_error_not_a_memory_error(tmp_path, monkeypatch):
    """The stack is sized by the header's frame count (up to 4 GiB: a y4m of a few MB declaring
    16000×16000 asked for 3.8 GiB up front) and a refused allocation was a MemoryError, an internal
    error; now a smaller buffer is tried and grown, and a VideoTooLarge names the file."""
    import thermod.io.video as v

    frames = _texture(10, seed=15)
    mp4 = write_video(tmp_path / "ten.mp4", frames, np.arange(10) / 25.0)
    empty, one = np.empty, 120 * 160

    def scarce(shape, dtype=float, *a, **k):        # memory for `room` frames at most
        if isinstance(shape, tuple) and len(shape) == 3 and shape[0] * shape[1] * shape[2] > room * one:
            raise MemoryError(f"cannot allocate {shape}")
        return empty(shape, dtype, *a, **k)

    monkeypatch.setattr(np, "empty", scarce)
    monkeypatch.setattr(v, "FALLBACK_BUFFER_BYTES", 3 * one, raising=False)
    room = 10
    whole = read_video(mp4)
    room = 5                                         # a part: 7 asked, then 3 grown to 5
    assert np.array_equal(read_video(mp4, duration_s=0.2).frames, whole.frames[:5])
    room = 9                                         # 10 declared: 3, then grown one at a time to 9
    with pytest.raises(VideoTooLarge, match=r"ten\.mp4: no memory for 10 frame\(s\) of 160×120"):
        read_video(mp4)


def test_a_time_window_keeps_the_files_times_and_refuses_an_empty_or_bad_one(tmp_path):
    frames = _texture(10, seed=13)
    mkv = _encode(tmp_path / "ten.mkv", "ffv1", "gray", frames, np.arange(10) * 40 + 1000)
    whole = read_video(mkv)
    part = read_video(mkv, start_s=0.2, duration_s=0.1)
    assert np.allclose(part.t, whole.t[5:8]) and np.array_equal(part.frames, whole.frames[5:8])
    assert np.array_equal(read_video(mkv, start_s=0.3).frames, whole.frames[8:])
    with pytest.raises(VideoError, match=r"ten\.mkv: no frame from 5 s after the first .* lasts 0\.36 s"):
        read_video(mkv, start_s=5.0)
    for kw, words in (({"start_s": -1.0}, "start -1.0 s"), ({"duration_s": 0.0}, "duration 0.0 s"),
                      ({"start_s": float("nan")}, "start nan s")):
        with pytest.raises(VideoError, match=words):
            read_video(mkv, **kw)


def test_writer_refuses_bad_frames_and_times(tmp_path):
    with VideoWriter(tmp_path / "w.mp4", 32, 16) as w:
        w.write(np.zeros((16, 32), np.uint8), 1.0)
        with pytest.raises(VideoError, match="not after the previous"):
            w.write(np.zeros((16, 32), np.uint8), 1.0)
        with pytest.raises(VideoError, match=r"expected uint8 \(16, 32\)"):
            w.write(np.zeros((16, 32), np.uint16), 2.0)
        w.write(np.zeros((16, 32), np.uint8), 1.5)
    assert len(read_video(tmp_path / "w.mp4").t) == 2
    with pytest.raises(VideoError, match="does not exist"):
        VideoWriter(tmp_path / "no" / "dir.mp4", 32, 16)
    with pytest.raises(VideoError, match="one time per frame"):
        write_video(tmp_path / "x.mp4", np.zeros((3, 8, 8), np.uint8), [0, 1])


def test_fps_is_for_tiff_sequences_only(tmp_path):
    mp4 = write_video(tmp_path / "a.mp4", _texture(2), [0, 0.1])
    with pytest.raises(VideoError, match="image sequences .TIFF or PNG frames. only"):
        read_video(mp4, fps=30)


# ---------------------------------------------------------------------------------------------- AGC
def test_percentile_agc_stretches_and_follows_the_scene_smoothly():
    rng = np.random.default_rng(13)
    agc = PercentileAGC(low_pct=1, high_pct=99, smoothing_s=0.5)
    base = rng.normal(3000, 100, (60, 80)).astype(np.float32)
    y, gain, offset = agc.apply(base, 0.0)
    assert y.dtype == np.uint8 and np.mean(y == 0) == pytest.approx(0.01, abs=0.005)
    assert offset == pytest.approx(np.percentile(base, 1), rel=1e-6)
    gains = [agc.apply(base + 400.0, k * 0.02)[2] for k in range(1, 51)]   # a warm object enters
    steps = np.diff(gains)
    assert np.all(steps > 0)                                        # the offset follows, monotonic
    assert gains[-1] - offset == pytest.approx(400 * (1 - np.exp(-1.0 / 0.5)), rel=0.01)
    y2, g2, o2 = agc.apply(base + 400.0, 1.1)
    assert np.array_equal(PercentileAGC.stretch(base + 400.0, g2, o2), y2)    # another frame, same AGC
    with pytest.raises(ThermodError):
        PercentileAGC(low_pct=50, high_pct=10)


# ----------------------------------------------------------------------------------------- fuzzing
@pytest.fixture(scope="module")
def seed_video(tmp_path_factory):
    d = tmp_path_factory.mktemp("seed")
    return write_video(d / "seed.mp4", _texture(4, h=16, w=16, seed=14), np.arange(4) / 25.0).read_bytes()


seed_tiff = cv2.imencode(".tif", np.arange(64, dtype=np.uint16).reshape(8, 8))[1].tobytes()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzzed_bytes_give_a_video_or_a_video_error(tmp_path, seed_video, data):
    as_tiff = data.draw(st.booleans())        # a video file (FFmpeg) or one file of a TIFF sequence (OpenCV)
    seed = seed_tiff if as_tiff else seed_video
    kind = data.draw(st.sampled_from(["random", "flip", "cut"]))
    if kind == "random":
        blob = data.draw(st.binary(max_size=4096))
    elif kind == "flip":
        b = bytearray(seed)
        for _ in range(data.draw(st.integers(1, 16))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
        blob = bytes(b)
    else:
        blob = seed[: data.draw(st.integers(0, len(seed)))]
    if as_tiff:
        path = tmp_path / "seq"
        path.mkdir(exist_ok=True)
        (path / "fuzz_0.tif").write_bytes(blob)
    else:
        path = tmp_path / "fuzz.mp4"
        path.write_bytes(blob)
    try:
        got = read_video(path, fps=30.0 if as_tiff else None, max_bytes=2**24)
    except VideoError as e:
        assert ("fuzz" in str(e)) or ("seq" in str(e))
        return
    assert got.frames.ndim == 3 and got.frames.shape[0] == got.t.shape[0] >= 1
    assert np.all(np.diff(got.t) > 0) and got.frames.dtype in (np.uint8, np.uint16)
