"""GigE Vision driver against the real Aravis fake camera (`arv-fake-gv-camera-0.8 -i 127.0.0.1`), a
genuine GVCP/GVSP peer on loopback, plus unit tests of the 16-bit frame-id unwrapping."""

import time

import numpy as np
import pytest

from tests.support import aravis
from thermod.drivers.aravis_camera import AravisCamera
from thermod.drivers.camera_base import FrameIdTracker, as_uint16_image
from thermod.errors import DeviceError

fake_camera = aravis.fake_camera
_collect = aravis._collect


# ------------------------------------------------------------------ frame-id unwrapping (pure)
def test_frame_id_wrap_skips_zero():
    tr = FrameIdTracker()
    out = [tr.update(i) for i in (65533, 65534, 65535, 1, 2)]
    assert [fid for fid, _ in out] == [65533, 65534, 65535, 65536, 65537]
    assert [g for _, g in out] == [0, 0, 0, 0, 0]
    assert tr.wraps == 1 and tr.lost == 0


def test_frame_id_gap_across_wrap():
    tr = FrameIdTracker()
    tr.update(65534)
    fid, gap = tr.update(3)            # lost 65535, 1, 2
    assert (fid, gap) == (65538, 3)
    fid, gap = tr.update(5)            # lost 4
    assert (fid, gap) == (65540, 1)
    assert tr.lost == 4 and tr.gaps == 2


def test_frame_id_invalid_and_reset():
    tr = FrameIdTracker()
    tr.update(100)
    assert tr.update(0) == (101, 0)    # 0 is invalid: numbered as the expected id
    assert tr.update(102) == (102, 0)  # and the stream continues without a phantom gap
    assert tr.update(7) == (103, 0)    # far backwards: device counter restarted
    assert tr.update(8) == (104, 0)
    assert (tr.invalid, tr.resets, tr.lost) == (1, 1, 0)
    tr.resync()                        # reconnect: unwrapped ids continue from where they were
    assert tr.update(40000) == (105, 0)


def test_extended_64bit_block_ids():
    tr = FrameIdTracker()
    tr.update(65534)
    assert tr.update(65536) == (65536, 1)   # a GEV 2 camera with 64-bit ids: 65535 was lost
    assert tr.extended and tr.update(1 << 40) == (1 << 40, (1 << 40) - 65537)


def test_byte_buffers_reshape_little_endian():
    img = (np.arange(12, dtype=np.uint16) * 1000 + 7).reshape(3, 4)
    raw = img.astype("<u2").tobytes()
    for data in (raw, np.frombuffer(raw, np.uint8), np.frombuffer(raw, np.uint8).reshape(1, -1),
                 np.frombuffer(raw, np.uint8).reshape(3, 8), img.reshape(1, -1)):
        np.testing.assert_array_equal(as_uint16_image(data, 3, 4, "cam"), img)
    with pytest.raises(DeviceError, match=r"cam: expected a 3×4 16-bit frame.*8-bit colour"):
        as_uint16_image(np.zeros((3, 4, 3), np.uint8), 3, 4, "cam")


def test_bad_arguments_are_device_errors():
    with pytest.raises(DeviceError, match="exactly one of address"):
        AravisCamera()
    with pytest.raises(DeviceError, match="pixel_formats"):
        AravisCamera("127.0.0.1", pixel_formats=("RGB8",))


# ------------------------------------------------------------------ real GVCP/GVSP on loopback
@pytest.mark.hardware
def test_frames_at_rate_with_mapped_timestamps(fake_camera):
    cam = AravisCamera("127.0.0.1", width=320, height=240, frame_rate_hz=40.0, packet_size=1500)
    with cam:
        frames = _collect(cam, 140)     # the fake camera starts its block ids at 65401: crosses the wrap
        st = cam.stats()
    f = frames[-1]
    assert f.image.dtype == np.uint16 and f.image.shape == (240, 320)
    assert f.image.max() > 0                          # the fake camera's gradient pattern, not zeros
    assert st["pixel_format"] == "Mono16" and st["packet_size"] == 1500
    t = np.array([f.t for f in frames])
    ids = np.array([f.frame_id for f in frames])
    assert np.all(np.diff(t) > 0)
    # the device's own timestamps (ns) give the configured period exactly; mapped to the host clock
    # they keep it up to the fitted drift (reads on a loaded host jitter far more than that)
    dev = np.array([f.device_ts for f in frames], np.int64)
    np.testing.assert_allclose(np.median(np.diff(dev) / np.diff(ids)), 25e6, rtol=0.005)
    np.testing.assert_allclose(np.median(np.diff(t) / np.diff(ids)), 1 / 40.0, rtol=0.05)
    lag = np.array([f.arrival - f.t for f in frames])
    # stamped by the device, not the read: never after the arrival, and the mapping sits on the lower
    # envelope of the arrivals (the fastest reads), whatever the load does to the others
    assert np.all(lag >= -1e-6) and np.min(lag) < 0.05, lag
    # a frame the loaded host did not read in time is lost, and then counted as an id gap
    assert np.all(np.diff(ids) == 1 + np.array([f.gap_before for f in frames[1:]]))
    assert st["frames_lost"] == sum(f.gap_before for f in frames), st
    assert st["id_wraps"] == 1 and st["invalid_ids"] == 0
    assert st["device"] == "127.0.0.1" and st["state"] == "streaming" and cam.stats()["state"] == "stopped"


