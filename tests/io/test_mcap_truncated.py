"""`thermod import` of an MCAP file cut short: the ``.mcap.part`` a killed `thermod record -o X.mcap`
leaves, and a complete file cut at many byte offsets. What is imported is checked against what the
`mcap` library's own streaming reader gets out of the same bytes."""

import json
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
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Footer, Header
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

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


def start_recorder(out: Path, endpoint: str) -> subprocess.Popen:
    """A real `thermod record -o OUT.mcap` process, this checkout's thermod whatever the environment's
    install points at."""
    path = os.pathsep.join(filter(None, (str(REPO), os.environ.get("PYTHONPATH"))))
    env = dict(os.environ, PYTHONPATH=path)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    return subprocess.Popen([sys.executable, "-m", "thermod.cli", "record", "-o", str(out), "--endpoint",
                             endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)


def kill(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(30) == -signal.SIGKILL, proc.stderr.read()


def valid_up_to_the_cut(path: Path) -> None:
    """The mcap library reads `path` record by record, chunk CRCs checked, from its Header up to a
    last record cut short, which is at most one chunk (1 MiB)."""
    size = path.stat().st_size
    records, end = [], 0
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False, validate_crcs=True).records:
                records.append(record)
                end = f.tell()
        except (McapError, struct.error, ValueError):      # the library's own end at the cut
            pass
    assert isinstance(records[0], Header) and not any(isinstance(r, Footer) for r in records)
    assert size - end <= (1 << 20) + 4096, (size, end)


def test_a_killed_mcap_recorder_leaves_a_part_file_that_imports(tmp_path, caplog, capsys):
    """Two real `thermod record -o X.mcap` processes on a publisher of ~50 frames/s (16×16, and 5 gyro
    samples each: ~0.17 MB/s, so a 1 MiB chunk fills in ~6 s) with the daemon's health (its
    calibration) every 0.5 s, the calibration changed partway as by a SIGHUP reload. `streaming` is
    SIGKILLed while messages flow, 3 s after the change; `paused` once nothing has been sent for a
    while and its ``.part`` holds every frame sent. `thermod import X.mcap.part` with no option
    recovers every complete frame and gyro sample the library streams from each file, with the
    daemon's last calibration and a warning that it changed; `streaming`'s frames reach to within 2 s
    of its kill (the recorder ends its chunk every second), `paused`'s to the last frame sent (it does
    so while nothing arrives, too)."""
    h, w, per_frame = 16, 16, 5
    calib = Calibration(width=w, height=h, cx=7.5, cy=7.5, fx=300.0, fy=310.0, tau_s=0.011)
    reloaded = Calibration(width=w, height=h, cx=7.5, cy=7.5, fx=320.0, fy=330.0, tau_s=0.012)
    names = ("streaming", "paused")
    outs = {k: tmp_path / f"{k}.mcap" for k in names}
    parts = {k: tmp_path / f"{k}.mcap.part" for k in names}
    pub = Publisher("tcp://127.0.0.1:*", queue_size=512, hwm=512).start()
    procs = {k: start_recorder(outs[k], pub.endpoint) for k in names}
    sent_t: list[float] = []          # each frame's stamp: the host clock when it was sent
    try:
        deadline = time.monotonic() + 120      # a bound against a hang, not a measured time
        seen = change = None
        last_health = -np.inf
        while True:
            for k, proc in procs.items():
                assert proc.poll() is None, (k, proc.stderr.read())
            now = time.monotonic()
            assert now < deadline, "the recorders never wrote frames and gyro"
            if now - last_health >= 0.5:
                pub.publish_health(calibration=calib if change is None else reloaded)
                last_health = now
            i = len(sent_t)
            pub.publish_raw(frame(i, h, w), now, frame_id=i)
            pub.publish_frame(frame(i, h, w).astype(np.float32), now, frame_id=i, deblurred=True)
            pub.publish_gyro(now - 0.02 + np.arange(per_frame) * 0.02 / per_frame,
                             np.full((per_frame, 3), 1e-3 * i), seq=per_frame * i)
            sent_t.append(now)
            time.sleep(0.02)
            if seen is None and i % 10 == 0:
                got = [streamed(parts[k]) if parts[k].exists() else {} for k in names]
                if all(len(g.get(mcap.RAW_TOPIC, [])) >= 5 and len(g.get(mcap.IMU_TOPIC, [])) >= 25
                       for g in got):
                    seen = now
            if seen is not None and change is None and now - seen >= 1.0:
                change = now
                last_health = -np.inf           # the reloaded calibration goes out next
            if change is not None and now - change >= 3.0:
                break
        kill(procs["streaming"])
        killed_at = time.monotonic()
        # nothing more is sent, not even health: only the recorder's own pace can end its chunk
        while len(streamed(parts["paused"]).get(mcap.RAW_TOPIC, [])) < 5 or \
                max(m.log_time for m in streamed(parts["paused"])[mcap.RAW_TOPIC]) < round(sent_t[-1] * 1e9):
            assert procs["paused"].poll() is None, procs["paused"].stderr.read()
            assert time.monotonic() < deadline, "the paused recorder never wrote its last frames"
            time.sleep(0.2)
        kill(procs["paused"])
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
            proc.stderr.close()
        pub.stop()

    for k in names:
        part = parts[k]
        assert part.exists() and not outs[k].exists()
        valid_up_to_the_cut(part)
        caplog.clear()
        capsys.readouterr()
        assert cli.main(["import", str(part), "-o", str(tmp_path / f"{k}.h5")]) == 0, capsys.readouterr().err
        n_frames, n_gyro = check_import_equals_stream(part, tmp_path / f"{k}.h5", h, w)
        assert 5 <= n_frames <= len(sent_t) and 25 <= n_gyro <= per_frame * len(sent_t)
        rec = recording.read(tmp_path / f"{k}.h5")
        assert rec.calibration == reloaded, k
        assert rec.extra_attrs["record"]["imported_calibration"] == "thermod metadata"
        logged = [r.getMessage() for r in caplog.records]
        assert sum("truncated MCAP file" in m for m in logged) == 1
        changed = f"{part}: the calibration changed while recording (2 calibrations"
        assert any(changed in m for m in logged), logged
        # every frame on disk has its CameraInfo, from the calibration in force when it arrived
        fx = camera_info_fx(part)
        assert sorted(fx) == sorted(m.log_time for m in streamed(part)[mcap.RAW_TOPIC])
        assert set(fx.values()) == {300.0, 320.0}, set(fx.values())
        if k == "streaming":
            lag = killed_at - rec.t[-1]
            assert lag < 2.0, f"the last frame on disk was sent {lag:.2f} s before the kill"
        else:
            assert rec.t[-1] == pytest.approx(sent_t[-1], abs=1e-6)


def camera_info_fx(path) -> dict[int, float]:
    """{log time: fx} of the CameraInfo messages the mcap library decodes from `path` before the cut."""
    out = {}
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, decoder_factories=[DecoderFactory()])
        try:
            for _, _, message, info in reader.iter_decoded_messages(topics=[mcap.CAMERA_INFO_TOPIC],
                                                                    log_time_order=False):
                out[message.log_time] = float(info.k[0])
        except (McapError, struct.error, ValueError):
            pass
    return out


