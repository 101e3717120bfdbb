"""``dffd devices``: discovery through a fake pyusb finder and a fake sysfs tree."""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import pytest
import usb.core

from dffd.cli.arguments import configure_devices
from drivers import usb as devices
from drivers.usb import UsbDevice, discover, discover_sysfs, report, udev_rule


class FakeInterface:
    def __init__(self, cls: int) -> None:
        self.bInterfaceClass = cls


class FakeDevice:
    """What pyusb's Device offers that the discovery reads."""

    def __init__(
        self,
        vid: int,
        pid: int,
        bus: int,
        ports: tuple[int, ...],
        interfaces: tuple[int, ...] = (0xFF,),
        device_class: int = 0,
    ) -> None:
        self.idVendor = vid
        self.idProduct = pid
        self.bus = bus
        self.port_numbers = ports
        self.bDeviceClass = device_class
        self._interfaces = interfaces

    def __iter__(self):
        return iter([[FakeInterface(c) for c in self._interfaces]])

    @property
    def serial_number(self) -> str:
        raise ValueError("The device has no langid (permission denied)")

    @property
    def product(self) -> str:
        raise usb.core.USBError("Access denied")


def _write(directory: Path, **files: str) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (directory / name).write_text(text + "\n")


@pytest.fixture
def sysfs(tmp_path: Path) -> Path:
    root = tmp_path / "devices"
    # FTDI cable with a serial number on bus 1 port 1.4 → ttyUSB0
    _write(
        root / "1-1.4",
        idVendor="0403",
        idProduct="6001",
        serial="A1B2C3",
        product="FT232R USB UART",
        busnum="1",
    )
    _write(root / "1-1.4:1.0", bInterfaceClass="ff")
    (root / "1-1.4:1.0" / "ttyUSB0").mkdir()
    # CH340 adapter without a serial number on bus 1 port 2 → ttyUSB1
    _write(root / "1-2", idVendor="1a86", idProduct="7523", product="USB Serial", busnum="1")
    _write(root / "1-2:1.0", bInterfaceClass="ff")
    (root / "1-2:1.0" / "ttyUSB1").mkdir()
    # UVC grabber on bus 2 port 1 → video0, video1
    _write(
        root / "2-1",
        idVendor="534d",
        idProduct="2109",
        product="USB Video",
        manufacturer="MACROSILICON",
        serial="GRAB01",
        busnum="2",
    )
    _write(root / "2-1:1.0", bInterfaceClass="0e")
    (root / "2-1:1.0" / "video4linux" / "video0").mkdir(parents=True)
    (root / "2-1:1.0" / "video4linux" / "video1").mkdir(parents=True)
    # a keyboard: neither
    _write(root / "1-3", idVendor="046d", idProduct="c31c", busnum="1")
    _write(root / "1-3:1.0", bInterfaceClass="03")
    return root


FAKES = [
    FakeDevice(0x0403, 0x6001, 1, (1, 4)),
    FakeDevice(0x1A86, 0x7523, 1, (2,)),
    FakeDevice(0x534D, 0x2109, 2, (1,), interfaces=(0x0E, 0x0E, 0x01), device_class=0xEF),
    FakeDevice(0x046D, 0xC31C, 1, (3,), interfaces=(0x03,)),
    FakeDevice(0x1D6B, 0x0002, 1, (), device_class=0x09),  # root hub
]


def _no_backend() -> list[object]:
    raise usb.core.NoBackendError("No backend available")


def test_discovery_maps_devices_to_nodes_and_serial_numbers(sysfs: Path) -> None:
    found = discover(lambda: FAKES, sysfs)
    assert [(d.kind, d.vid_pid, d.port_path, d.nodes) for d in found] == [
        ("serial", "0403:6001", "1-1.4", ("/dev/ttyUSB0",)),
        ("serial", "1a86:7523", "1-2", ("/dev/ttyUSB1",)),
        ("video", "534d:2109", "2-1", ("/dev/video0", "/dev/video1")),
    ]
    ftdi, ch340, grabber = found
    assert ftdi.serial_number == "A1B2C3"
    assert ftdi.vendor == "FTDI"
    assert ftdi.product == "FT232R USB UART"
    assert ch340.serial_number is None  # sysfs has none, and libusb may not read descriptors
    assert grabber.bus == 2


def test_report_lists_devices_and_prints_rules(sysfs: Path) -> None:
    out, err = io.StringIO(), io.StringIO()
    assert report(out, err, finder=lambda: FAKES, sysfs_root=sysfs) == 0
    text = out.getvalue()
    assert "USB serial bridges:" in text
    assert "USB video devices:" in text
    assert "-> /dev/ttyUSB0" in text
    assert "-> /dev/video0, /dev/video1" in text
    assert 'ATTRS{serial}=="A1B2C3", SYMLINK+="visca0"' in text
    assert 'KERNELS=="1-2", SYMLINK+="visca1"' in text
    assert "pinned to the USB port" in text
    assert err.getvalue() == ""


def test_none_found_is_said_clearly_with_a_template_rule(tmp_path: Path) -> None:
    out, err = io.StringIO(), io.StringIO()
    keyboard_only = [FakeDevice(0x046D, 0xC31C, 1, (3,), interfaces=(0x03,))]
    assert report(out, err, finder=lambda: keyboard_only, sysfs_root=tmp_path) == 0
    text = out.getvalue()
    assert text.startswith("No USB serial bridges")
    assert "template" in text
    assert 'ATTRS{idVendor}=="VVVV"' in text


def test_missing_libusb_is_a_message_not_a_traceback(tmp_path: Path) -> None:
    out, err = io.StringIO(), io.StringIO()
    code = report(out, err, finder=_no_backend, sysfs_root=tmp_path / "absent")
    assert code == 1
    assert "libusb is not available" in err.getvalue()
    assert "apt install libusb-1.0-0" in err.getvalue()
    assert "Traceback" not in err.getvalue() + out.getvalue()


def test_missing_libusb_falls_back_to_sysfs(sysfs: Path) -> None:
    out, err = io.StringIO(), io.StringIO()
    assert report(out, err, finder=_no_backend, sysfs_root=sysfs) == 0
    assert "Listing from" in err.getvalue()
    assert "0403:6001" in out.getvalue()
    assert [d.vid_pid for d in discover_sysfs(sysfs)] == ["0403:6001", "1a86:7523", "534d:2109"]


def test_udev_rule_text() -> None:
    device = UsbDevice(
        "serial", 0x0403, 0x6001, "FTDI", None, "A1B2C3", 1, "1-1.4", ("/dev/ttyUSB0",)
    )
    assert udev_rule(device, "visca0", "dialout") == (
        'SUBSYSTEM=="tty", ATTRS{idVendor}=="0403", ATTRS{idProduct}=="6001", '
        'ATTRS{serial}=="A1B2C3", SYMLINK+="visca0", GROUP="dialout", MODE="0660"'
    )
    no_serial = UsbDevice("serial", 0x067B, 0x2303, "Prolific", None, None, 3, "3-1.2", ())
    assert 'KERNELS=="3-1.2"' in udev_rule(no_serial, "cam", "uucp")
    assert 'GROUP="uucp"' in udev_rule(no_serial, "cam", "uucp")


def test_subcommand_parser_defaults() -> None:
    parser = argparse.ArgumentParser()
    configure_devices(parser)
    args = parser.parse_args(["--name", "visca1"])
    assert args.name == "visca1"
    assert args.group == "dialout"
    assert args.sysfs_root == devices.SYSFS_USB