@pytest.mark.hardware
def test_open_by_serial_and_rate_change(fake_camera):
    cam = AravisCamera(device_id=fake_camera.serial, width=160, height=120, frame_rate_hz=20.0)
    with cam:
        frames = _collect(cam, 20)
    assert cam.stats()["frame_rate_hz"] == pytest.approx(20.0)
    # the camera's own clock shows the new period (host arrival times would show the machine's load)
    dev = np.array([f.device_ts for f in frames], np.int64)
    ids = np.array([f.frame_id for f in frames])
    np.testing.assert_allclose(np.median(np.diff(dev) / np.diff(ids)), 50e6, rtol=0.005)
    assert frames[0].image.shape == (120, 160)


@pytest.mark.hardware
def test_unknown_serial_and_absent_camera_name_what_to_check(fake_camera):
    with pytest.raises(DeviceError, match="no GigE camera with id/serial 'NOPE'"):
        AravisCamera(device_id="NOPE").start()
    with pytest.raises(DeviceError, match=r"frame rate 5000.0 Hz not accepted"):
        AravisCamera("127.0.0.1", frame_rate_hz=5000.0).start()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=r"no GigE Vision camera answers at 127.0.0.2 .*UDP 3956"):
        AravisCamera("127.0.0.2").start()
    assert time.monotonic() - t0 < 5.0      # one 0.3 s probe; the bound only catches a hang


@pytest.mark.hardware
@pytest.mark.slow
@pytest.mark.parametrize("by", ["address", "serial"])
def test_reconnects_after_camera_restart(fake_camera, by):
    where = {"address": "127.0.0.1"} if by == "address" else {"device_id": fake_camera.serial}
    cam = AravisCamera(**where, width=160, height=120, frame_rate_hz=40.0, backoff_s=(0.1, 0.5))
    with cam:
        before = _collect(cam, 15)
        fake_camera.kill()
        t_kill = time.monotonic()
        polls = []
        while time.monotonic() - t_kill < 2.0:
            t0 = time.monotonic()
            assert cam.poll(0.2) is None
            polls.append(time.monotonic() - t0)
        # poll(0.2) stays bounded while the camera is away (one ≤ 0.1 s probe per reopen, not a full
        # Aravis open); the bound, 10× that, catches a poll that blocks, not a slow machine
        assert max(polls) < 3.0
        st = cam.stats()
        assert st["state"] == "reconnecting" and st["disconnects"] == 1
        fake_camera.start()
        after = _collect(cam, 20)                    # backoff ≤ 0.5 s, then frames again
        st = cam.stats()
    assert st["reconnects"] == 1 and st["state"] == "streaming"
    # unwrapped ids keep increasing across the reconnect; the outage shows as a gap sized by time
    assert after[0].frame_id > before[-1].frame_id
    outage = after[0].t - before[-1].t
    assert after[0].gap_before == pytest.approx(outage * 40 - 1, abs=2)
    assert all(b.t > a.t for a, b in zip(after, after[1:], strict=False))


@pytest.mark.hardware
def test_no_reconnect_mode_raises(fake_camera):
    cam = AravisCamera("127.0.0.1", width=160, height=120, frame_rate_hz=40.0, reconnect=False,
                       stall_timeout_s=0.3)
    cam.start()
    try:
        assert _collect(cam, 1)
        fake_camera.kill()
        with pytest.raises(DeviceError, match="camera lost .*GVCP probe"):
            for _ in range(20):
                cam.poll(0.1)
    finally:
        cam.stop()


