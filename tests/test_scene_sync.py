"""The dynamics server's scene sync: what the render server and the bridge must load, and when."""

from __future__ import annotations

import dataclasses

from droneulator.config import load_config
from droneulator.runtime.ipc import LoadScene
from droneulator.runtime.scene_sync import SceneSync


def test_a_reset_to_another_scene_is_sent_once_and_to_every_later_newcomer() -> None:
    cfg = load_config(scene="default")
    sync = SceneSync(cfg)
    assert sync.changed() is None and sync.for_newcomer() is None  # as the run started
    cfg.scene, cfg.seed = "orchard", 3  # what World.reset does to its config
    assert sync.changed() == LoadScene("orchard", 3, cfg.light, cfg.vegetation)
    assert sync.changed() is None  # once per change
    assert sync.for_newcomer() == LoadScene("orchard", 3, cfg.light, cfg.vegetation)


def test_a_vegetation_or_light_change_reaches_a_restarted_process() -> None:
    """A render server restarted after a reset changed only the vegetation (or the light) is welcomed with
    the scene and seed, so it must be told the rest: it starts from the run's own config."""
    cfg = load_config(scene="vineyard")
    sync = SceneSync(cfg)
    cfg.vegetation = 0.5
    assert sync.for_newcomer() == LoadScene("vineyard", cfg.seed, cfg.light, 0.5)
    cfg.vegetation = load_config(scene="vineyard").vegetation
    cfg.light = dataclasses.replace(cfg.light, time_of_day_h=18.0)
    assert sync.for_newcomer() == LoadScene("vineyard", cfg.seed, cfg.light, cfg.vegetation)
    cfg.light = load_config(scene="vineyard").light
    assert sync.for_newcomer() is None
