"""Backend registry: a name maps to a module and class, imported only when selected."""

from __future__ import annotations

import importlib
from typing import Any

from hapticd_drivers.base import BackendUnavailableError, Device

# name -> (module, class, pip extra that provides its optional dependency)
BACKENDS: dict[str, tuple[str, str, str | None]] = {
    "replay": ("hapticd_drivers.replay", "ReplayDevice", None),
    "sim": ("hapticd_drivers.sim", "SimulatedFinger", None),
    "hid": ("hapticd_drivers.hid_backend", "HidDelta", "hid"),
    "usb": ("hapticd_drivers.usb_backend", "UsbDelta", "usb"),
    "dhd": ("hapticd_drivers.dhd_backend", "DhdDevice", None),
}


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def open_device(backend: str, **kwargs: Any) -> Device:
    """Create (not yet open) a device of ``backend`` with backend-specific ``kwargs``."""
    try:
        module_name, class_name, extra = BACKENDS[backend]
    except KeyError:
        raise BackendUnavailableError(
            f"unknown device backend {backend!r}; known backends: {', '.join(backend_names())}"
        ) from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        hint = f" (install it with: pip install 'hapticd[{extra}]')" if extra else ""
        raise BackendUnavailableError(
            f"device backend {backend!r} needs a package that is missing: {exc.name}{hint}"
        ) from exc
    cls = getattr(module, class_name)
    return cls(**kwargs)
