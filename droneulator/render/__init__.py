"""Headless sensor rendering: RGB, metric depth and segmentation for body-mounted cameras."""

from droneulator.render.renderer import CameraFrame, Renderer

__all__ = ["CameraFrame", "Renderer"]
