"""USB lookup on a fake sysfs/dev tree shaped like the kernel's (FTDI tty, CDC-ACM tty, UVC camera)."""

import os

import pytest

from thermod.drivers.usb_lookup import (
    by_id_links,
    find_tty,
    find_usb,
    find_video,
    list_usb_devices,
    parse_usb_spec,
)
from thermod.errors import DeviceError


def usb_dev(sysfs, name, vid, pid, serial=None, product=None, nodes=()):
    d = sysfs / "bus/usb/devices" / name
    d.mkdir(parents=True)
    (d / "idVendor").write_text(f"{vid:04x}\n")
    (d / "idProduct").write_text(f"{pid:04x}\n")
    if serial:
        (d / "serial").write_text(serial + "\n")
    if product:
        (d / "product").write_text(product + "\n")
    for rel in nodes:
        (d / rel).mkdir(parents=True)
    return d


@pytest.fixture
def tree(tmp_path):
    sysfs, dev = tmp_path / "sys", tmp_path / "dev"
    usb_dev(sysfs, "usb1", 0x1D6B, 0x0002, product="EHCI Host Controller")          # root hub: no nodes
    usb_dev(sysfs, "1-1", 0x0403, 0x6015, "DK0ABCDE", "FT231X USB UART", ["1-1:1.0/ttyUSB1"])
    usb_dev(sysfs, "1-2", 0x0403, 0x6015, "DK0ZZZZZ", "FT231X USB UART", ["1-2:1.0/ttyUSB0"])
    usb_dev(sysfs, "1-3", 0x2E8A, 0x000A, "E6614", "Pico", ["1-3:1.0/tty/ttyACM0", "1-3:1.1"])
    usb_dev(sysfs, "1-4", 0x09CB, 0x4007, "BOSON123", "Boson",
            ["1-4:1.0/video4linux/video2", "1-4:1.0/video4linux/video3", "1-4:1.2/ttyACM1"])
    (sysfs / "bus/usb/devices/1-4:1.0").mkdir()          # interface entries at top level are skipped
    (dev / "serial/by-id").mkdir(parents=True)
    (dev / "v4l/by-id").mkdir(parents=True)
    for n in ("ttyUSB0", "ttyUSB1", "ttyACM0", "ttyACM1", "video2", "video3"):
        (dev / n).touch()
    os.symlink("../../ttyUSB1", dev / "serial/by-id/usb-FTDI_FT231X_USB_UART_DK0ABCDE-if00-port0")
    os.symlink("../../video2", dev / "v4l/by-id/usb-FLIR_Boson_BOSON123-video-index0")
    return sysfs, dev


def test_lists_devices_with_their_nodes(tree):
    sysfs, _ = tree
    devs = {d.sysfs.name: d for d in list_usb_devices(sysfs)}
    assert sorted(devs) == ["1-1", "1-2", "1-3", "1-4", "usb1"]
    assert devs["1-1"].ttys == ["ttyUSB1"] and devs["1-3"].ttys == ["ttyACM0"]
    assert devs["1-4"].videos == ["video2", "video3"] and devs["1-4"].ttys == ["ttyACM1"]
    assert devs["usb1"].ttys == [] and devs["1-1"].describe() == "0403:6015 serial DK0ABCDE (FT231X USB UART)"
    assert list_usb_devices(sysfs / "nowhere") == []


def test_find_by_vid_pid_serial(tree):
    sysfs, dev = tree
    kw = dict(sysfs_root=sysfs, dev_root=str(dev))
    assert find_tty(0x0403, 0x6015, "DK0ZZZZZ", **kw) == str(dev / "ttyUSB0")   # not the enumeration order
    assert find_tty(0x0403, 0x6015, "DK0ABCDE", **kw) == str(dev / "ttyUSB1")
    assert find_tty(0x2E8A, 0x000A, **kw) == str(dev / "ttyACM0")
    assert find_video(0x09CB, 0x4007, **kw) == str(dev / "video2")
    assert len(find_usb(0x0403, 0x6015, sysfs_root=sysfs)) == 2


def test_ambiguous_and_missing_devices_explain_themselves(tree):
    sysfs, dev = tree
    with pytest.raises(DeviceError, match=r"0403:6015: 2 devices match .*DK0ABCDE.*DK0ZZZZZ.*VID:PID:SERIAL"):
        find_tty(0x0403, 0x6015, sysfs_root=sysfs, dev_root=str(dev))
    with pytest.raises(DeviceError, match=r"0403:6001: no tty node .*present: .*0403:6015 serial DK0ABCDE"):
        find_tty(0x0403, 0x6001, sysfs_root=sysfs, dev_root=str(dev))
    with pytest.raises(DeviceError, match="no video node"):
        find_video(0x0403, 0x6015, "DK0ABCDE", sysfs_root=sysfs, dev_root=str(dev))


def test_by_id_links_survive_renumbering(tree):
    sysfs, dev = tree
    assert by_id_links(str(dev / "ttyUSB1"), dev_root=str(dev)) == \
        [str(dev / "serial/by-id/usb-FTDI_FT231X_USB_UART_DK0ABCDE-if00-port0")]
    assert by_id_links(str(dev / "video2"), dev_root=str(dev)) == \
        [str(dev / "v4l/by-id/usb-FLIR_Boson_BOSON123-video-index0")]
    assert by_id_links(str(dev / "ttyUSB0"), dev_root=str(dev)) == []
    # replug: the adapter comes back as ttyUSB3, udev re-points the same by-id name
    link = dev / "serial/by-id/usb-FTDI_FT231X_USB_UART_DK0ABCDE-if00-port0"
    (dev / "ttyUSB3").touch()
    link.unlink()
    os.symlink("../../ttyUSB3", link)
    assert by_id_links(str(dev / "ttyUSB3"), dev_root=str(dev)) == [str(link)]


def test_parse_usb_spec():
    assert parse_usb_spec("usb:0403:6015") == (0x0403, 0x6015, None)
    assert parse_usb_spec("usb:0403:6015:DK0ABCDE") == (0x0403, 0x6015, "DK0ABCDE")
    with pytest.raises(DeviceError, match="hex"):
        parse_usb_spec("usb:ftdi:6015")
    with pytest.raises(DeviceError, match="expected usb:VID:PID"):
        parse_usb_spec("usb:0403")
