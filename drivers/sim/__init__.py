"""Simulated camera: VISCA device, world, optics renderer and frame source."""
