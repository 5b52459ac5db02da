"""The ``hid`` backend: a report-protocol delta device through cython-hidapi (see report_device)."""

from hapticd_drivers.report_device import HidDelta

__all__ = ["HidDelta"]
