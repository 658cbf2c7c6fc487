"""Roadwatch core: configuration, geometry, processing stages, traffic measures and storage."""

__version__ = "0.1.0"
