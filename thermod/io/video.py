"""Thermal video in and out: grey frames with per-frame times, through FFmpeg (PyAV) or OpenCV.

Reading (`iter_video`, `read_video`, `probe_video`): a video file FFmpeg decodes, grey formats as
coded (uint8 or uint16, not rescaled), YUV as its luma plane as a player shows it (limited range
mapped to full, `limited_to_full`; `VideoInfo.luma_only`), RGB as its luma (uint16 whenever a
component has over 8 bits), or a sequence of grey 8- or 16-bit TIFF or PNG frames (a folder or a
glob, natural order of names) whose frame k is at ``t0 + k / fps``.

The rules it keeps: a frame's time is float64 s on the container's own clock (its presentation
timestamp; variable frame rate kept), never mapped to the flight log's (the sync's job); times
increase strictly, and a repeated or decreasing timestamp is a `VideoError`, never re-ordered (AVI
stores no presentation times: its frames are timed by their slots, as FFmpeg's best-effort time). Of
several video streams the one FFmpeg would play is read (`choose_stream`; cover art never). A file cut
short keeps the frames decoded before the cut, with a note (`VideoFrames.notes`); a damaged packet
loses the frames up to the next keyframe, where decoding resumes (a note). A side over `MAX_SIDE`,
more than `MAX_FRAMES` frames or a stack over `max_bytes` is refused before it is allocated;
`iter_video` streams one frame at a time.

Writing (`VideoWriter`, `write_video`): 8-bit grey frames to H.264 (libx264, yuv420p) with the given
times as timestamps (time base 1/90000 s). `PercentileAGC` is a thermal camera's automatic gain
control: a percentile stretch whose gain and offset follow the scene smoothly. Errors are
`VideoError` naming the file. Details: docs/design.md §3, "Flights from other tools".
"""

from __future__ import annotations

import glob
import heapq
import math
import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from thermod.errors import FileError, ThermodError

MAX_SIDE = 16384                  # px, as the recording format's calibration bounds
MAX_FRAMES = 10_000_000
DEFAULT_MAX_BYTES = 4 * 2**30     # read_video's in-memory stack
FALLBACK_BUFFER_BYTES = 2**26     # its first buffer when one sized by the header cannot be had
WINDOW_TOLERANCE_S = 1e-6         # a frame this close to a time window's edge is on the edge
WRITE_TIME_BASE = Fraction(1, 90000)
TIFF_SUFFIXES = (".tif", ".tiff")
PNG_SUFFIXES = (".png",)
SEQUENCE_SUFFIXES = TIFF_SUFFIXES + PNG_SUFFIXES   # an image sequence's frames, one kind a sequence
# what FFmpeg and PyAV raise on a damaged file (av.error.FFmpegError is a ValueError, and PyAV decodes
# metadata strings itself); each becomes a VideoError naming the file
_DECODE_ERRORS = (av.error.FFmpegError, ValueError, UnicodeError, OSError, EOFError)
_GREY16 = {"gray16le", "gray16be", "gray9le", "gray9be", "gray10le", "gray10be", "gray12le", "gray12be",
           "gray14le", "gray14be"}


class VideoError(FileError):
    """A video or image sequence cannot be read or written as asked: names the file and the problem."""


class VideoTooLarge(VideoError):
    """A video (or the part of it asked for) holds more frames than `read_video`'s memory limit."""


@dataclass(frozen=True)
class VideoInfo:
    """What a video holds, before decoding it.

    n_frames is the count the container declares (None when it declares none, as MKV does);
    duration_s the stream's declared duration (None if unknown); bit_depth 8 or 16 (the dtype
    frames come out as); luma_only True when colour input is read as its luma (module docstring).
    """

    path: str
    kind: str                     # "video", "tiff-sequence" or "png-sequence"
    width: int
    height: int
    bit_depth: int
    n_frames: int | None
    duration_s: float | None
    frame_rate_hz: float | None   # the container's average rate (None if unknown)
    codec: str
    pix_fmt: str
    luma_only: bool = False
    full_range: bool = True       # False: limited-range YUV (16–235 luma at 8 bit), mapped to full on read
    stream_index: int = 0         # the container's index of the stream read
    video_streams: tuple[tuple[int, int, int], ...] = ()   # (index, width, height) of every video stream

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint16 if self.bit_depth == 16 else np.uint8)

    @property
    def frame_bytes(self) -> int:
        return self.width * self.height * self.dtype.itemsize


@dataclass
class VideoFrames:
    """A loaded video: frames [N, H, W] (uint8 or uint16) and their times t [N] (float64 s,
    strictly increasing, on the container's clock)."""

    frames: np.ndarray
    t: np.ndarray
    info: VideoInfo
    files: list[str] = field(default_factory=list)   # an image sequence's files, in order
    notes: list[str] = field(default_factory=list)   # what the reader kept or ignored (a cut, a rotation)


