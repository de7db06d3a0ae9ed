"""`thermod import` of an MCAP file cut short: the ``.mcap.part`` a killed `thermod record -o X.mcap`
leaves, and a complete file cut at many byte offsets. What is imported is checked against what the
`mcap` library's own streaming reader gets out of the same bytes."""

import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import NonSeekingReader

from thermod import cli
from thermod.io import mcap, recording
from thermod.physics.calibration import Calibration
from thermod.runtime.publish import Publisher

REPO = Path(__file__).resolve().parents[2]


def streamed(path) -> dict[str, list]:
    """{topic: [Message]} the mcap library streams from `path` before it stops at the cut."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        try:
            for _, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                out.setdefault(channel.topic, []).append(message)
        except (McapError, struct.error, ValueError):      # the library's own end at the cut
            pass
    return out


def calibration_toml(path: Path, calib: Calibration) -> Path:
    """A [calibration] table: a truncated recording has none of its own."""
    keys = ("width", "height", "fx", "fy", "cx", "cy", "tau_s")
    path.write_text("[calibration]\n" + "".join(f"{k} = {getattr(calib, k)!r}\n" for k in keys))
    return path


def frame(i: int, h: int, w: int) -> np.ndarray:
    """Frame `i`'s counts, different for every i, so an imported frame says which it is."""
    return ((np.arange(h * w, dtype=np.int64).reshape(h, w) * 7 + 1009 * i) % 60000).astype(np.uint16)


def check_import_equals_stream(path: Path, out: Path, h: int, w: int) -> tuple[int, int]:
    """The recording imported from `path` holds exactly the raw frames and gyro samples the mcap
    library streams from it; returns their numbers."""
    got = streamed(path)
    raw, imu = got.get(mcap.RAW_TOPIC, []), got.get(mcap.IMU_TOPIC, [])
    rec = recording.read(out)
    assert rec.n_frames == len(raw) and len(rec.gyro_t) == len(imu)
    order = np.argsort([m.log_time for m in raw], kind="stable")
    assert np.allclose(rec.t, np.array([raw[k].log_time for k in order]) * 1e-9, rtol=0, atol=1e-9)
    for i, k in enumerate(order):
        assert np.array_equal(rec.frames[i], frame(raw[k].sequence, h, w))
    assert np.allclose(np.sort(rec.gyro_t), np.sort([m.log_time for m in imu]) * 1e-9, rtol=0, atol=1e-9)
    return len(raw), len(imu)


def test_a_killed_mcap_recorder_leaves_a_part_file_that_imports(tmp_path, caplog, capsys):
    """A real `thermod record -o rec.mcap` process on a publisher, SIGKILLed once the library reads
    frames and gyro in its ``.part``: `thermod import rec.mcap.part` recovers every complete frame and
    gyro sample — those the library streams from the file — and says the file was truncated."""
    h, w = 96, 128
    calib = Calibration(width=w, height=h, cx=63.5, cy=47.5, fx=300.0, fy=310.0, tau_s=0.011)
    out, part = tmp_path / "rec.mcap", tmp_path / "rec.mcap.part"
    pub = Publisher("tcp://127.0.0.1:*", queue_size=512, hwm=512).start()
    # this checkout's thermod in the recorder process, whatever the environment's install points at
    path = os.pathsep.join(filter(None, (str(REPO), os.environ.get("PYTHONPATH"))))
    env = dict(os.environ, PYTHONPATH=path)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    proc = subprocess.Popen([sys.executable, "-m", "thermod.cli", "record", "-o", str(out), "--endpoint",
                             pub.endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=env)
    sent = 0
    try:
        deadline = time.monotonic() + 120      # a bound against a hang, not a measured time
        while True:
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "the recorder never wrote frames and gyro"
            t = 1000.0 + 0.02 * sent
            pub.publish_health(calibration=calib)
            pub.publish_raw(frame(sent, h, w), t, frame_id=sent)
            pub.publish_frame(frame(sent, h, w).astype(np.float32), t, frame_id=sent, deblurred=True)
            pub.publish_gyro(t - 0.02 + np.arange(20) * 1e-3, np.full((20, 3), 1e-3 * sent), seq=20 * sent)
            sent += 1
            time.sleep(0.01)
            if sent % 10 == 0 and part.exists():
                on_disk = streamed(part)
                if len(on_disk.get(mcap.RAW_TOPIC, [])) >= 5 and len(on_disk.get(mcap.IMU_TOPIC, [])) >= 100:
                    break
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        proc.stderr.close()
        pub.stop()
    assert part.exists() and not out.exists()

    # without a calibration: the recorder writes it last, so the error says what to give
    capsys.readouterr()
    assert cli.main(["import", str(part), "-o", str(tmp_path / "a.h5")]) == 2
    err = capsys.readouterr().err
    assert f"{part}: no thermod calibration" in err and "truncated recording" in err, err
    # nor from --tau and CameraInfo: the recorder writes camera info last too (not defaults in silence)
    assert cli.main(["import", str(part), "-o", str(tmp_path / "a.h5"), "--tau", "0.011"]) == 2
    assert f"no complete message on {mcap.CAMERA_INFO_TOPIC}" in capsys.readouterr().err
    assert not (tmp_path / "a.h5").exists()

    toml = calibration_toml(tmp_path / "c.toml", calib)
    caplog.clear()
    assert cli.main(["import", str(part), "-o", str(tmp_path / "rec.h5"), "--calibration", str(toml)]) == 0
    n_frames, n_gyro = check_import_equals_stream(part, tmp_path / "rec.h5", h, w)
    # what the recorder flushed: at least what was seen before the kill, at most what was sent
    assert 5 <= n_frames <= sent and 100 <= n_gyro <= 20 * sent
    warnings = [r.getMessage() for r in caplog.records if "truncated MCAP file" in r.getMessage()]
    total = sum(len(v) for v in streamed(part).values())
    assert len(warnings) == 1 and str(part) in warnings[0]
    assert f"recovered the {total} complete messages" in warnings[0]
    assert recording.read(tmp_path / "rec.h5").calibration.fx == 300.0


# ------------------------------------------------------------------------------- cut at many offsets
H, W, TICKS = 240, 320, 12
CALIB = Calibration(width=W, height=H, cx=159.5, cy=119.5, fx=300.0, fy=300.0, tau_s=0.01)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """A complete MCAP from thermod's writer, as `thermod record` writes it (uncompressed chunks of
    about 1 MiB, here a few frames each): its folder, and where its top-level records start."""
    d = tmp_path_factory.mktemp("cut")
    w = mcap.McapWriter(d / "whole.mcap", compress=False)
    for i in range(TICKS):
        t = 1.0 + 0.02 * i
        w.raw(frame(i, H, W), t, i)
        w.deblurred(frame(i, H, W).astype(np.float32), t, i)
        w.gyro(t - 0.02 + np.arange(20) * 1e-3, np.full((20, 3), 0.1 * i), 20 * i)
    w.metadata(CALIB)
    w.commit()
    data = (d / "whole.mcap").read_bytes()
    starts, pos = [], len(mcap.MAGIC)
    while pos < len(data) - len(mcap.MAGIC):
        starts.append(pos)
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]      # opcode u8, length u64, content
    assert pos == len(data) - len(mcap.MAGIC)
    return d, starts


