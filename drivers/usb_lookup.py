"""Find the tty or video node of a USB device by vendor/product/serial, through sysfs.

Device numbers (ttyUSB0, video2) change when devices are replugged or enumerate in another order;
the USB identity does not. ``find_tty(0x0403, 0x6015, "DK0ABCDE")`` walks
``<sysfs_root>/bus/usb/devices/*`` (``idVendor``, ``idProduct``, ``serial``), looks under the
device's interfaces (``<dev>:<cfg>.<if>/ttyUSB0``, ``…/tty/ttyACM0``, ``…/video4linux/video0``) and
returns ``<dev_root>/<node>``. :func:`by_id_links` lists the stable udev names
(/dev/serial/by-id, /dev/v4l/by-id) pointing at a node. Both roots are injectable so tests run on
a fake tree. :func:`usb_present` asks libusb through pyusb (when a backend exists) whether such a
device is attached at all, to tell "unplugged" from "no driver bound".
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from thermod.errors import DeviceError


@dataclass
class UsbDevice:
    """One USB device found in sysfs, with the device nodes of its interfaces."""

    sysfs: Path
    vendor: int
    product: int
    serial: str | None
    manufacturer: str | None = None
    product_name: str | None = None
    ttys: list[str] = field(default_factory=list)
    videos: list[str] = field(default_factory=list)

    def describe(self) -> str:
        s = f"{self.vendor:04x}:{self.product:04x}"
        if self.serial:
            s += f" serial {self.serial}"
        if self.product_name:
            s += f" ({self.manufacturer + ' ' if self.manufacturer else ''}{self.product_name})"
        return s


def parse_usb_spec(spec: str) -> tuple[int, int, str | None]:
    """``usb:VID:PID[:SERIAL]`` (hex) → (vid, pid, serial or None)."""
    parts = spec.split(":")
    if parts[0] != "usb" or len(parts) not in (3, 4):
        raise DeviceError(f"device {spec!r}: expected usb:VID:PID[:SERIAL] with hex ids, e.g. usb:0403:6015")
    try:
        vid, pid = int(parts[1], 16), int(parts[2], 16)
    except ValueError as e:
        raise DeviceError(f"device {spec!r}: vendor/product ids must be hex, e.g. usb:0403:6015") from e
    return vid, pid, (parts[3] or None) if len(parts) == 4 else None


def _read(p: Path) -> str | None:
    try:
        return p.read_text().strip()
    except OSError:
        return None


def list_usb_devices(sysfs_root: str | os.PathLike = "/sys") -> list[UsbDevice]:
    """All USB devices with their tty and video nodes (sorted by sysfs name)."""
    base = Path(sysfs_root) / "bus" / "usb" / "devices"
    out = []
    if not base.is_dir():
        return out
    for dev in sorted(base.iterdir()):
        if ":" in dev.name:
            continue                                   # an interface, not a device
        vid, pid = _read(dev / "idVendor"), _read(dev / "idProduct")
        if vid is None or pid is None:
            continue
        try:
            d = UsbDevice(dev, int(vid, 16), int(pid, 16), _read(dev / "serial"), _read(dev / "manufacturer"),
                          _read(dev / "product"))
        except ValueError:
            continue
        for intf in sorted(dev.glob(f"{dev.name}:*")):
            for p in sorted(intf.glob("tty*")) + sorted(intf.glob("tty/tty*")):
                if p.name != "tty" and p.name not in d.ttys:
                    d.ttys.append(p.name)
            d.videos += sorted(p.name for p in intf.glob("video4linux/video*"))
        out.append(d)
    return out


def find_usb(vid: int, pid: int, serial: str | None = None, *, sysfs_root="/sys") -> list[UsbDevice]:
    """USB devices matching vendor/product (and serial, when given)."""
    return [d for d in list_usb_devices(sysfs_root)
            if d.vendor == vid and d.product == pid and (serial is None or d.serial == serial)]


def _pick(vid, pid, serial, sysfs_root, what: str) -> UsbDevice:
    found = [d for d in find_usb(vid, pid, serial, sysfs_root=sysfs_root) if getattr(d, what)]
    want = f"{vid:04x}:{pid:04x}" + (f" serial {serial}" if serial else "")
    if not found:
        others = [d.describe() for d in list_usb_devices(sysfs_root)]
        node = "tty" if what == "ttys" else "video"
        raise DeviceError(f"USB device {want}: no {node} node found in {sysfs_root}/bus/usb/devices — check "
                          f"the cable and `lsusb`; present: {', '.join(others) or 'none'}")
    if len(found) > 1:
        matches = ", ".join(d.describe() for d in found)
        raise DeviceError(f"USB device {want}: {len(found)} devices match ({matches}) — add the serial "
                          "number: usb:VID:PID:SERIAL")
    return found[0]


def find_tty(vid: int, pid: int, serial: str | None = None, *, sysfs_root="/sys", dev_root="/dev") -> str:
    """The tty device path (``/dev/ttyUSB0``) of the one matching USB device."""
    return os.path.join(dev_root, _pick(vid, pid, serial, sysfs_root, "ttys").ttys[0])


def find_video(vid: int, pid: int, serial: str | None = None, *, sysfs_root="/sys", dev_root="/dev") -> str:
    """The V4L2 node (``/dev/video0``, the first, i.e. the capture node) of the one matching USB device."""
    return os.path.join(dev_root, _pick(vid, pid, serial, sysfs_root, "videos").videos[0])


def by_id_links(node: str, *, dev_root="/dev") -> list[str]:
    """Stable udev symlinks (serial/by-id, serial/by-path, v4l/by-id, v4l/by-path) resolving to ``node``."""
    target = os.path.realpath(node)
    out = []
    for sub in ("serial/by-id", "serial/by-path", "v4l/by-id", "v4l/by-path"):
        d = Path(dev_root) / sub
        if d.is_dir():
            out += [str(p) for p in sorted(d.iterdir()) if os.path.realpath(p) == target]
    return out


def usb_present(vid: int, pid: int, serial: str | None = None) -> bool | None:
    """Whether libusb sees such a device (None when pyusb has no usable backend)."""
    try:
        import usb.core
        import usb.util
        devs = list(usb.core.find(find_all=True, idVendor=vid, idProduct=pid))
    except Exception:  # noqa: BLE001 - no backend (libusb missing) or no permission: unknown, not absent
        return None
    if serial is None:
        return bool(devs)
    for d in devs:
        try:
            if usb.util.get_string(d, d.iSerialNumber) == serial:
                return True
        except Exception:  # noqa: BLE001 - reading strings needs permissions; skip that device
            continue
    return False