# ----------------------------------------------------------------------------------------- reading
def probe_video(source: str | os.PathLike, fps: float | None = None, *, stream: int | None = None
                ) -> VideoInfo:
    """The `VideoInfo` of a video file or an image sequence (TIFF or PNG frames: needs `fps`); `stream`
    is a container's stream index (default: `choose_stream`'s)."""
    files = _sequence_files(source)
    if files is not None:
        return _probe_sequence(source, files, fps)
    av = _av()
    path = _existing_file(source)
    try:
        with av.open(str(path), metadata_errors="replace") as c:
            return _info_from_container(path, c, stream)
    except _DECODE_ERRORS as e:
        raise VideoError(path, f"not a video FFmpeg can read, or truncated before its header ends ({e})"
                         ) from None


def iter_video(source: str | os.PathLike, fps: float | None = None, t0: float = 0.0, *,
               stream: int | None = None, notes: list[str] | None = None
               ) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (t_s, frame) one frame at a time: frame is [H, W] uint8 or uint16 (module docstring).

    For an image sequence `fps` (Hz) is required and frame k is at t0 + k / fps; for a video file
    `fps` and `t0` must be left unset (its own timestamps are used). Raises `VideoError` for a
    truncated file, a missing video stream, zero frames or timestamps that do not increase; with a
    `notes` list, a file cut short after its first frame ends the frames with a note there instead."""
    files = _sequence_files(source)
    if files is not None:
        info = _probe_sequence(source, files, fps)
        yield from _iter_sequence(info, files, float(fps), float(t0))
        return
    if fps is not None or t0:
        raise VideoError(source, "fps/t0 apply to image sequences (TIFF or PNG frames) only; a video "
                                 "file's own timestamps are used")
    yield from _iter_av(_existing_file(source), stream, notes)


def read_video(source: str | os.PathLike, fps: float | None = None, t0: float = 0.0,
               max_bytes: int = DEFAULT_MAX_BYTES, *, start_s: float = 0.0,
               duration_s: float | None = None, stream: int | None = None) -> VideoFrames:
    """Load a video (or image sequence) into memory: `VideoFrames`, with every frame or those read from
    `start_s` to `start_s` + `duration_s` after the first frame (times stay the file's own).

    Refuses, before decoding, a whole video whose declared frame count needs more than `max_bytes`,
    and stops with `VideoTooLarge` as soon as the frames kept exceed it (read a part of it, or
    stream it with `iter_video`). A file cut short gives the frames before the cut, with a note."""
    start_s = float(start_s)
    if not (math.isfinite(start_s) and start_s >= 0):
        raise VideoError(source, f"start {start_s} s: expected 0 or more seconds after the first frame")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise VideoError(source, f"duration {duration_s} s: expected more than 0 seconds")
    info = probe_video(source, fps, stream=stream)
    whole = start_s == 0 and duration_s is None
    if whole and info.n_frames is not None and info.n_frames * info.frame_bytes > max_bytes:
        raise VideoTooLarge(source, f"{info.n_frames} frames of {info.width}×{info.height} need "
                                    f"{info.n_frames * info.frame_bytes / 2**30:.2f} GiB, over the "
                                    f"{max_bytes / 2**30:.2f} GiB limit; read a part of it")
    cap = max(1, max_bytes // info.frame_bytes)
    # one buffer sized from the header, grown by doubling when a header under-counts: the peak is the
    # frames themselves, not a list of them plus the stacked copy
    guess = info.n_frames or (int(info.duration_s * info.frame_rate_hz) + 2
                              if info.duration_s and info.frame_rate_hz else 256)
    if duration_s is not None and info.frame_rate_hz:
        guess = min(guess, int(duration_s * info.frame_rate_hz) + 2)
    buf = _frame_buffer(source, min(max(guess, 1), cap), info)
    times, notes = [], []
    first = last = None
    for t, f in iter_video(source, fps, t0, stream=None if info.kind != "video" else info.stream_index,
                           notes=notes):
        first = t if first is None else first
        last = t
        if t - first < start_s - WINDOW_TOLERANCE_S:
            continue
        if duration_s is not None and t - first >= start_s + duration_s - WINDOW_TOLERANCE_S:
            break
        n = len(times)
        if n == buf.shape[0]:
            if n >= cap:
                raise VideoTooLarge(source, f"more than {cap} frames of {info.width}×{info.height} "
                                            f"({max_bytes / 2**30:.2f} GiB limit); read a part of it")
            grown = _frame_buffer(source, min(2 * n, cap), info, n + 1)
            grown[:n] = buf
            buf = grown
        buf[n] = f
        times.append(t)
    n = len(times)
    if n == 0:
        raise VideoError(source, f"no frame from {start_s:g} s after the first frame"
                                 + (f" for {duration_s:g} s" if duration_s is not None else "")
                                 + (f" (the video lasts {last - first:.3g} s)" if first is not None else ""))
    frames = buf[:n] if n > 0.9 * buf.shape[0] else buf[:n].copy()
    files = _sequence_files(source) or []
    return VideoFrames(frames, np.asarray(times, dtype=np.float64), info, [str(p) for p in files], notes)


def _frame_buffer(source, rows: int, info: VideoInfo, least: int = 1) -> np.ndarray:
    """An empty [rows, H, W] stack, or, when the memory for one sized by the header is refused, the
    `least` rows or at most `FALLBACK_BUFFER_BYTES` (grown as frames come); VideoTooLarge when even
    that is refused."""
    for r in (rows, max(least, min(rows, FALLBACK_BUFFER_BYTES // info.frame_bytes))):
        try:
            return np.empty((r, info.height, info.width), info.dtype)
        except MemoryError:
            continue
    raise VideoTooLarge(source, f"no memory for {least} frame(s) of {info.width}×{info.height} "
                                f"({least * info.frame_bytes / 2**20:.0f} MiB); read a part of it")


def _av():
    av.logging.set_level(av.logging.PANIC)    # errors reach the caller as exceptions, not stderr noise
    return av


def _existing_file(source) -> Path:
    path = Path(source)
    if not path.is_file():
        raise VideoError(path, "no such file (expected a video file, or a folder or glob of TIFF or PNG "
                               "frames)")
    return path


def choose_stream(streams) -> int | None:
    """The video stream FFmpeg would play: cover art (attached pictures) left out, then the default
    one, then the largest, then the first; None when there is none."""
    attached = int(av.stream.Disposition.attached_pic)
    default = int(av.stream.Disposition.default)
    best, key = None, None
    for s in streams:
        disp = int(s.disposition or 0)
        if disp & attached:
            continue
        w, h = _size(s)
        k = (bool(disp & default), w * h)
        if key is None or k > key:
            best, key = s.index, k
    return best


def _size(s) -> tuple[int, int]:
    """A stream's (width, height), (0, 0) when unknown (a damaged header leaves PyAV no codec
    context, and then asking for the width raises)."""
    try:
        return int(s.width or 0), int(s.height or 0)
    except (AttributeError, ValueError):
        return 0, 0


def _video_stream(path: Path, c, stream: int | None):
    if stream is None:
        stream = choose_stream(c.streams.video)
        if stream is None:
            raise VideoError(path, "contains no video stream (only cover art)" if c.streams.video
                             else "contains no video stream")
    found = [s for s in c.streams.video if s.index == stream]
    if not found:
        raise VideoError(path, f"has no video stream #{stream} (its video streams: "
                               f"{[s.index for s in c.streams.video]})")
    return found[0]


def _info_from_container(path: Path, c, stream: int | None = None) -> VideoInfo:
    s = _video_stream(path, c, stream)
    cc = s.codec_context
    if cc is None:
        raise VideoError(path, "its video stream has no codec FFmpeg can decode (damaged header?)")
    w, h = int(cc.width or 0), int(cc.height or 0)
    _check_size(path, w, h)
    pix = cc.pix_fmt or (s.format.name if s.format else "") or ""
    depth = 16 if pix in _GREY16 or _is_high_depth_yuv(pix) or _component_bits(pix) > 8 else 8
    luma_only = pix not in ("gray",) and pix not in _GREY16
    # a player shows YUV as limited range unless the stream says full (yuvj*, or the range flag: 2 = JPEG);
    # RGB and palette formats have no range (swscale's grey of them is full range)
    yuv = pix.startswith(("yuv", "nv", "p0", "p2", "y2", "uyv", "yvy", "ayuv", "v210", "xv"))
    full_range = (not luma_only or not yuv or pix.startswith("yuvj")
                  or int(getattr(cc, "color_range", 0) or 0) == 2)
    n = int(s.frames) if s.frames else None
    if n is not None and n > MAX_FRAMES:
        raise VideoError(path, f"declares {n} frames, over the {MAX_FRAMES} this reader accepts")
    duration = None
    if s.duration and s.time_base:
        duration = float(s.duration * s.time_base)
    elif c.duration and len(c.streams) == 1:
        # a container's duration can count from 0 while the stream starts later (Matroska keeps a cut's
        # original times): the span that holds frames starts at its start time
        start = c.start_time / 1e6 if c.start_time is not None and c.start_time > 0 else 0.0
        duration = c.duration / 1e6 - start
    rate = float(s.average_rate) if s.average_rate else None
    streams = tuple((v.index, *_size(v)) for v in c.streams.video)
    return VideoInfo(str(path), "video", w, h, depth, n, duration, rate, cc.name or "?", pix, luma_only,
                     full_range, s.index, streams)


def limited_to_full(y: np.ndarray, bits: int = 8) -> np.ndarray:
    """Limited-range luma codes (16–235 at 8 bit, ×2^(bits−8) above) as full-range values (0 to
    2^bits − 1), rounded and clipped: what a player shows (ITU-R BT.601/709 quantisation)."""
    scale = 1 << (bits - 8)
    top = (1 << bits) - 1
    v = (np.asarray(y, np.float64) - 16 * scale) * top / (219 * scale)
    return np.clip(np.rint(v), 0, top).astype(np.uint8 if bits == 8 else np.uint16)


def full_to_limited(v: np.ndarray) -> np.ndarray:
    """8-bit full-range values as limited-range luma codes (16–235), the inverse of `limited_to_full`."""
    return np.rint(16 + np.asarray(v, np.float64) * 219 / 255).astype(np.uint8)


_LIMITED_TO_FULL_8 = limited_to_full(np.arange(256))


def _coded_bits(pix: str) -> int:
    m = re.search(r"(9|10|12|14|16)(le|be)$", pix)
    return int(m.group(1)) if m else 16


def _component_bits(pix: str) -> int:
    """The most bits of any component of pixel format `pix` (0 when FFmpeg does not know it): over 8,
    the frames are read as 16-bit (RGB48, GBRP16, grey + alpha at 16 bits …), never cut to 8."""
    try:
        return max((int(c.bits) for c in av.VideoFormat(pix).components), default=0)
    except (ValueError, TypeError):
        return 0


def _is_high_depth_yuv(pix: str) -> bool:
    return (bool(re.match(r"^(yuv|yuvj|nv|p0|p2)\w*?(9|10|12|14|16)(le|be)$", pix))
            or pix.startswith(("p010", "p016")))


def _check_size(path, w: int, h: int) -> None:
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise VideoError(path, f"frame size {w}×{h}: expected 1–{MAX_SIDE} px per side")


def _iter_av(path: Path, stream: int | None = None, notes: list[str] | None = None
             ) -> Iterator[tuple[float, np.ndarray]]:
    av = _av()
    try:
        c = av.open(str(path), metadata_errors="replace")
    except _DECODE_ERRORS as e:
        raise VideoError(path, f"not a video FFmpeg can read, or truncated before its header ends ({e})"
                         ) from None
    with c:
        info = _info_from_container(path, c, stream)
        s = _video_stream(path, c, info.stream_index)
        # AVI stores no presentation times, only one slot per frame in decode order (with B-frames the
        # demuxer's pts follow that order, not the pictures'): the frames, in presentation order, take the
        # slots of the packets read so far, earliest first, as a decoder's reordering does with true pts
        slots = [] if c.format.name == "avi" else None
        n, first, last, periods, errors, damaged = 0, 0.0, -math.inf, [], [], []
        skipped, resumes, resumed = [0], [], []   # packets left out; errors resumed after; frames there
        for frame in _decoded(c, s, errors, slots, skipped, resumes):
            if len(resumes) > len(resumed):      # decoding resumed at a keyframe after damaged packets
                resumed.append(n + len(damaged))
            t = _frame_time(path, frame, n, s.time_base, heapq.heappop(slots) if slots else None)
            if frame.is_corrupt:       # its missing data concealed by the decoder: pixels no camera saw
                damaged.append(n + len(damaged))
                continue
            if not t > last:
                raise VideoError(path, f"frame {n} has timestamp {t:.6f} s, not after the previous "
                                       f"{last:.6f} s (expected strictly increasing presentation times)")
            if n >= MAX_FRAMES:
                raise VideoError(path, f"more than {MAX_FRAMES} frames")
            if n == 0:
                first = t
                _note_first_frame(frame, notes)
            elif len(periods) < 1000:          # enough for the typical frame period
                periods.append(t - last)
            img = _grey(path, frame, info)
            last = t
            n += 1
            yield t, img
    if n == 0:
        raise VideoError(path, "the video stream holds zero decodable frames (empty or truncated)"
                         + (f" ({errors[0]})" if errors else "")
                         + (f"; {len(damaged)} damaged" if damaged else ""))
    if damaged and notes is None:
        raise VideoError(path, f"frame {damaged[0]} is damaged (decoded with missing data concealed)")
    if damaged:
        notes.append(f"{len(damaged)} damaged frame(s) (decoded with missing data concealed) left out: "
                     f"{damaged[:10]}{' …' if len(damaged) > 10 else ''}")
    if resumed and notes is None:
        raise VideoError(path, f"damaged data before frame {resumed[0]} ({errors[0]})")
    if resumed:
        notes.append(f"{skipped[0]} damaged packet(s) and the frames depending on them left out "
                     f"({errors[0]}); decoding resumed at the next keyframe, frame(s) {resumed[:10]}"
                     f"{' …' if len(resumed) > 10 else ''}")
    stopped = errors[resumes[-1] if resumes else 0:]   # errors after the last resumption: the end
    problem = (f"decoding stopped at frame {n}: truncated or corrupt ({stopped[0]})" if stopped
               else _incomplete(info, n + skipped[0], last - first, periods))
    if problem and notes is None:
        raise VideoError(path, problem)
    if problem:
        notes.append(f"{problem}; the {n} frames decoded before it are kept")


def _decoded(c, s, errors: list, slots: list | None = None, skipped: list | None = None,
             resumes: list | None = None):
    """The stream's frames in presentation order. A packet the decoder refuses (damaged data) is
    left out with the packets after it up to the next keyframe, where decoding resumes (as FFmpeg's
    CLI goes on, but with no frame decoded from a missing reference); a demuxer error (a cut packet
    header) ends the stream. Each error is appended to `errors`, each packet left out counted in
    `skipped[0]`, and `resumes` the number of errors each time decoding resumes after them (the
    errors past the last stopped the stream); at an error the frames the decoder holds are flushed,
    not lost. With `slots`, each decoded packet's decode time is pushed onto that heap first."""
    skipped = [0] if skipped is None else skipped
    resumes = [] if resumes is None else resumes
    resync = False
    try:
        for packet in c.demux(s):
            if resync and packet.size and not packet.is_keyframe:
                skipped[0] += 1
                continue
            if resync and packet.size:
                resumes.append(len(errors))
            resync = False
            slot = packet.dts if slots is not None and packet.size and packet.dts is not None else None
            if slot is not None:
                heapq.heappush(slots, slot)
            try:
                yield from s.decode(packet)
            except _DECODE_ERRORS as e:     # the decoder's: this packet is lost, not the rest of the file
                errors.append(e)
                skipped[0] += 1
                resync = True
                if slot is not None and slot in slots:
                    slots.remove(slot)
                    heapq.heapify(slots)
    except _DECODE_ERRORS as e:     # the demuxer's (a cut packet header): the end of what can be read
        errors.append(e)
    if not errors:                  # demux's last, empty packet has flushed the decoder
        return
    try:
        yield from s.decode(None)
    except av.error.EOFError:
        pass
    except _DECODE_ERRORS as e:
        errors.append(e)


