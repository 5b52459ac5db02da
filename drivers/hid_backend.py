"""The ``hid`` backend: a protocol delta device through cython-hidapi (see protocol_device)."""

from hapticd_drivers.protocol_device import HidDelta

__all__ = ["HidDelta"]
