"""Lamina device: camera capture, laser and motion control, on-device stripe extraction."""

__version__ = "0.1.0"