def _note_first_frame(frame, notes: list[str] | None) -> None:
    """What a player would do to the frames that the reader does not: rotate, deinterlace."""
    if notes is None:
        return
    rotation = int(round(getattr(frame, "rotation", 0) or 0)) % 360
    if rotation:
        notes.append(f"the file asks players to rotate it by {360 - rotation}° clockwise; the frames are "
                     "read as coded (the sensor's rows and columns), unrotated")
    if getattr(frame, "interlaced_frame", False):
        notes.append("the video is interlaced: each frame's two fields are read woven as one picture")


def _frame_time(path: Path, frame, k: int, time_base, slot: int | None = None) -> float:
    pts = slot if slot is not None else frame.pts if frame.pts is not None else getattr(frame, "dts", None)
    # the frames flushed from the decoder at the end carry no time base of their own: the stream's
    time_base = frame.time_base or time_base
    if pts is None or time_base is None:
        raise VideoError(path, f"frame {k} has no timestamp (expected a container with presentation times)")
    t = float(pts * time_base)
    if not math.isfinite(t):
        raise VideoError(path, f"frame {k} has a non-finite timestamp")
    return t


def _grey(path: Path, frame, info: VideoInfo) -> np.ndarray:
    """The frame's grey level: the grey plane or the luma plane as coded, else swscale's grey."""
    fmt = frame.format.name
    if frame.width != info.width or frame.height != info.height:
        raise VideoError(path, f"frame size changes from {info.width}×{info.height} to "
                               f"{frame.width}×{frame.height} (expected one size for the whole video)")
    h, w = frame.height, frame.width
    if fmt == "gray" or (fmt.startswith(("yuv", "yuvj", "nv")) and info.bit_depth == 8):
        plane = frame.planes[0]
        a = np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)
        return a[:h, :w].copy() if info.full_range else _LIMITED_TO_FULL_8[a[:h, :w]]
    planar16 = info.bit_depth == 16 and fmt.startswith(("yuv", "yuvj")) and fmt.endswith(("le", "be"))
    if fmt in _GREY16 or planar16:
        plane = frame.planes[0]
        dt = np.dtype("<u2" if fmt.endswith("le") else ">u2")
        a = np.frombuffer(plane, dt).reshape(-1, plane.line_size // 2)[:h, :w].astype(np.uint16)
        return a if info.full_range else limited_to_full(a, _coded_bits(fmt))
    if info.bit_depth == 16 and frame.format.is_rgb:
        # swscale's 16-bit grey of deep RGB keeps about 8 bits (codes off by up to ±250): the BT.601
        # luma of its exact RGB48 instead, so a grey picture stored as RGB comes back as it was
        rgb = frame.to_ndarray(format="rgb48le").astype(np.float32)
        return np.clip(np.rint(rgb @ _BT601_LUMA), 0, 65535).astype(np.uint16)
    target = "gray16le" if info.bit_depth == 16 else "gray"
    return np.ascontiguousarray(frame.to_ndarray(format=target))


_BT601_LUMA = np.array([0.299, 0.587, 0.114], np.float32)


def _incomplete(info: VideoInfo, n: int, span: float, periods: list[float]) -> str | None:
    """How a stream that ends well before its header says it should was cut short, or None: judged by
    the declared duration when there is one (a frame count can count a CFR container's empty slots,
    as AVI's does for variable-rate video), else by the declared frame count."""
    if info.duration_s and periods:
        period = float(np.median(periods))
        missing = info.duration_s - span - period
        # the last frame lasts a nominal period in the header's sum, which a variable rate can exceed
        nominal = 1.0 / info.frame_rate_hz if info.frame_rate_hz else 0.0
        if missing > max(3 * period, 2 * nominal, 0.02 * info.duration_s):
            return (f"truncated: the header declares {info.duration_s:.3f} s, the decodable frames cover "
                    f"{info.duration_s - missing:.3f} s")
    elif info.n_frames is not None and n < info.n_frames:
        return f"truncated: the header declares {info.n_frames} frames, {n} could be decoded"
    return None


# ---------------------------------------------------------------------------------- image sequences
def _sequence_files(source) -> list[Path] | None:
    """The files of an image sequence (a folder or a glob of TIFF or PNG frames), or None when
    `source` names one file. A folder's frames are its .tif/.tiff/.png files, all of one kind."""
    s = str(source)
    if any(ch in s for ch in "*?["):
        files = [Path(p) for p in glob.glob(s) if Path(p).is_file()]
        if not files:
            raise VideoError(source, "the pattern matches no files (expected TIFF or PNG frames)")
    elif Path(s).is_dir():
        files = [p for p in Path(s).iterdir() if p.is_file() and p.suffix.lower() in SEQUENCE_SUFFIXES]
        if not files:
            raise VideoError(source, "the folder holds no .tif/.tiff/.png files (expected a sequence of "
                                     "TIFF or PNG frames)")
        kinds = {p.suffix.lower() in PNG_SUFFIXES for p in files}
        if len(kinds) > 1:
            raise VideoError(source, "the folder holds both TIFF and PNG files: expected the frames of one "
                                     "sequence (give a glob, e.g. 'DIR/*.png', to choose)")
    else:
        return None
    if len(files) > MAX_FRAMES:
        raise VideoError(source, f"{len(files)} files, over the {MAX_FRAMES} frames this reader accepts")
    return sorted(files, key=_natural_key)


def _natural_key(p: Path):
    return [int(x) if x.isdigit() else x.lower() for x in re.split(r"(\d+)", p.name)]


def _read_frame(path: Path) -> np.ndarray:
    """One frame of an image sequence: a PNG by its name, else a TIFF."""
    return _read_png(path) if path.suffix.lower() in PNG_SUFFIXES else _read_tiff(path)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_COLOUR = {0: "grey", 2: "RGB", 3: "palette", 4: "grey + alpha", 6: "RGBA"}


def _read_png(path: Path) -> np.ndarray:
    """One grey PNG: its header (IHDR: size, bit depth, colour type) is checked before OpenCV decodes
    and allocates it."""
    try:
        with open(path, "rb") as f:
            head = f.read(29)
    except OSError as e:
        raise VideoError(path, f"cannot read it ({e.strerror or e})") from None
    if len(head) < 29 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise VideoError(path, "not a PNG (no PNG signature and IHDR header)")
    w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    depth, colour = head[24], head[25]
    if colour != 0:
        raise VideoError(path, f"{PNG_COLOUR.get(colour, f'colour type {colour}')} PNG: expected a "
                               "single-channel grey PNG")
    if depth not in (8, 16):
        raise VideoError(path, f"{depth}-bit grey PNG: expected 8- or 16-bit grey")
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise VideoError(path, f"image size {w}×{h}: expected 1–{MAX_SIDE} px per side")
    return _image(path, "an 8- or 16-bit grey PNG")


def _read_tiff(path: Path) -> np.ndarray:
    """One grey TIFF: its declared size is checked (tifffile reads the header only) before OpenCV
    decodes and allocates it."""
    import tifffile

    try:
        with tifffile.TiffFile(str(path)) as tf:
            page = tf.pages[0]
            shape, samples = tuple(int(v) for v in page.shape), int(page.samplesperpixel)
    except Exception as e:   # noqa: BLE001 - tifffile raises many kinds (TypeError, AttributeError, …) on damage
        raise VideoError(path, f"not an image OpenCV can read (expected an 8- or 16-bit grey TIFF: {e})"
                         ) from None
    if samples != 1:
        raise VideoError(path, f"{samples} channels: expected a single-channel grey TIFF")
    if len(shape) != 2 or not all(1 <= v <= MAX_SIDE for v in shape):
        raise VideoError(path, f"image shape {shape}: expected one grey plane of 1–{MAX_SIDE} px per side")
    return _image(path, "an 8- or 16-bit grey TIFF")


def _image(path: Path, expected: str) -> np.ndarray:
    """OpenCV's decode of an image file whose header was checked: one grey 8- or 16-bit plane."""
    import cv2

    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise VideoError(path, f"OpenCV cannot read it as an image ({e})") from None
    if img is None:
        raise VideoError(path, f"not an image OpenCV can read (expected {expected})")
    if img.ndim == 3:
        raise VideoError(path, f"{img.shape[2]} channels: expected {expected}")
    if img.dtype not in (np.uint8, np.uint16):
        raise VideoError(path, f"pixel type {img.dtype}: expected 8- or 16-bit unsigned grey")
    return img


def _probe_sequence(source, files: list[Path], fps: float | None) -> VideoInfo:
    if fps is None or not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 100_000):
        raise VideoError(source, "an image sequence has no timestamps: give its frame rate "
                                 f"(0 < fps ≤ 100000 Hz), got {fps!r}")
    first = _read_frame(files[0])
    h, w = first.shape
    _check_size(files[0], w, h)
    depth = 16 if first.dtype == np.uint16 else 8
    png = files[0].suffix.lower() in PNG_SUFFIXES
    return VideoInfo(str(source), "png-sequence" if png else "tiff-sequence", w, h, depth, len(files),
                     len(files) / fps, float(fps), "png" if png else "tiff",
                     "gray16" if depth == 16 else "gray")


