"""Luma range as players show it: a limited-range H.264 (16–235, what ffmpeg and most encoders write
unless told otherwise, range flag unset) is read as full-range values, and written back with the range
the input had; ffmpeg's own decode to RGB (what a player shows) is the reference both ways."""

import subprocess

import numpy as np
import pytest

from thermod.io import video

W, H = 256, 32
RAMP = np.tile(np.arange(256, dtype=np.uint8), (H, 1))


@pytest.fixture(autouse=True)
def ffmpeg(require):
    import shutil
    require(shutil.which("ffmpeg") is not None and shutil.which("ffprobe") is not None, "ffmpeg and ffprobe")


def encode(path, frames, *extra):
    """`frames` (uint8 grey, full range) through the ffmpeg CLI to lossless H.264 yuv420p."""
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{W}x{H}",
                    "-r", "10", "-i", "-", "-c:v", "libx264", "-qp", "0", "-pix_fmt", "yuv420p", *extra,
                    str(path)], input=np.ascontiguousarray(frames).tobytes(), check=True)


def as_player_shows(path) -> np.ndarray:
    """ffmpeg's decode to RGB (range flag honoured, limited assumed when unset): the red channel."""
    out = subprocess.run(["ffmpeg", "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "rgb24",
                          "-"], capture_output=True, check=True).stdout
    return np.frombuffer(out, np.uint8).reshape(-1, H, W, 3)[..., 0]


def color_range(path) -> str:
    return subprocess.run(["ffprobe", "-v", "error", "-show_entries", "stream=color_range", "-of",
                           "default=nw=1:nk=1", str(path)], capture_output=True, text=True,
                          check=True).stdout.strip()


def test_a_limited_range_stream_reads_as_a_player_shows_it(tmp_path):
    src = tmp_path / "limited.mp4"
    encode(src, np.stack([RAMP] * 3))
    assert color_range(src) in ("unknown", "tv")          # ffmpeg's default: limited, often unflagged
    shown = as_player_shows(src)
    got = video.read_video(src)
    assert not got.info.full_range and got.frames.dtype == np.uint8
    assert np.abs(got.frames.astype(int) - shown).max() <= 1
    assert np.abs(got.frames[0].astype(int) - RAMP).max() <= 1            # the grey ramp, not 16–235
    assert got.frames.min() == 0 and got.frames.max() == 255


def test_a_full_range_stream_reads_as_coded(tmp_path):
    src = tmp_path / "full.mp4"
    encode(src, np.stack([RAMP] * 3), "-color_range", "pc")
    got = video.read_video(src)
    assert got.info.full_range
    assert np.abs(got.frames.astype(int) - as_player_shows(src)).max() <= 1


@pytest.mark.parametrize("full_range", [True, False])
def test_written_video_shows_the_frames_in_the_inputs_range(tmp_path, full_range):
    out = tmp_path / "out.mp4"
    with video.VideoWriter(out, W, H, crf=0, full_range=full_range) as w:
        for k in range(3):
            w.write(RAMP, k / 10)
    # limited: x264 flags the VUI's full-range bit off, which ffprobe shows as tv or unknown; players
    # take both as limited
    assert color_range(out) in (("pc",) if full_range else ("tv", "unknown"))
    assert np.abs(as_player_shows(out).astype(int) - RAMP).max() <= 1
    assert np.abs(video.read_video(out).frames.astype(int) - RAMP).max() <= 1


def test_limited_full_mapping_is_the_bt601_quantisation():
    assert video.limited_to_full(np.array([16, 235, 0, 255, 126])).tolist() == [0, 255, 0, 255, 128]
    assert video.full_to_limited(np.array([0, 255, 128])).tolist() == [16, 235, 126]
    ten = video.limited_to_full(np.array([64, 940]), bits=10)
    assert ten.dtype == np.uint16 and ten.tolist() == [0, 1023]
