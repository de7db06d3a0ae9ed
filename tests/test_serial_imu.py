"""Serial IMU driver against the emulator on a real pty: framing, CRC, resync, loss accounting,
disconnect/reopen, counter wrap and device reset, usb: selection."""

import os
import time

import numpy as np
import pytest

from thermod.drivers.serial_imu import SYNC, FrameParser, SerialIMU, SerialIMUError, crc16_ccitt, encode_frame
from thermod.sim.emu_serial import SerialIMUEmulator


def rates(t):
    t = np.asarray(t)
    return np.stack([np.sin(3 * t), np.cos(2 * t), 0.05 * (t % 7.0)], axis=1)


def run(gyro, seconds, timeout=0.01, tolerate=()):
    out, errors, t_end = [], 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        try:
            b = gyro.poll(timeout)
        except tolerate:
            errors += 1
            continue
        if b is not None:
            out.append(b)
    return out, errors


def seqs_of(batches):
    return np.concatenate([b.seq + np.arange(len(b)) for b in batches])


def test_crc_and_frame_layout():
    assert crc16_ccitt(b"123456789") == 0x29B1            # CRC-16/CCITT-FALSE check value
    f = encode_frame(7, 123456, [0.5, -1.0, 2.0])
    assert f[:2] == SYNC and f[2] == 20 and f[3] == 1 and len(f) == 26
    assert int.from_bytes(f[-2:], "little") == crc16_ccitt(f[2:-2])
    g = encode_frame(7, 123456, [0.5, -1.0, 2.0], int16_scale=1e-3)
    assert len(g) == 24 and g[2] == 18 and g[3] == 2


def test_parser_resyncs_on_garbage_split_frames_and_bad_crc():
    good = [encode_frame(i, 1000 * i, [i, -i, 0.25]) for i in range(5)]
    bad = bytearray(encode_frame(99, 0, [9, 9, 9]))
    bad[10] ^= 0x10
    junk = b"\x00\xa5\x13\xa5\x5a\xff\x07"                  # includes a false sync with a bad length
    stream = junk + good[0] + good[1] + bytes(bad) + good[2] + b"\xa5" + good[3] + good[4][:3]
    p = FrameParser()
    got = []
    for i in range(len(stream)):                           # byte by byte: frames split everywhere
        got += p.feed(stream[i:i + 1])
    got += p.feed(good[4][3:])
    assert [g[0] for g in got] == [0, 1, 2, 3, 4]
    assert got[3][2] == (3.0, -3.0, 0.25)
    assert p.crc_errors == 1
    assert p.garbage_bytes == len(junk) + 1 + len(bad) - 1   # the rejected frame's bytes after its sync byte