def _iter_sequence(info: VideoInfo, files: list[Path], fps: float, t0: float
                ) -> Iterator[tuple[float, np.ndarray]]:
    for k, p in enumerate(files):
        img = _read_frame(p)
        if img.shape != (info.height, info.width) or img.dtype != info.dtype:
            raise VideoError(p, f"{img.shape[1]}×{img.shape[0]} {img.dtype}: expected "
                                f"{info.width}×{info.height} {info.dtype} like the sequence's first file")
        yield t0 + k / fps, img


# ----------------------------------------------------------------------------------------- writing
class VideoWriter:
    """Write 8-bit grey frames to a playable H.264 video (libx264, yuv420p) with given times.

    The luma plane is the frame itself, flagged full range (0–255), or with ``full_range=False`` its
    limited-range codes (16–235, flagged so: a player shows the frame), and the chroma is neutral,
    so `read_video` gives the frames back (exactly at crf=0 and full range). `write(frame, t)` takes an [H, W]
    uint8 frame and its time (s); times must increase by at least one tick of the 1/90000 s time
    base, and the file's timestamps start at 0 at the first frame (`t0` keeps its time). Odd sides
    are padded by one edge row/column (yuv420p needs even sides). Use as a context manager; the
    file is complete after `close()`. `crf` is x264's constant-quality factor (0 = lossless luma,
    18 ≈ visually lossless).
    """

    def __init__(self, path: str | os.PathLike, width: int, height: int, *, crf: int = 18,
                 preset: str = "medium", nominal_fps: float = 30.0, full_range: bool = True):
        self.path = Path(path)
        self.full_range = bool(full_range)
        _check_size(self.path, width, height)
        if not self.path.parent.is_dir():
            raise VideoError(self.path, f"directory {self.path.parent} does not exist")
        if not 0 <= crf <= 51:
            raise VideoError(self.path, f"crf {crf}: expected 0–51")
        av = _av()
        self.width, self.height = int(width), int(height)
        self._pad = (self.height % 2, self.width % 2)
        self._t0 = None
        self._last_pts = -1
        self.n_frames = 0
        try:
            self._c = av.open(str(self.path), "w")
            rate = Fraction(nominal_fps).limit_denominator(1001) if nominal_fps > 0 else Fraction(30)
            s = self._c.add_stream("libx264", rate=rate)
            s.width, s.height = self.width + self._pad[1], self.height + self._pad[0]
            s.pix_fmt = "yuv420p"
            s.time_base = WRITE_TIME_BASE
            s.codec_context.time_base = WRITE_TIME_BASE
            # mbtree off: PyAV's bundled x264 (av 17–18) encodes the same frames differently from run
            # to run with it (4 of 6 encodes differed, up to 24 codes); without it every encode is the
            # same, and what the tests and benchmarks measure on a video is repeatable
            s.options = {"crf": str(int(crf)), "preset": preset, "x264-params": "mbtree=0"}
            # full range: luma 0–255 is the frame as given; limited: 16–235, as the input had it
            s.codec_context.color_range = 2 if self.full_range else 1
            self._s = s
        except _DECODE_ERRORS as e:
            raise VideoError(self.path, f"cannot open for writing H.264 ({e})") from None

    def write(self, frame: np.ndarray, t: float) -> None:
        av = _av()
        f = np.asarray(frame)
        if f.shape != (self.height, self.width) or f.dtype != np.uint8:
            raise VideoError(self.path, f"frame {self.n_frames}: got {f.dtype} {f.shape}, expected uint8 "
                                        f"({self.height}, {self.width})")
        if not math.isfinite(t):
            raise VideoError(self.path, f"frame {self.n_frames}: time {t!r} is not finite")
        if self._t0 is None:
            self._t0 = float(t)
        pts = int(round((float(t) - self._t0) / WRITE_TIME_BASE))
        if pts <= self._last_pts:
            raise VideoError(self.path, f"frame {self.n_frames}: time {t:.6f} s is not after the previous "
                                        "frame's (expected times increasing by ≥ 1/90000 s)")
        if any(self._pad):
            f = np.pad(f, ((0, self._pad[0]), (0, self._pad[1])), mode="edge")
        # the luma plane is the frame itself (full range) or its limited-range codes, chroma neutral
        if not self.full_range:
            f = full_to_limited(f)
        h, w = f.shape
        planar = np.concatenate([f.ravel(), np.full(h * w // 2, 128, np.uint8)]).reshape(h * 3 // 2, w)
        vf = av.VideoFrame.from_ndarray(planar, format="yuv420p")
        vf.pts, vf.time_base, vf.color_range = pts, WRITE_TIME_BASE, 2 if self.full_range else 1
        try:
            for p in self._s.encode(vf):
                self._c.mux(p)
        except _DECODE_ERRORS as e:
            raise VideoError(self.path, f"encoding frame {self.n_frames} failed ({e})") from None
        self._last_pts = pts
        self.n_frames += 1

    @staticmethod
    def check_path(path: str | os.PathLike) -> None:
        """Refuse, before any work, a path whose container cannot hold H.264 (from its suffix: none,
        .txt, .gif, .webm …) or whose folder cannot be written: a VideoError naming it."""
        import tempfile

        p = Path(path)
        if not p.parent.is_dir():
            raise VideoError(p, f"directory {p.parent} does not exist")
        try:
            with tempfile.NamedTemporaryFile(dir=p.parent, prefix=".thermod-check-", suffix=p.suffix) as tmp:
                with _av().open(tmp.name, "w") as c:
                    c.add_stream("libx264", rate=30)
        except OSError as e:
            raise VideoError(p, f"cannot write in {p.parent} ({e.strerror or e})") from None
        except _DECODE_ERRORS as e:
            raise VideoError(p, f"cannot hold H.264 (expected a .mp4, .mkv, .mov, .avi or .ts name: {e})"
                             ) from None

    @property
    def t0(self) -> float | None:
        """The first frame's time: the file's timestamps are relative to it."""
        return self._t0

    def close(self) -> None:
        if self._c is None:
            return
        try:
            for p in self._s.encode():
                self._c.mux(p)
            self._c.close()
        except _DECODE_ERRORS as e:
            raise VideoError(self.path, f"finishing the file failed ({e})") from None
        finally:
            self._c = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()


def write_video(path: str | os.PathLike, frames: np.ndarray | Sequence[np.ndarray], t: Sequence[float],
                *, crf: int = 18, preset: str = "medium") -> Path:
    """Write [N, H, W] uint8 frames at times t (s) as H.264 (`VideoWriter`); returns the path."""
    t = np.asarray(t, dtype=np.float64)
    n = len(frames)
    if n == 0 or t.shape != (n,):
        raise VideoError(path, f"expected ≥ 1 frame and one time per frame, got {n} frames and "
                               f"{t.shape} times")
    f0 = np.asarray(frames[0])
    if f0.ndim != 2:
        raise VideoError(path, f"frames must be [N, H, W] grey, got frame shape {f0.shape}")
    fps = 1.0 / float(np.median(np.diff(t))) if n > 1 and np.all(np.diff(t) > 0) else 30.0
    with VideoWriter(path, f0.shape[1], f0.shape[0], crf=crf, preset=preset, nominal_fps=fps) as w:
        for f, tk in zip(frames, t, strict=True):
            w.write(f, float(tk))
    return Path(path)


# --------------------------------------------------------------------------------------------- AGC
@dataclass
class PercentileAGC:
    """A thermal camera's automatic gain control: counts → 8-bit by a percentile stretch.

    Each frame's `low_pct` and `high_pct` percentiles are pulled towards by an exponential
    smoother (time constant `smoothing_s`, so the gain and offset change gradually, as a
    camera's do); the stretch maps the smoothed low level to 0 and the high level to 255:

        y = clip((x − offset) · gain, 0, 255),   offset = lo,  gain = 255 / max(hi − lo, min_span)

    `apply(frame, t)` returns (uint8 frame, gain, offset); the first frame sets the levels."""

    low_pct: float = 1.0
    high_pct: float = 99.0
    smoothing_s: float = 0.5
    min_span: float = 1.0
    _lo: float | None = field(default=None, init=False, repr=False)
    _hi: float | None = field(default=None, init=False, repr=False)
    _t: float | None = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if not (0 <= self.low_pct < self.high_pct <= 100):
            raise ThermodError(f"AGC percentiles: expected 0 ≤ low < high ≤ 100, got {self.low_pct}, "
                               f"{self.high_pct}")
        if not (self.smoothing_s >= 0 and self.min_span > 0):
            raise ThermodError("AGC: expected smoothing_s ≥ 0 and min_span > 0")

    def apply(self, frame: np.ndarray, t: float) -> tuple[np.ndarray, float, float]:
        x = np.asarray(frame, dtype=np.float32)
        lo, hi = (float(v) for v in np.percentile(x, (self.low_pct, self.high_pct)))
        if self._lo is None or self.smoothing_s == 0:
            self._lo, self._hi = lo, hi
        else:
            a = 1.0 - math.exp(-max(float(t) - self._t, 0.0) / self.smoothing_s)
            self._lo += a * (lo - self._lo)
            self._hi += a * (hi - self._hi)
        self._t = float(t)
        gain = 255.0 / max(self._hi - self._lo, self.min_span)
        return self.stretch(x, gain, self._lo), gain, self._lo

    @staticmethod
    def stretch(frame: np.ndarray, gain: float, offset: float) -> np.ndarray:
        """y = clip((x − offset) · gain, 0, 255) as uint8 (rounded): one frame's stretch applied to
        another, e.g. a deblurred frame shown with its input's AGC."""
        x = np.asarray(frame, dtype=np.float32)
        return np.clip((x - offset) * gain + 0.5, 0, 255).astype(np.uint8)