@pytest.mark.hardware
def test_incomplete_buffers_counted_and_skipped(fake_camera):
    fake_camera.kill()
    fake_camera.start("-r", "10")          # the fake camera drops 1 % of its GVSP packets
    cam = AravisCamera("127.0.0.1", width=160, height=120, frame_rate_hz=40.0)
    with cam:
        frames, end = [], time.monotonic() + 120    # only catches a stopped camera
        while len(frames) < 20 or cam.stats()["bad_buffers"] < 3:
            assert time.monotonic() < end, cam.stats()
            frames += _collect(cam, 1)
        st = cam.stats()
    assert st["bad_buffers"] >= 3 and st["bad_status"].get("missing-packets", 0) >= 3
    assert all(f.image.shape == (120, 160) for f in frames)
    # a skipped buffer is a lost frame: it shows up as a frame-id gap on the next good frame
    assert st["frames_lost"] == sum(f.gap_before for f in frames) > 0
    ids = [f.frame_id for f in frames]
    assert all(b - a == 1 + f.gap_before for a, b, f in zip(ids, ids[1:], frames[1:], strict=False))
    assert st["frames_lost"] <= st["bad_buffers"] + 3     # (+ the rare frame whose leader was lost)


@pytest.mark.hardware
def test_stop_after_silent_loss_does_not_block(fake_camera):
    # the daemon restarts a stalled source with stop() + start(): neither may hang on a dead camera
    cam = AravisCamera("127.0.0.1", width=160, height=120, frame_rate_hz=40.0)
    cam.start()
    assert _collect(cam, 1)
    fake_camera.kill()
    time.sleep(0.1)                        # loss not yet detected by the driver (no poll since)
    t0 = time.monotonic()
    cam.stop()
    with pytest.raises(DeviceError, match="no GigE Vision camera answers"):
        cam.start()
    assert time.monotonic() - t0 < 5.0     # a 0.2 s and a 0.3 s probe; the bound only catches a hang
    fake_camera.start()
    cam.start()
    try:
        assert len(_collect(cam, 10)) == 10
    finally:
        cam.stop()


@pytest.mark.hardware
def test_radiometry_is_none_without_flir_features(fake_camera):
    """The fake camera has no Planck features (R, B, F, O): `radiometry()` says None, open or closed."""
    cam = AravisCamera("127.0.0.1", width=160, height=120)
    assert cam.radiometry() is None                      # no session yet
    with cam:
        assert cam._device is not None and not cam._device.is_feature_available("R")
        assert cam.radiometry() is None
        assert cam.poll(1.0) is not None                 # reading features left the stream working
    assert cam.radiometry() is None


def _fake_xml_with_planck_features(path) -> None:
    """The fake camera's own GenICam XML plus FLIR-style Planck features: R an IntReg, B/F/O FloatRegs,
    in scratch registers the fake device does not use (RW, so the test writes the camera's values)."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    Aravis.enable_interface("Fake")
    xml = Aravis.Camera.new("Fake_1").get_device().get_genicam_xml()
    xml = xml[0] if isinstance(xml, tuple) else xml

    def reg(kind, name, address, length):
        sign = "<Sign>Signed</Sign>" if kind == "IntReg" else ""
        return (f'<{kind} Name="{name}" NameSpace="Custom"><Address>{address:#x}</Address>'
                f"<Length>{length}</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>{sign}"
                f"<Endianess>BigEndian</Endianess></{kind}>\n")

    extra = reg("IntReg", "R", 0x240, 4) + "".join(
        reg("FloatReg", name, 0x248 + 8 * i, 8) for i, name in enumerate("BFO"))
    assert xml.count("</RegisterDescription>") == 1
    path.write_text(xml.replace("</RegisterDescription>", extra + "</RegisterDescription>"))


@pytest.mark.hardware
def test_radiometry_reads_planck_features_over_gvcp(fake_camera, tmp_path):
    """With R, B, F, O in the camera's GenICam description, `radiometry()` reads them over GVCP."""
    from thermod.physics.radiometry import Planck

    xml = tmp_path / "fake-flir.xml"
    _fake_xml_with_planck_features(xml)
    fake_camera.start("-g", str(xml))
    cam = AravisCamera("127.0.0.1", width=160, height=120)
    with cam:
        dev = cam._device
        assert cam.radiometry() is None                  # registers still 0: B = 0 is no valid model
        dev.set_integer_feature_value("R", 16556)
        for name, v in (("B", 1428.0), ("F", 1.0), ("O", -88.0)):
            dev.set_float_feature_value(name, v)
        assert cam.radiometry() == Planck(R=16556.0, B=1428.0, F=1.0, O=-88.0)
        assert cam.poll(1.0) is not None
