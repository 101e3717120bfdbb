"""``dffd devices``: find the camera's USB serial bridge and video grabber, print a udev rule.

Devices are enumerated with pyusb (libusb); each is matched to its Linux device node through
``/sys/bus/usb/devices`` (``<bus>-<port path>:<config>.<interface>/ttyUSB0``, ``…/tty/ttyACM0``,
``…/video4linux/video0``). Serial numbers are read from sysfs, which needs no permission on the
device; libusb is only asked when sysfs has none.

Without libusb (``usb.core.NoBackendError``) the command says how to install it and lists what
sysfs alone shows.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TextIO

import usb.core

EXIT_OK = 0
EXIT_FAILURE = 1

SYSFS_USB = Path("/sys/bus/usb/devices")
DEFAULT_LINK_NAME = "visca0"
DEFAULT_GROUP = "dialout"
RULES_FILE = "/etc/udev/rules.d/99-dffd-visca.rules"

# USB-to-RS-232 bridge vendors seen on VISCA cables and adapters.
SERIAL_BRIDGE_VENDORS: dict[int, str] = {
    0x0403: "FTDI",
    0x067B: "Prolific (PL2303)",
    0x1A86: "WCH (CH340/CH341)",
    0x10C4: "Silicon Labs (CP210x)",
    0x0557: "ATEN",
    0x04E2: "Exar",
}
USB_CLASS_CDC = 0x02  # communications (CDC-ACM serial ports)
USB_CLASS_VIDEO = 0x0E  # USB video class (UVC grabbers and webcams)

Finder = Callable[[], Iterable[Any]]


class LibusbMissingError(RuntimeError):
    """pyusb found no libusb backend."""


@dataclass(frozen=True, slots=True)
class UsbDevice:
    """One serial bridge or video device and the nodes it provides."""

    kind: Literal["serial", "video"]
    vendor_id: int
    product_id: int
    vendor: str
    product: str | None
    serial_number: str | None
    bus: int | None
    port_path: str | None  # sysfs name, e.g. "1-1.4"
    nodes: tuple[str, ...]  # /dev/ttyUSB0, /dev/video0, …

    @property
    def vid_pid(self) -> str:
        """``vvvv:pppp`` in hex, as lsusb prints it."""
        return f"{self.vendor_id:04x}:{self.product_id:04x}"


def discover(finder: Finder | None = None, sysfs_root: Path = SYSFS_USB) -> list[UsbDevice]:
    """Serial bridges and video devices seen by libusb (raises :class:`LibusbMissingError`)."""
    find = finder or _pyusb_find
    try:
        devices = list(find())
    except usb.core.NoBackendError as exc:
        raise LibusbMissingError(str(exc)) from exc
    found = []
    for dev in devices:
        port_path = _port_path(dev)
        sysfs = sysfs_root / port_path if port_path else None
        classes = _interface_classes(dev)
        if sysfs is not None and sysfs.is_dir():
            classes |= _sysfs_interface_classes(sysfs_root, port_path or "")
        kind = _classify(int(dev.idVendor), classes)
        if kind is None:
            continue
        found.append(
            UsbDevice(
                kind=kind,
                vendor_id=int(dev.idVendor),
                product_id=int(dev.idProduct),
                vendor=SERIAL_BRIDGE_VENDORS.get(
                    int(dev.idVendor), _read(sysfs, "manufacturer") or ""
                ),
                product=_read(sysfs, "product") or _descriptor(dev, "product"),
                serial_number=_read(sysfs, "serial") or _descriptor(dev, "serial_number"),
                bus=None if dev.bus is None else int(dev.bus),
                port_path=port_path,
                nodes=_nodes(sysfs_root, port_path) if port_path else (),
            )
        )
    return sorted(found, key=lambda d: (d.kind, d.port_path or "", d.vid_pid))


def discover_sysfs(sysfs_root: Path = SYSFS_USB) -> list[UsbDevice]:
    """The same listing from sysfs alone (no libusb needed; Linux only)."""
    found: list[UsbDevice] = []
    if not sysfs_root.is_dir():
        return found
    for entry in sorted(sysfs_root.iterdir()):
        if ":" in entry.name or not (entry / "idVendor").exists():
            continue
        try:
            vid = int(_read(entry, "idVendor") or "", 16)
            pid = int(_read(entry, "idProduct") or "", 16)
        except ValueError:
            continue
        kind = _classify(vid, _sysfs_interface_classes(sysfs_root, entry.name))
        if kind is None:
            continue
        bus = _read(entry, "busnum")
        found.append(
            UsbDevice(
                kind=kind,
                vendor_id=vid,
                product_id=pid,
                vendor=SERIAL_BRIDGE_VENDORS.get(vid, _read(entry, "manufacturer") or ""),
                product=_read(entry, "product"),
                serial_number=_read(entry, "serial"),
                bus=int(bus) if bus and bus.isdigit() else None,
                port_path=entry.name,
                nodes=_nodes(sysfs_root, entry.name),
            )
        )
    return sorted(found, key=lambda d: (d.kind, d.port_path or "", d.vid_pid))


def udev_rule(
    device: UsbDevice | None, name: str = DEFAULT_LINK_NAME, group: str = DEFAULT_GROUP
) -> str:
    """A udev rule giving the bridge's tty a stable ``/dev/<name>`` owned by ``group``.

    Matches the serial number when the bridge has one, else the physical USB port; with no
    device, a template with placeholders.
    """
    tail = f'SYMLINK+="{name}", GROUP="{group}", MODE="0660"'
    if device is None:
        return (
            'SUBSYSTEM=="tty", ATTRS{idVendor}=="VVVV", ATTRS{idProduct}=="PPPP", '
            f'ATTRS{{serial}}=="SERIAL", {tail}'
        )
    match = (
        f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="{device.vendor_id:04x}", '
        f'ATTRS{{idProduct}}=="{device.product_id:04x}", '
    )
    if device.serial_number:
        match += f'ATTRS{{serial}}=="{device.serial_number}", '
    elif device.port_path:
        match += f'KERNELS=="{device.port_path}", '
    return match + tail


def report(
    out: TextIO,
    err: TextIO,
    *,
    finder: Finder | None = None,
    sysfs_root: Path = SYSFS_USB,
    name: str = DEFAULT_LINK_NAME,
    group: str = DEFAULT_GROUP,
) -> int:
    """Print the listing and the udev rule; return the exit code."""
    try:
        devices = discover(finder, sysfs_root)
    except LibusbMissingError:
        err.write(
            "dffd devices: libusb is not available to pyusb (usb.core.NoBackendError).\n"
            "  Install it: sudo apt install libusb-1.0-0   (Fedora: sudo dnf install libusbx)\n"
        )
        if not sysfs_root.is_dir():
            err.write(f"  {sysfs_root} is not readable either; nothing can be listed.\n")
            return EXIT_FAILURE
        err.write(f"  Listing from {sysfs_root} instead.\n")
        devices = discover_sysfs(sysfs_root)
    serial = [d for d in devices if d.kind == "serial"]
    video = [d for d in devices if d.kind == "video"]
    if not devices:
        out.write(
            "No USB serial bridges (FTDI, Prolific, CH340, CP210x, …) and no USB video "
            "devices found.\n"
            "Check the cable and power; a camera on a built-in RS-232 port "
            "(/dev/ttyS*) is not a USB device.\n"
        )
    for title, group_devices in (("USB serial bridges", serial), ("USB video devices", video)):
        if not group_devices:
            continue
        out.write(f"{title}:\n")
        for d in group_devices:
            out.write(f"  {_describe(d)}\n")
    out.write(
        f"\nudev rule for the camera's serial port (save as {RULES_FILE}, then run\n"
        "  sudo udevadm control --reload-rules && sudo udevadm trigger):\n"
    )
    if not serial:
        out.write("  # template: fill in from `udevadm info -a -n /dev/ttyUSB0`\n")
        out.write(f"{udev_rule(None, name, group)}\n")
    if len(serial) > 1:
        out.write(
            "# several bridges: keep only the camera's rule (unplug the camera's cable and "
            "run again to see which one goes)\n"
        )
    for i, d in enumerate(serial):
        link = name if len(serial) == 1 else f"{name.rstrip('0123456789')}{i}"
        note = "" if d.serial_number else "  # no serial number: pinned to the USB port"
        out.write(f"# {_describe(d)}{note}\n{udev_rule(d, link, group)}\n")
    return EXIT_OK


def run(args: argparse.Namespace) -> int:
    """Run ``dffd devices``."""
    return report(
        sys.stdout, sys.stderr, sysfs_root=args.sysfs_root, name=args.name, group=args.group
    )


# -- private helpers ------------------------------------------------------------------------


def _pyusb_find() -> Iterable[Any]:
    return usb.core.find(find_all=True) or ()


def _port_path(dev: Any) -> str | None:
    ports = getattr(dev, "port_numbers", None)
    if dev.bus is None or not ports:
        return None
    return f"{int(dev.bus)}-{'.'.join(str(p) for p in ports)}"


def _interface_classes(dev: Any) -> set[int]:
    classes = {int(getattr(dev, "bDeviceClass", 0))}
    try:
        for config in dev:
            for interface in config:
                classes.add(int(interface.bInterfaceClass))
    except (usb.core.USBError, ValueError, NotImplementedError, TypeError):
        pass  # descriptors unreadable: sysfs or the vendor id still classify it
    return classes


def _sysfs_interface_classes(sysfs_root: Path, port_path: str) -> set[int]:
    classes = set()
    for interface in sysfs_root.glob(f"{port_path}:*"):
        value = _read(interface, "bInterfaceClass")
        if value:
            try:
                classes.add(int(value, 16))
            except ValueError:
                continue
    return classes


def _classify(vendor_id: int, classes: set[int]) -> Literal["serial", "video"] | None:
    if USB_CLASS_VIDEO in classes:
        return "video"
    if vendor_id in SERIAL_BRIDGE_VENDORS or USB_CLASS_CDC in classes:
        return "serial"
    return None


def _nodes(sysfs_root: Path, port_path: str) -> tuple[str, ...]:
    nodes: list[str] = []
    for interface in sorted(sysfs_root.glob(f"{port_path}:*")):
        for pattern in ("tty*", "tty/tty*", "video4linux/video*"):
            nodes += [f"/dev/{p.name}" for p in sorted(interface.glob(pattern)) if p.name != "tty"]
    return tuple(dict.fromkeys(nodes))


def _read(directory: Path | None, name: str) -> str | None:
    if directory is None:
        return None
    try:
        text = (directory / name).read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return None
    return text or None


def _descriptor(dev: Any, attribute: str) -> str | None:
    try:
        value = getattr(dev, attribute)
    except (usb.core.USBError, ValueError, NotImplementedError):
        return None  # reading string descriptors needs access to the device
    return str(value) if value else None


def _describe(d: UsbDevice) -> str:
    parts = [d.vid_pid, d.vendor or "?"]
    if d.product:
        parts.append(f"'{d.product}'")
    parts.append(f"serial {d.serial_number}" if d.serial_number else "no serial number")
    if d.port_path:
        parts.append(f"bus {d.bus} port {d.port_path}")
    parts.append("-> " + (", ".join(d.nodes) if d.nodes else "no device node (driver not bound?)"))
    return "  ".join(parts)
