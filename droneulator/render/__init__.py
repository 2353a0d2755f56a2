"""Headless sensor rendering: RGB, metric depth and segmentation for body-mounted cameras."""

from droneulator.render.renderer import CameraFrame, Renderer, fleet_renderer

__all__ = ["CameraFrame", "Renderer", "fleet_renderer"]
