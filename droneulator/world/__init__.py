"""The world: a scene, a clock and every vehicle in it, stepped together (:class:`World`)."""

from droneulator.world.world import FrameSet, StepResult, World

__all__ = ["FrameSet", "StepResult", "World"]
