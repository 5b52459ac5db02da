"""hapticd: real-time haptic rendering for two-finger grasping with underactuated devices."""

__version__ = "0.1.0"
