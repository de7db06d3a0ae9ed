"""Videos as cameras and tools write them, made by the ffmpeg CLI and checked against ffmpeg's own
decode: AVI's slot times with B-frames, several video streams and cover art, a file cut mid-stream,
rotation and interlace flags, RGB's range, and the same kinds through `thermod import`."""

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thermod.io import video

W, H, N, FPS = 64, 48, 12, 10


@pytest.fixture(autouse=True)
def ffmpeg(require):
    import shutil
    require(shutil.which("ffmpeg") is not None and shutil.which("ffprobe") is not None, "ffmpeg and ffprobe")


def frames(n=N, w=W, h=H) -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.integers(0, 256, (n, h, w), dtype=np.uint8)


def encode(path, *args, src=None, w=W, h=H) -> Path:
    """`src` (grey uint8 [N, H, W], at FPS) through the ffmpeg CLI with the given output options."""
    src = frames(w=w, h=h) if src is None else src
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{w}x{h}",
                    "-r", str(FPS), "-i", "-", *args, str(path)], input=src.tobytes(), check=True)
    return Path(path)


def ffmpeg_grey(path, w=W, h=H) -> np.ndarray:
    """ffmpeg's decode of the first video stream to RGB (what a player shows): the red channel."""
    out = subprocess.run(["ffmpeg", "-v", "error", "-i", str(path), "-map", "0:v:0", "-fps_mode",
                          "passthrough", "-f", "rawvideo", "-pix_fmt", "rgb24", "-"], capture_output=True,
                         check=True).stdout
    return np.frombuffer(out, np.uint8).reshape(-1, h, w, 3)[..., 0].astype(int)


def ffprobe_count(path) -> int:
    out = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-count_frames",
                          "-show_entries", "stream=nb_read_frames", "-of", "csv=p=0", str(path)],
                         capture_output=True, text=True, check=True).stdout
    return int(out.split()[0].strip(","))          # MPEG-TS lists its program's stream again


def test_avi_h264_with_b_frames_takes_the_times_of_its_slots(tmp_path):
    """AVI stores no presentation times: with B-frames its pts were decode-order slots, refused as
    timestamps going back; the frames now take the slots in order, as the MKV of the same stream. A
    variable rate is kept as skipped slots (without B-frames: with them, ffmpeg's AVI muxer places the
    gap at the packets' decode times, a reorder delay late)."""
    for kind, args in (("cfr", ["-bf", "2"]),
                       ("vfr", ["-bf", "0", "-vf", r"setpts=PTS+gt(N\,5)*0.5/TB", "-fps_mode",
                                "passthrough"])):
        avi = encode(tmp_path / f"{kind}.avi", "-c:v", "libx264", *args)
        mkv = encode(tmp_path / f"{kind}.mkv", "-c:v", "libx264", *args)
        a, m = video.read_video(avi), video.read_video(mkv)
        assert len(a.t) == N == ffprobe_count(avi)
        assert np.allclose(a.t - a.t[0], m.t - m.t[0], atol=1e-3), (a.t, m.t)
        assert np.abs(a.frames.astype(int) - ffmpeg_grey(avi)).max() <= 1
    assert np.diff(a.t).max() == pytest.approx(0.6, abs=1e-3)            # the VFR gap is kept


def test_of_several_video_streams_the_played_one_is_read_and_never_cover_art(tmp_path):
    small = encode(tmp_path / "small.mkv", "-c:v", "ffv1", src=frames(w=32, h=24), w=32, h=24)
    main = encode(tmp_path / "main.mkv", "-c:v", "libx264")
    cover = tmp_path / "cover.png"
    subprocess.run(["ffmpeg", "-v", "error", "-i", str(main), "-frames:v", "1", str(cover)], check=True)
    two = tmp_path / "two.mkv"
    subprocess.run(["ffmpeg", "-v", "error", "-i", str(small), "-i", str(main), "-map", "0", "-map", "1",
                    "-c", "copy", "-disposition:v:0", "0", "-disposition:v:1", "default", str(two)],
                   check=True)
    got = video.read_video(two)
    assert (got.info.width, got.info.stream_index, len(got.t)) == (W, 1, N)
    assert got.info.video_streams == ((0, 32, 24), (1, W, H))
    assert video.read_video(two, stream=0).frames.shape == (N, 24, 32)
    with pytest.raises(video.VideoError, match=r"two\.mkv: has no video stream #5"):
        video.read_video(two, stream=5)
    # cover art first: an MP4 flags it, a Matroska track of one PNG frame is not the default one
    for name in ("art.mp4", "art.mkv"):
        out = tmp_path / name
        subprocess.run(["ffmpeg", "-v", "error", "-i", str(cover), "-i", str(main), "-map", "0", "-map", "1",
                        "-c", "copy", "-disposition:v:0", "attached_pic", "-disposition:v:1", "default",
                        str(out)], check=True)
        got = video.read_video(out)
        assert got.info.codec == "h264" and len(got.t) == N, name


