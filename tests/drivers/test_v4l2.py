"""V4L2 camera driver through its capture seam, against the Y16 V4L2 device emulator (flat uint8 byte
frames like OpenCV's V4L2 backend, Boson-style telemetry rows, buffer timestamps, unplug/replug)."""

import os
import time

import cv2
import numpy as np
import pytest

from tests.support.camera_polling import poll_frames
from thermod.drivers.v4l2_camera import V4L2Camera, fourcc_code, fourcc_str, resolve_device
from thermod.errors import DeviceError
from thermod.sim.emu_camera import EmuV4L2Device

H, W = 512, 640


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    base = rng.integers(20000, 30000, size=(H, W), dtype=np.uint16)
    return np.stack([base + 100 * i for i in range(5)]).astype(np.uint16)


def test_fourcc_codes():
    assert fourcc_code("Y16 ") == cv2.VideoWriter_fourcc(*"Y16 ")
    assert fourcc_str(fourcc_code("Y16 ")) == "Y16 "


@pytest.mark.parametrize("layout", ["flat", "rows", "u16"])
def test_boson_telemetry_stripped_and_bytes_reshaped(scene, layout):
    dev = EmuV4L2Device(scene, width=W, height=H, telemetry_rows=(2, 0), layout=layout, fps_modes=(60.0,),
                        n_buffers=16)
    cam = V4L2Camera("/dev/video0", width=W, height=H, frame_rate_hz=60.0, telemetry_rows=(2, 0),
                     capture_factory=dev.open)
    with cam:
        frames = poll_frames(cam, 12)
        st = cam.stats()
    for f in frames:
        assert f.image.dtype == np.uint16 and f.image.shape == (H, W)
        # telemetry (0xFFFF rows) gone; frame ids count lost frames, so they index the emulated stream
        np.testing.assert_array_equal(f.image, scene[f.frame_id % len(scene)])
    assert st["flat_frames"] == (0 if layout == "u16" else 12)
    assert frames[0].frame_id == 0 and st["frames_lost"] == sum(f.gap_before for f in frames)
    assert st["frames_lost"] == dev.captures[-1].timeline.lost_overrun
    assert st["timestamp_clock"] == "monotonic"
    lag = np.array([f.arrival - f.t for f in frames])
    # stamped at the end of readout (1 ms emulated transport before arrival), never at the read; the
    # read itself may come late on a loaded machine, the stamp does not move with it
    assert np.all(lag >= 0.001 - 1e-6) and np.min(lag) < 0.004
    dt = np.diff([f.t for f in frames]) / np.diff([f.frame_id for f in frames])
    np.testing.assert_allclose(dt, 1 / 60, atol=1e-6)                  # device timestamps, not reads


def test_bottom_telemetry_and_wrong_row_config(scene):
    dev = EmuV4L2Device(scene, telemetry_rows=(0, 2), fps_modes=(30.0,))
    with V4L2Camera("/dev/video0", telemetry_rows=(0, 2), capture_factory=dev.open) as cam:
        np.testing.assert_array_equal(poll_frames(cam, 1)[0].image, scene[0])
    with pytest.raises(DeviceError, match=r"frame size 640×512 .*not accepted, device delivers 640×514"):
        V4L2Camera("/dev/video0", capture_factory=dev.open).start()


def test_emulator_order_semantics_need_fourcc_before_convert_rgb(scene):
    dev = EmuV4L2Device(scene, fps_modes=(30.0,))
    cap = dev.open("/dev/video0", cv2.CAP_V4L2)
    cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)                 # wrong order: the format change turns it back on
    cap.set(cv2.CAP_PROP_FOURCC, fourcc_code("Y16 "))
    ok, img = cap.read()
    assert ok and img.shape == (H, W, 3) and img.dtype == np.uint8
    # the driver sees such frames for what they are instead of reshaping garbage
    from thermod.drivers.camera_base import as_uint16_image

    with pytest.raises(DeviceError, match="8-bit colour"):
        as_uint16_image(img, H, W, "v4l2:/dev/video0")
    cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
    ok, img = cap.read()
    assert img.shape == (1, 2 * H * W) and img.dtype == np.uint8


def test_open_by_id_symlink(tmp_path, scene):
    node = tmp_path / "video7"
    node.touch()
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    link = by_id / "usb-FLIR_Boson_12345-video-index0"
    link.symlink_to(node)
    assert resolve_device(link) == os.path.realpath(node)
    with pytest.raises(DeviceError, match="/dev/video99: no such device"):
        resolve_device(99)
    dev = EmuV4L2Device(scene, path=os.path.realpath(node), fps_modes=(30.0,))
    with V4L2Camera(link, capture_factory=dev.open) as cam:
        assert poll_frames(cam, 1)
        assert cam.stats()["device"] == os.path.realpath(node)
    with pytest.raises(DeviceError, match=r"no such device.*has \['usb-FLIR_Boson_12345-video-index0'\]"):
        resolve_device(by_id / "usb-other")


