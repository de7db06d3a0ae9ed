"""Sequences of PNG frames, as ffmpeg and DJI's thermal tools write them: read like TIFF sequences,
checked against ffmpeg's own decode, and refused from their header when they are not grey."""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from thermod.cli.import_video import is_video
from thermod.io.video import VideoError, read_video

W, H, N = 64, 48, 6


@pytest.fixture
def ffmpeg(require):
    require(shutil.which("ffmpeg") is not None, "ffmpeg")


def ffmpeg_pngs(folder: Path, pix_fmt: str, n: int = N) -> Path:
    """`n` frames of ffmpeg's test pattern written by ffmpeg as PNGs of `pix_fmt`."""
    folder.mkdir()
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", f"testsrc2=size={W}x{H}:rate=10",
                    "-frames:v", str(n), "-pix_fmt", pix_fmt, str(folder / "frame_%d.png")], check=True)
    return folder


def ffmpeg_gray16(folder: Path) -> np.ndarray:
    """ffmpeg's decode of the sequence (frame_1.png …) as 16-bit grey, [n, H, W]."""
    out = subprocess.run(["ffmpeg", "-v", "error", "-i", str(folder / "frame_%d.png"), "-f", "rawvideo",
                          "-pix_fmt", "gray16le", "-"], capture_output=True, check=True).stdout
    return np.frombuffer(out, "<u2").reshape(-1, H, W)


def test_a_16_bit_png_sequence_reads_as_ffmpeg_decodes_it(ffmpeg, tmp_path):
    folder = ffmpeg_pngs(tmp_path / "seq", "gray16be")
    got = read_video(folder, fps=10.0, t0=2.0)
    assert got.info.kind == "png-sequence" and got.info.bit_depth == 16 and got.frames.dtype == np.uint16
    assert np.array_equal(got.frames, ffmpeg_gray16(folder))
    np.testing.assert_allclose(got.t, 2.0 + np.arange(N) / 10.0)
    assert [Path(f).name for f in got.files][:3] == ["frame_1.png", "frame_2.png", "frame_3.png"]
    assert is_video(str(folder)) and is_video(str(folder / "*.png"))


def test_an_8_bit_grey_png_sequence_reads(ffmpeg, tmp_path):
    folder = ffmpeg_pngs(tmp_path / "seq8", "gray")
    got = read_video(str(folder / "*.png"), fps=25.0)
    assert got.info.bit_depth == 8 and got.frames.shape == (N, H, W)
    assert np.array_equal(got.frames.astype(np.uint16) * 257, ffmpeg_gray16(folder))


def test_png_frames_that_are_not_grey_are_refused_from_their_header(ffmpeg, tmp_path):
    rgb = ffmpeg_pngs(tmp_path / "rgb", "rgb24", n=2)
    with pytest.raises(VideoError, match=r"frame_1\.png: RGB PNG: expected a single-channel grey PNG"):
        read_video(rgb, fps=10)
    grey = ffmpeg_pngs(tmp_path / "big", "gray16be", n=2)
    data = bytearray((grey / "frame_2.png").read_bytes())
    data[16:20] = (100_000).to_bytes(4, "big")                 # IHDR width: refused before any decode
    (grey / "frame_2.png").write_bytes(bytes(data))
    with pytest.raises(VideoError, match=r"frame_2\.png: image size 100000×48"):
        read_video(grey, fps=10)
    (grey / "frame_2.png").write_bytes(b"\x89PNG\r\n\x1a\n but cut")
    with pytest.raises(VideoError, match=r"frame_2\.png: not a PNG"):
        read_video(grey, fps=10)
    mixed = ffmpeg_pngs(tmp_path / "mixed", "gray16be", n=2)
    (mixed / "extra.tif").write_bytes(b"II*\x00")
    with pytest.raises(VideoError, match="both TIFF and PNG"):
        read_video(mixed, fps=10)


def test_dji_thermal_pngs_read_as_a_sequence(shared_data, require):
    """The real 16-bit PNG frames DJI's thermal tools export (H20T, 640×512)."""
    import cv2

    files = sorted(shared_data.glob("thermal/H20T_DJI_*_R.png"))
    require(bool(files), "../shared/data/thermal/H20T_DJI_*_R.png (real DJI thermal frames)")
    got = read_video(str(shared_data / "thermal" / "H20T_DJI_*_R.png"), fps=30.0)
    assert got.info.kind == "png-sequence" and got.frames.shape == (len(files), 512, 640)
    for k, f in enumerate(files):
        assert np.array_equal(got.frames[k], cv2.imread(str(f), cv2.IMREAD_UNCHANGED))


def test_a_folder_without_frames_or_with_a_cut_frame_is_refused_as_frames(ffmpeg, tmp_path):
    """A folder of JPEGs (or nothing) given --camera and --fps was taken for a ROS bag and told that
    --camera and --fps apply to a flight import only; it is refused as an image sequence now. A cut
    8-bit PNG's error expected a 16-bit one."""
    import os
    import sys

    jpgs = tmp_path / "jpgs"
    jpgs.mkdir()
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", f"testsrc2=size={W}x{H}:rate=10",
                    "-frames:v", "2", str(jpgs / "frame_%d.jpg")], check=True)
    env = dict(os.environ, NUMBA_CACHE_DIR=os.environ.get("NUMBA_CACHE_DIR", str(tmp_path / "numba")))
    r = subprocess.run([sys.executable, "-m", "thermod.cli", "import", str(jpgs), "-o",
                        str(tmp_path / "a.h5"), "--camera", "boson640_14mm", "--fps", "30"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 2 and f"{jpgs}: the folder holds no .tif/.tiff/.png files" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "a.h5").exists()
    cut = ffmpeg_pngs(tmp_path / "cut", "gray", n=2)
    data = (cut / "frame_2.png").read_bytes()
    (cut / "frame_2.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(VideoError, match=r"frame_2\.png: not an image .*expected an 8- or 16-bit grey PNG"):
        read_video(cut, fps=10)
