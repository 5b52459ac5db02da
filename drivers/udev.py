"""udev rules and device discovery for the hardware backends.

``rules()`` writes udev rules from the backends' vendor and product IDs, so a
user in the seat (``TAG+="uaccess"``) or in the ``plugdev`` group may open the
devices without root. ``discover()`` reports, per backend, the devices it finds
or why it cannot look (a missing package, libusb not loadable, no SDK).
"""

from __future__ import annotations

import importlib
from importlib import resources
from pathlib import Path
from typing import Any

from hapticd_drivers import models
from hapticd_drivers.base import DeviceError

FORCE_DIMENSION_VID = 0x1451  # their devices speak their own protocol: the dhd backend


def usb_ids() -> list[tuple[int, int | None, str]]:
    """(vendor, product or None for all, what) of every device a backend can drive."""
    import yaml

    out: list[tuple[int, int | None, str]] = []
    for path in sorted(Path(str(resources.files("hapticd_drivers") / "devices")).glob("*.yaml")):
        usb = (yaml.safe_load(path.read_text()) or {}).get("usb")
        if usb:
            out.append(
                (int(usb["vendor_id"]), int(usb["product_id"]), f"{path.stem} (usb, hid backends)")
            )
    out.append((FORCE_DIMENSION_VID, None, "Force Dimension devices (dhd backend, via their SDK)"))
    # Models driven without their vendor's SDK, by the IDs their row of the model table
    # gives (the Falcon's FTDI chip: falcon backend).
    out += [(v, p, f"{m.name} (falcon backend)") for m in models.MODELS for v, p in m.usb_ids]
    return out


def rules() -> str:
    """udev rules text for every device in ``usb_ids()``."""
    lines = [
        "# hapticd: let the user at the seat (or the plugdev group) open haptic devices.",
        "# Install: hapticd udev-rules | sudo tee /etc/udev/rules.d/70-hapticd.rules",
        "#          sudo udevadm control --reload && sudo udevadm trigger",
    ]
    for vid, pid, what in usb_ids():
        match = f'ATTRS{{idVendor}}=="{vid:04x}"'
        if pid is not None:
            match += f', ATTRS{{idProduct}}=="{pid:04x}"'
        lines.append(f"# {what}")
        lines.append(f'SUBSYSTEM=="usb", {match}, MODE="0660", GROUP="plugdev", TAG+="uaccess"')
        lines.append(f'KERNEL=="hidraw*", {match}, MODE="0660", GROUP="plugdev", TAG+="uaccess"')
    return "\n".join(lines) + "\n"


def discover_hid() -> list[dict[str, Any]]:
    """hid devices per model (serial numbers), or why cython-hidapi cannot look."""
    try:
        hid = importlib.import_module("hid")
    except ImportError:
        return [
            {
                "backend": "hid",
                "problem": "cython-hidapi is not installed: pip install 'hapticd[hid]'",
            }
        ]
    return [
        {
            "backend": "hid",
            "model": what,
            "found": [d.get("serial_number") for d in hid.enumerate(vid, pid)],
        }
        for vid, pid, what in _ids()
    ]


def discover_usb() -> list[dict[str, Any]]:
    """usb devices per model (serial numbers), or why pyusb and libusb cannot look."""
    report: list[dict[str, Any]] = []
    try:
        core = importlib.import_module("usb.core")
        libusb_package = importlib.import_module("libusb_package")
        backend = libusb_package.get_libusb1_backend()
        if backend is None:
            raise DeviceError("libusb could not be loaded")
        for vid, pid, what in _ids():
            found = list(core.find(find_all=True, idVendor=vid, idProduct=pid, backend=backend))
            serials = []
            for dev in found:
                try:
                    serials.append(dev.serial_number)
                except (ValueError, core.USBError) as exc:
                    serials.append(f"(cannot open: {exc}; are the udev rules installed?)")
            report.append({"backend": "usb", "model": what, "found": serials})
    except ImportError:
        report.append(
            {
                "backend": "usb",
                "problem": "pyusb or libusb-package is not installed: pip install 'hapticd[usb]'",
            }
        )
    except (DeviceError, OSError) as exc:
        report.append({"backend": "usb", "problem": str(exc)})
    return report


def _ids() -> list[tuple[int, int, str]]:
    """The protocol devices' IDs (the hid and usb backends look for these)."""
    own = {ids for m in models.MODELS for ids in m.usb_ids}
    return [(v, p, w) for v, p, w in usb_ids() if p is not None and (v, p) not in own]
