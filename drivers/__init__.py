"""hapticd's device layer: one small interface, one backend per module, chosen by name.

This package never imports ``hapticd``. Import name ``hapticd_drivers``.
"""

from hapticd_drivers.base import (
    BackendUnavailableError,
    Device,
    DeviceError,
    DeviceInfo,
    DeviceLostError,
    DeviceState,
)
from hapticd_drivers.registry import BACKENDS, backend_names, open_device

__all__ = [
    "BACKENDS",
    "BackendUnavailableError",
    "Device",
    "DeviceError",
    "DeviceInfo",
    "DeviceLostError",
    "DeviceState",
    "backend_names",
    "open_device",
]