def test_real_opencv_seam_reports_unopenable_device(tmp_path):
    node = tmp_path / "video9"
    node.touch()                                          # exists, but is no V4L2 device
    with pytest.raises(DeviceError, match=r"cannot open .*video9"):
        V4L2Camera(node).start()


def test_bad_settings_raise_device_errors(scene):
    dev = EmuV4L2Device(scene, fps_modes=(30.0, 60.0))
    with pytest.raises(DeviceError, match="frame rate 45.0 Hz not accepted"):
        V4L2Camera("/dev/video0", frame_rate_hz=45.0, capture_factory=dev.open).start()
    with pytest.raises(DeviceError, match="cannot open /dev/video5"):
        V4L2Camera("/dev/video5", capture_factory=dev.open).start()
    with pytest.raises(DeviceError, match="telemetry_rows"):
        V4L2Camera("/dev/video0", telemetry_rows=(-1, 0))


def test_dropped_and_overrun_frames_counted_from_timestamps(scene):
    dev = EmuV4L2Device(scene, fps_modes=(60.0,), drop=[3], n_buffers=4)
    with V4L2Camera("/dev/video0", frame_rate_hz=60.0, capture_factory=dev.open) as cam:
        first = poll_frames(cam, 5)
        overrun_first = dev.captures[-1].timeline.lost_overrun
        time.sleep(0.25)                               # a stalled reader: ~15 frames, 4 buffers
        late = poll_frames(cam, 8)
        st = cam.stats()
    if overrun_first == 0:                             # (unless a loaded machine stalled the reader)
        assert [f.gap_before for f in first] == [0, 0, 0, 1, 0]
    cap = dev.captures[-1]
    assert cap.timeline.lost_transport == 1 and cap.timeline.lost_overrun >= 8
    assert st["frames_lost"] == sum(f.gap_before for f in first + late) == 1 + cap.timeline.lost_overrun
    ids = [f.frame_id for f in first + late]
    assert all(b - a == 1 + f.gap_before for a, b, f in zip(ids, ids[1:], (first + late)[1:], strict=False))


def test_device_clock_timestamps_are_mapped(scene):
    # a UVC-style hardware clock: unrelated offset and 300 ppm drift
    dev = EmuV4L2Device(scene, fps_modes=(60.0,), clock_offset_s=5000.0, drift_ppm=300.0)
    with V4L2Camera("/dev/video0", frame_rate_hz=60.0, capture_factory=dev.open) as cam:
        frames = poll_frames(cam, 60)
        st = cam.stats()
    assert st["timestamp_clock"] == "device"
    tl = dev.captures[-1].timeline
    err = np.array([f.t - tl.completes(f.frame_id) for f in frames[20:]])
    assert np.all(np.abs(err) < 0.003)                 # within the transport latency + jitter


def test_unplug_replug_reopens(scene):
    dev = EmuV4L2Device(scene, fps_modes=(60.0,))
    cam = V4L2Camera("/dev/video0", frame_rate_hz=60.0, capture_factory=dev.open, read_timeout_s=0.1,
                     backoff_s=(0.05, 0.2))
    with cam:
        before = poll_frames(cam, 3)
        dev.unplug()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:
            assert cam.poll(0.1) is None
        assert cam.stats()["state"] == "reopening" and cam.stats()["read_errors"] == 1
        dev.replug()
        after, deadline = [], time.monotonic() + 30     # reopen after ≤ 0.2 s backoff; 30 s: a hang
        while len(after) < 3:
            assert time.monotonic() < deadline, cam.stats()
            if (f := cam.poll(0.5)) is not None:
                after.append(f)
        st = cam.stats()
    assert st["reopens"] == 1 and st["state"] == "streaming"
    assert after[0].frame_id > before[-1].frame_id and after[0].gap_before >= 20   # ≥ 0.5 s at 60 Hz


def test_no_reopen_raises(scene):
    dev = EmuV4L2Device(scene, fps_modes=(60.0,))
    with V4L2Camera("/dev/video0", capture_factory=dev.open, reopen=False) as cam:
        poll_frames(cam, 1)
        dev.unplug()
        with pytest.raises(DeviceError, match="read failed"):
            cam.poll(0.5)
