"""Lamina host: turns device stripe points into millimetre contours and meshes."""

__version__ = "0.1.0"