def check_cut(d: Path, cut: int, capsys) -> int:
    """`thermod import` of the first `cut` bytes: the complete messages before the cut (as the mcap
    library streams them), or exit 2 with an error naming the file; never a traceback (exit 1).
    Returns the exit code."""
    data = (d / "whole.mcap").read_bytes()
    part, out = d / "cut.mcap.part", d / "cut.h5"
    part.write_bytes(data[:cut])
    out.unlink(missing_ok=True)
    toml = calibration_toml(d / "cut.toml", CALIB)
    capsys.readouterr()
    rc = cli.main(["import", str(part), "-o", str(out), "--calibration", str(toml)])
    err = capsys.readouterr().err
    got = streamed(part)
    if rc == 0:
        n_frames, n_gyro = check_import_equals_stream(part, out, H, W)
        assert n_frames > 0
        if cut == len(data):
            assert (n_frames, n_gyro) == (TICKS, 20 * TICKS)
    else:
        assert rc == 2, (cut, err)
        assert f"{part}: " in err and not out.exists(), (cut, err)
        # refused only when nothing complete precedes the cut: no frame the library can stream
        assert not got.get(mcap.RAW_TOPIC), (cut, err)
        assert "not a readable MCAP file" in err or "no frames" in err, (cut, err)
    return rc


def test_cut_at_record_boundaries_and_inside_records(whole, capsys):
    """Cuts at, just after and inside the data section's records (the header, chunks, metadata and
    data end: at the start, after the opcode, after the length, halfway, one byte short), inside each
    message index, and in the summary section (every message is complete there)."""
    d, starts = whole
    data = (d / "whole.mcap").read_bytes()
    ends = [*starts[1:], len(data) - len(mcap.MAGIC)]
    cuts = {0, 4, len(mcap.MAGIC), len(data) - 1, len(data)}
    summary = False
    for s, e in zip(starts, ends, strict=True):
        opcode = data[s]
        if summary:
            cuts.add(s)
        elif opcode in (Opcode.HEADER, Opcode.CHUNK, Opcode.METADATA, Opcode.DATA_END):
            cuts |= {s, s + 1, s + 9, (s + e) // 2, e - 1}
        else:
            cuts.add((s + e) // 2)
        summary = summary or opcode == Opcode.DATA_END
    codes = [check_cut(d, cut, capsys) for cut in sorted(cuts)]
    assert codes.count(0) > 10 and codes.count(2) > 5      # both outcomes are exercised


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0.0, 1.0))
def test_cut_at_any_offset(whole, capsys, fraction):
    d, _ = whole
    check_cut(d, round(fraction * (d / "whole.mcap").stat().st_size), capsys)