@pytest.mark.parametrize("int16_scale", [None, 2e-4])
def test_every_good_frame_received_every_bad_one_counted_none_accepted(int16_scale):
    emu = SerialIMUEmulator(rate_fn=rates, garbage_prob=0.03, drop_prob=0.01, corrupt_prob=0.02,
                            int16_scale=int16_scale, drift_ppm=150.0, seed=3)
    with emu:
        gyro = SerialIMU(emu.link)
        gyro.start()
        batches, _ = run(gyro, 1.0)
        time.sleep(0.02)
        batches += run(gyro, 0.03)[0]
        gyro.stop()
    got = seqs_of(batches)
    good = np.array(emu.log["good"])
    good = good[(good >= got.min()) & (good <= got.max())]   # bytes sent before the port opened are flushed
    bad = emu.log["corrupted"]
    assert len(good) > 800 and len(bad) > 5 and len(emu.log["dropped"]) > 2
    assert np.array_equal(got, good)                       # all good frames, in order, nothing else
    assert not np.isin(bad, got).any()
    st = gyro.stats()
    n_bad = sum(got.min() < s <= got.max() for s in bad)
    n_tail = sum(s > got.max() for s in bad)            # rejected after the last good frame was read
    assert n_bad <= st["crc_errors"] <= n_bad + n_tail + 3   # + rare false syncs inside a corrupted frame
    junk = sum(n for s, n in emu.log["garbage_before"].items() if got.min() < s <= got.max())
    assert junk > 100 and st["garbage_bytes"] >= junk
    lost = sorted(s for s in emu.log["dropped"] + bad if got.min() < s < got.max())
    assert st["lost"] == len(lost)
    for prev, b in zip(batches[:-1], batches[1:], strict=True):
        end = prev.seq + len(prev)
        assert b.seq == end + b.n_lost and b.gap_before == (b.n_lost > 0)
    # rates as sent (float32 exactly, int16 within half a step), at the true sample times
    t_true = np.array([emu.truth_t[s] for s in got])
    r = np.concatenate([b.rate for b in batches])
    assert r.dtype == np.float32
    tol = 1e-6 if int16_scale is None else int16_scale / 2 + 1e-6
    assert np.max(np.abs(r - rates(t_true))) <= tol
    # times come from the device clock: close to the truth, not to the 5 ms write bursts
    t = np.concatenate([b.t for b in batches])
    assert np.all(np.diff(t) > 0)
    err = (t - t_true)[len(t) // 2:]
    assert abs(np.median(err)) < 1.0e-3 and np.std(err) < 0.5e-3


def test_disconnect_raises_once_then_reopens_with_a_gap():
    with SerialIMUEmulator(rate_fn=rates, seed=1) as emu:
        gyro = SerialIMU(emu.link, reopen_interval_s=0.05)
        gyro.start()
        before, _ = run(gyro, 0.2)
        emu.disconnect(0.3)
        with pytest.raises(SerialIMUError, match="disconnected.*will reopen"):
            for _ in range(50):
                gyro.poll(0.01)
        assert gyro.stats()["connected"] == 0
        after, errors = run(gyro, 0.6, tolerate=SerialIMUError)
        gyro.stop()
    assert errors == 0                                     # raised once; later polls retry quietly
    st = gyro.stats()
    assert st["disconnects"] == 1 and st["reconnects"] == 1
    gap = [b for b in after if b.gap_before]
    assert len(gap) == 1 and gap[0] is after[0]
    assert gap[0].seq == before[-1].seq + len(before[-1]) + gap[0].n_lost
    assert gap[0].n_lost >= len(emu.log["offline"]) >= 250
    assert sum(len(b) for b in after) > 150


def test_counter_wrap_and_device_reset():
    # counters start 300 samples before the 32-bit wrap; later the device reboots (counters → 0)
    with SerialIMUEmulator(rate_fn=rates, seq0=2**32 - 300, t_us0=2**32 - 250_000, seed=2) as emu:
        gyro = SerialIMU(emu.link, reopen_interval_s=0.05)
        gyro.start()
        first, _ = run(gyro, 0.5)
        emu.disconnect(0.1, reset_counters=True)
        after, errors = run(gyro, 0.5, tolerate=SerialIMUError)
        gyro.stop()
    s = seqs_of(first)
    assert s[0] >= 2**32 - 300 and s[-1] > 2**32 + 100 and np.all(np.diff(s) == 1)   # unwrapped
    t = np.concatenate([b.t for b in first + after])
    assert np.all(np.diff(t) > 0)
    assert errors == 1 and gyro.stats()["resets"] == 1
    assert after[0].gap_before and after[0].seq > s[-1]
    assert np.all(np.diff(seqs_of(after)) == 1)
    # the mapping restarted on the new device clock: times still track the truth, which the z rate
    # encodes (0.05 · (t mod 7), float32: ~1 µs resolution)
    t_after = np.concatenate([b.t for b in after])
    z = np.concatenate([b.rate for b in after])[:, 2].astype(np.float64) / 0.05
    truth = 7.0 * np.round((t_after - z) / 7.0) + z
    assert np.median(np.abs(t_after - truth)[-200:]) < 1.5e-3


def test_device_reboot_without_disconnect():
    with SerialIMUEmulator(rate_fn=rates, seq0=5000, t_us0=10**9, batch_s=0.02, seed=4) as emu:
        gyro = SerialIMU(emu.link)
        gyro.start()
        first, _ = run(gyro, 0.3)
        emu.reboot()                                    # counters restart at 0 mid-stream
        after, errors = run(gyro, 0.4)
        gyro.stop()
    assert errors == 0 and gyro.stats()["resets"] == 1
    batches = first + after
    s = seqs_of(batches)
    assert np.all(np.diff(s) >= 1)                      # the unwrapped sequence keeps increasing
    gaps = [b for b in batches if b.gap_before]
    assert len(gaps) == 1 and gaps[0].n_lost <= 5       # nothing was lost: the host-time estimate is close
    t = np.concatenate([b.t for b in batches])
    assert np.all(np.diff(t) > 0)
    z = np.concatenate([b.rate for b in batches])[:, 2].astype(np.float64) / 0.05
    truth = 7.0 * np.round((t - z) / 7.0) + z
    assert np.median(np.abs(t - truth)[-100:]) < 1.5e-3


def test_open_errors_name_the_port(tmp_path):
    with pytest.raises(SerialIMUError, match=r"cannot open .*nope.*by-id"):
        SerialIMU(str(tmp_path / "nope")).start()


def test_usb_spec_resolves_through_sysfs(tmp_path):
    with SerialIMUEmulator(rate_fn=rates) as emu:
        sysfs, dev = tmp_path / "sys", tmp_path / "dev"
        d = sysfs / "bus/usb/devices/1-1.2"
        (d / "1-1.2:1.0" / "ttyUSB3").mkdir(parents=True)
        (d / "idVendor").write_text("0403\n")
        (d / "idProduct").write_text("6015\n")
        (d / "serial").write_text("EMU0001\n")
        dev.mkdir()
        os.symlink(emu.link, dev / "ttyUSB3")
        gyro = SerialIMU("usb:0403:6015:EMU0001", sysfs_root=str(sysfs), dev_root=str(dev))
        gyro.start()
        batches, _ = run(gyro, 0.1)
        gyro.stop()
    assert sum(len(b) for b in batches) > 50
    with pytest.raises(SerialIMUError, match="0403:6016.*no tty"):
        SerialIMU("usb:0403:6016", sysfs_root=str(sysfs), dev_root=str(dev)).start()