def test_a_file_cut_mid_stream_keeps_what_ffmpeg_decodes_with_a_note(tmp_path):
    for name, args in (("cut.mkv", []), ("cut.mp4", ["-movflags", "+faststart"]), ("cut.ts", [])):
        path = encode(tmp_path / name, "-c:v", "libx264", *args, src=frames(n=40))
        data = path.read_bytes()
        path.write_bytes(data[: len(data) * 6 // 10])
        got = video.read_video(path)
        n = ffprobe_count(path)
        assert 3 <= len(got.t) < 40 and abs(len(got.t) - n) <= 1, (name, len(got.t), n)
        assert np.abs(got.frames.astype(int) - ffmpeg_grey(path)[: len(got.t)]).max() <= 1
        if name != "cut.ts":              # MPEG-TS declares no length: a cut is its end
            assert got.notes and "kept" in got.notes[0], name
    with pytest.raises(video.VideoError, match=r"cut\.mkv: .*truncated"):
        list(video.iter_video(tmp_path / "cut.mkv"))           # streamed without notes: refused at the end


def test_a_damaged_packet_mid_file_loses_only_the_frames_up_to_the_next_keyframe(tmp_path):
    """A packet the decoder refuses (its NAL sizes zeroed, as a bad sector leaves it) once ended the
    read there, losing the rest of the file; now the frames from the next keyframe on are kept, with
    a note, and a stream read without notes is refused at its end."""
    path = encode(tmp_path / "damaged.mp4", "-c:v", "libx264", "-g", "10", "-sc_threshold", "0", "-bf", "0",
                  "-movflags", "+faststart", src=frames(n=30))
    whole = video.read_video(path)
    out = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries",
                          "packet=pos,size,flags", "-of", "json", str(path)], capture_output=True, text=True,
                         check=True).stdout
    packets = json.loads(out)["packets"]
    assert [k for k, p in enumerate(packets) if "K" in p["flags"]] == [0, 10, 20]
    pos, size = int(packets[13]["pos"]), int(packets[13]["size"])      # a P-frame of the second GOP
    data = bytearray(path.read_bytes())
    data[pos:pos + size] = bytes(size)
    path.write_bytes(bytes(data))
    got = video.read_video(path)
    keep = np.r_[0:13, 20:30]                         # packets 13–19 lost; 20 is the next keyframe
    assert np.allclose(got.t, whole.t[keep]) and np.array_equal(got.frames, whole.frames[keep])
    assert len(got.notes) == 1 and "7 damaged packet(s)" in got.notes[0] and "resumed" in got.notes[0]
    with pytest.raises(video.VideoError, match=r"damaged\.mp4: damaged data before frame 13"):
        list(video.iter_video(path))


def rotate_90(mp4: Path) -> None:
    """Set the video track's display matrix to a 90° rotation (what a phone or gimbal camera writes;
    ffmpeg 5's CLI has no option for it)."""
    d = bytearray(mp4.read_bytes())
    i = d.find(b"tkhd")
    off = i + 4 + (40 if d[i + 4] == 0 else 52)
    assert struct.unpack(">9i", d[off:off + 36]) == (0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)
    d[off:off + 36] = struct.pack(">9i", 0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000)
    mp4.write_bytes(bytes(d))


def test_rotation_interlace_and_rgb_are_read_as_coded_and_said(tmp_path):
    src = frames()
    rot = encode(tmp_path / "rot.mp4", "-c:v", "libx264", "-pix_fmt", "yuvj420p")
    rotate_90(rot)
    probe = subprocess.run(["ffprobe", "-v", "error", "-show_streams", str(rot)], capture_output=True,
                           text=True, check=True).stdout
    assert "rotation=-90" in probe
    got = video.read_video(rot)
    assert got.frames.shape == (N, H, W)                      # the sensor's rows and columns
    assert any("rotate it by 90° clockwise" in n for n in got.notes)
    inter = encode(tmp_path / "inter.mp4", "-c:v", "libx264", "-flags", "+ildct+ilme", "-top", "1")
    assert any("interlaced" in n for n in video.read_video(inter).notes)
    rgb = encode(tmp_path / "rgb.avi", "-c:v", "rawvideo", "-pix_fmt", "bgr24")
    got = video.read_video(rgb)
    assert got.info.full_range and np.array_equal(got.frames, src)


def test_deep_rgb_and_grey_alpha_are_read_at_16_bits_never_cut_to_8(tmp_path):
    """16-bit counts an NLE or a PNG exporter stores as RGB48, GBRP16 (FFV1), RGBA64 or grey + alpha
    were read as 8-bit (swscale's grey, the low byte lost, no note); now 16-bit, the grey exactly."""
    src = np.random.default_rng(2).integers(0, 65536, (3, H, W)).astype("<u2")
    for pix, codec in (("rgb48be", "png"), ("gbrp16le", "ffv1"), ("rgba64be", "png"), ("ya16be", "png"),
                       ("gray9le", "ffv1")):
        out = tmp_path / f"{pix}.mkv"
        subprocess.run(["ffmpeg", "-v", "error", "-f", "rawvideo", "-pix_fmt", "gray16le", "-s", f"{W}x{H}",
                        "-r", str(FPS), "-i", "-", "-c:v", codec, "-pix_fmt", pix, str(out)],
                       input=src.tobytes(), check=True)
        got = video.read_video(out)
        assert (got.info.bit_depth, got.frames.dtype) == (16, np.uint16), pix
        want = src >> 7 if pix == "gray9le" else src          # grey formats as coded: 9 bits (rounded)
        err = np.abs(got.frames.astype(int) - want).max()
        assert err <= (pix == "gray9le"), (pix, err)