def test_the_recorder_writes_each_calibration_when_it_arrives(tmp_path, caplog, capsys):
    """Frames before the first health message get their CameraInfo when its calibration arrives, which
    is written and flushed at once (a copy of the ``.part`` then, as a kill would leave it, imports
    with it); the same calibration again writes nothing, a new one (a reload) a second record. The
    complete file imports the last one, with a warning; each CameraInfo has the one in force when its
    frame arrived."""
    h, w = 12, 16
    first = Calibration(width=w, height=h, cx=7.5, cy=5.5, fx=200.0, fy=210.0, tau_s=0.01)
    second = Calibration(width=w, height=h, cx=7.5, cy=5.5, fx=250.0, fy=260.0, tau_s=0.012)
    out = tmp_path / "rec.mcap"
    part = tmp_path / "rec.mcap.part"
    writer = mcap.McapRecordWriter(out, flush_s=3600.0)     # no flush by the clock here

    def raw(i):
        writer.add("raw", {"t": 10.0 + 0.02 * i, "frame_id": i}, frame(i, h, w))

    for i in range(3):
        raw(i)
    writer.add("health", {"t": 10.05, "calibration": {**first.as_dict(), "source": "config"}}, None)
    (tmp_path / "early.mcap.part").write_bytes(part.read_bytes())
    for i in range(3, 5):
        raw(i)
    writer.add("health", {"t": 10.1, "calibration": first.as_dict()}, None)
    writer.add("health", {"t": 10.15, "calibration": second.as_dict()}, None)
    for i in range(5, 7):
        raw(i)
    assert writer.finish(attrs={"endpoint": "x"}) == out and writer.source == "health"

    assert camera_info_fx(tmp_path / "early.mcap.part") == {round((10.0 + 0.02 * i) * 1e9): 200.0
                                                            for i in range(3)}
    assert cli.main(["import", str(tmp_path / "early.mcap.part"), "-o", str(tmp_path / "early.h5")]) == 0
    early = recording.read(tmp_path / "early.h5")
    assert early.calibration == first and early.n_frames == 3

    with open(out, "rb") as f:
        reader = make_reader(f)
        records = [m.metadata for m in reader.iter_metadata() if m.name == mcap.METADATA_NAME]
    assert [json.loads(m["calibration"])["fx"] for m in records] == [200.0, 250.0, 250.0]
    assert [m.get("from_t") for m in records] == ["10.05", "10.15", None]
    assert records[-1]["calibration_source"] == "health" and records[-1]["endpoint"] == "x"
    assert sorted(camera_info_fx(out).values()) == [200.0] * 5 + [250.0] * 2
    caplog.clear()
    assert cli.main(["import", str(out), "-o", str(tmp_path / "rec.h5")]) == 0
    assert recording.read(tmp_path / "rec.h5").calibration == second
    assert any(f"{out}: the calibration changed while recording (2 calibrations" in r.getMessage()
               and "in force from t = 10.15 s" in r.getMessage() for r in caplog.records)


