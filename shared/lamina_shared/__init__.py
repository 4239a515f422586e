"""Lamina shared: the wire protocol, the raw capture format and common data types."""

__version__ = "0.1.0"