def test_a_repeated_or_backward_time_that_the_muxer_moved_one_tick_on_is_refused(tmp_path):
    """A frame whose time repeats (or goes back) is refused from Matroska, but MP4 and NUT move it one
    tick after the previous frame: those files imported with a frame 0.1 ms after the one before (a
    rate spike across it), or, with every other time repeated, failed on a calibration field naming
    no file; both are now refused naming the file and the frame."""
    from thermod.ingest.camera_video import read_camera_video
    from thermod.ingest.video_only import VideoImportError
    from thermod.physics.calibration import Calibration

    cam = Calibration().replace(width=W, height=H, fx=100.0, fy=100.0, cx=W / 2 - 0.5, cy=H / 2 - 0.5,
                                frame_rate_hz=FPS)
    back = (r"setpts=round((N-2*eq(N\,5))/10/TB)", r"frame 5 at 0\.4000\d+ s comes 0\.0977 ms after frame 4")
    repeat = (r"setpts=round(floor(N/2)/10/TB)", r"0\.0122 ms apart at the median \(81920 fps")
    cases = {"back.mp4": ("libx264", *back), "repeat.nut": ("ffv1", *repeat)}
    for name, (codec, setpts, message) in cases.items():
        path = encode(tmp_path / name, "-c:v", codec, "-bf", "0", "-vf", setpts, "-fps_mode", "passthrough")
        assert np.all(np.diff(video.read_video(path).t) > 0)        # the muxer made them increase
        with pytest.raises(VideoImportError, match=rf"{name.replace('.', '[.]')}: .*{message}"):
            read_camera_video(path, cam, VideoImportError, "a test")
    ok = encode(tmp_path / "ok.mp4", "-c:v", "libx264", "-vf", r"setpts=round((N+3*gt(N\,5))/10/TB)",
                "-fps_mode", "passthrough")
    assert len(read_camera_video(ok, cam, VideoImportError, "a test").frames.t) == N     # a gap is no fault


def test_an_animated_gif_is_a_video_not_a_ros_bag(tmp_path):
    """A thermal viewer's GIF export was sent to the ROS bag reader ("expected an .mcap file …");
    FFmpeg reads it (palette of greys, 1/100 s delays), so it is imported as a video."""
    from thermod.cli.import_video import is_video

    gif = encode(tmp_path / "export.gif")
    got = video.read_video(gif)
    assert is_video(str(gif)) and np.array_equal(got.frames, frames())
    assert np.allclose(np.diff(got.t), 1 / FPS)


# ------------------------------------------------------------------------------------ through the CLI
def thermod(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).parents[2] / ".numba_cache"))
    return subprocess.run([sys.executable, "-m", "thermod.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=600)


def test_real_clip_kinds_import_or_are_refused_naming_the_file(tmp_path, shared_data, require):
    """The real drone clip re-encoded as tools write it: AVI with B-frames, a second (smaller) video
    stream first, a cut Matroska, the NUT suffix; a text file renamed .mp4 is refused (exit 2)."""
    clip = shared_data / "video" / "ici_drone_640x512.mp4"
    require(clip.exists(), f"{clip}")
    cut = ["ffmpeg", "-v", "error", "-ss", "2", "-t", "1.2", "-i", str(clip)]
    d = tmp_path / "dir with spaces é"
    d.mkdir()
    subprocess.run([*cut, "-c:v", "libx264", "-bf", "2", str(d / "b frames.avi")], check=True)
    subprocess.run([*cut, "-f", "lavfi", "-i", "testsrc=s=320x240:d=1", "-map", "1:v", "-map", "0:v",
                    "-c:v", "libx264", str(d / "two.mkv")], check=True)
    subprocess.run([*cut, "-c:v", "ffv1", str(d / "clip.nut")], check=True)
    subprocess.run([*cut, "-t", "2.4", "-c:v", "libx264", str(d / "cut.mkv")], check=True)
    data = (d / "cut.mkv").read_bytes()
    (d / "cut.mkv").write_bytes(data[: len(data) * 6 // 10])
    expect = {"b frames.avi": "", "two.mkv": "2 video streams", "clip.nut": "", "cut.mkv": "kept"}
    for name, note in expect.items():
        r = thermod("import", d / name, "-o", tmp_path / f"{name}.h5", "--camera", "boson640_14mm")
        assert r.returncode == 0, (name, r.stderr)
        assert note in r.stderr, (name, r.stderr)
    (d / "text.mp4").write_text("not a video\n")
    r = thermod("import", d / "text.mp4", "-o", tmp_path / "text.h5", "--camera", "boson640_14mm")
    assert r.returncode == 2 and f"{d / 'text.mp4'}: not a video FFmpeg can read" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "text.h5").exists()