def test_a_recording_killed_before_any_calibration_needs_one(tmp_path, capsys):
    """No health message yet, no --config: the ``.part`` has frames but no calibration, and the import
    error says what to give."""
    out, part = tmp_path / "rec.mcap", tmp_path / "rec.mcap.part"
    writer = mcap.McapRecordWriter(out, flush_s=0.0)
    for i in range(3):
        writer.add("raw", {"t": 1.0 + 0.02 * i, "frame_id": i}, frame(i, 12, 16))
    cut = tmp_path / "cut.mcap.part"
    cut.write_bytes(part.read_bytes())
    writer.discard()
    capsys.readouterr()
    assert cli.main(["import", str(cut), "-o", str(tmp_path / "a.h5")]) == 2
    err = capsys.readouterr().err
    assert f"{cut}: no thermod calibration" in err and "truncated recording" in err, err
    assert "--calibration" in err and not (tmp_path / "a.h5").exists()


def test_an_idle_recorder_ends_its_chunk(tmp_path):
    """Messages then nothing: `tick` (what `record` calls while nothing arrives) ends the chunk once
    `flush_s` have passed, so the ``.part`` holds every message though no more come."""
    out, part = tmp_path / "rec.mcap", tmp_path / "rec.mcap.part"
    writer = mcap.McapRecordWriter(out, Calibration(width=16, height=12, cx=7.5, cy=5.5), flush_s=0.2)
    for i in range(4):
        writer.add("raw", {"t": 1.0 + 0.02 * i, "frame_id": i}, frame(i, 12, 16))
    time.sleep(0.3)
    writer.tick()
    got = streamed(part)
    assert [m.sequence for m in got[mcap.RAW_TOPIC]] == list(range(4))
    assert len(got[mcap.CAMERA_INFO_TOPIC]) == 4
    writer.discard()


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


# ------------------------------------------------------------------ chunks that do not open in bounds
def _compressed_file(path: Path, compression, payload: bytes) -> Path:
    """One message of `payload` in one chunk, written by the mcap library's own Writer."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f, compression=compression)
        w.start()
        cid = w.register_channel("/blob", "application/octet-stream", 0)
        w.add_message(cid, log_time=1, data=payload, publish_time=1)
        w.finish()
    return path


def _chunks(path: Path) -> list:
    from mcap.records import Chunk

    with open(path, "rb") as f:
        return [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]


def _declare(path: Path, size: int) -> Path:
    """`path` with its first chunk's declared uncompressed size (a u64) set to `size`."""
    data = bytearray(path.read_bytes())
    header_len = struct.unpack_from("<Q", data, len(mcap.MAGIC) + 1)[0]
    at = len(mcap.MAGIC) + 9 + header_len                   # the chunk record: opcode, length, ...
    assert data[at] == Opcode.CHUNK
    struct.pack_into("<Q", data, at + 9 + 16, size)         # ... start, end time, uncompressed_size
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("kind", ["lz4", "zstd"])
def test_a_chunk_that_decompresses_beyond_the_bound_is_refused_before_it_is_allocated(tmp_path, kind,
                                                                                      monkeypatch):
    """A compression bomb (8 MiB of zeros in a few kB) declaring 100 bytes, against a 1 MiB bound:
    decoded up to the bound only and refused by `Bag`, naming the file; a true declaration over the
    bound is refused from the field; under the bound the bomb's lie is named."""
    from mcap.writer import CompressionType

    comp = CompressionType.LZ4 if kind == "lz4" else CompressionType.ZSTD
    path = _compressed_file(tmp_path / f"bomb_{kind}.mcap", comp, bytes(8 * 2**20))
    (chunk,) = _chunks(path)
    assert chunk.compression == kind and len(chunk.data) < 2**17
    assert "declares 8388" in mcap.chunk_problem(chunk, limit=2**20)
    (chunk,) = _chunks(_declare(path, 100))
    assert "more than 1048576 bytes" in mcap.chunk_problem(chunk, limit=2**20)
    assert "not the 100 it declares" in mcap.chunk_problem(chunk, limit=16 * 2**20)
    monkeypatch.setattr(mcap, "MAX_CHUNK_BYTES", 2**20)
    with pytest.raises(mcap.RecordingError, match=rf"bomb_{kind}\.mcap.*more than 1048576 bytes"):
        mcap.Bag(path)


def test_a_chunk_whose_size_field_lies_is_refused_by_thermod_import(tmp_path, capsys):
    """The chunk's declared uncompressed size (a u64 the library allocates by) set to 2⁴⁰ in the file:
    `thermod import` exits 2 naming the file, before any allocation of that size."""
    from mcap.writer import CompressionType

    path = _compressed_file(tmp_path / "lies.mcap", CompressionType.ZSTD, bytes(range(256)) * 64)
    _declare(path, 2**40)
    assert cli.main(["import", str(path), "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "lies.mcap" in err and "declares 1099511627776 bytes uncompressed" in err, err
    assert not (tmp_path / "x.h5").exists()
