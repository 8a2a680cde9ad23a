"""Cameras, geometry and per-pixel buffers: everything that produces a capture folder."""
