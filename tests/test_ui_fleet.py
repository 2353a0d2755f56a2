"""The browser UI with a fleet: a real Chromium (Playwright) against a real two-vehicle ``droneulator run
--ui``. The page draws both vehicles, the selector points the camera views and the map click at the
second one, and that vehicle, not the first, flies there; every effect is checked through the API.
Screenshot: out/screenshots/ui_fleet.png (tests/screenshots.py).
"""

from __future__ import annotations

import math
import time
from typing import Any

import pytest
from screenshots import SHOTS
from ui_session import CHROMIUM, ui_page, wait

from droneulator.config import CameraConfig, fleet, load_config
from droneulator.ui.images import vehicle_streams

#: RGB of the map's pixel where world point (x, y) is drawn
MAP_PIXEL = """([x, y]) => {
  const [u, v] = window.droneulatorUI.map.toCanvas(x, y);
  const c = document.getElementById("map");
  return [...c.getContext("2d").getImageData(Math.round(u), Math.round(v), 1, 1).data.slice(0, 3)];
}"""


def test_vehicle_streams_come_from_scene_info_or_the_vehicles_names() -> None:
    """The UI subscribes to the image topics ``scene_info`` lists; an API that lists none (served
    without the bridge) gets the names the bridge would give, by the same rule."""
    topics = {"rgb": "/a/rgb", "depth": "/a/d", "seg": "/a/s", "info_rgb": "/a/i", "pose": "/a/p"}
    listed = {"vehicles": [{"name": "x", "cameras": ["down"], "topics": {"cameras": {"down": topics}}}]}
    assert vehicle_streams(listed, "ns") == {"x": {"down": {"rgb": "/a/rgb", "depth": "/a/d", "seg": "/a/s"}}}
    two = {"vehicles": [{"name": "uav0", "cameras": ["front"]}, {"name": "uav1", "cameras": ["front"]}]}
    streams = vehicle_streams(two, "droneulator")
    assert list(streams) == ["uav0", "uav1"]
    assert streams["uav1"]["front"]["rgb"] == "/droneulator/uav1/front/color/image_raw/compressed"
    one = vehicle_streams({"vehicles": [{"name": "uav0", "cameras": ["front"]}]}, "droneulator")
    assert one["uav0"]["front"]["depth"] == "/droneulator/front/depth/image_raw"
    assert vehicle_streams({}, "droneulator") == {}


def click_map(page: Any, x: float, y: float) -> None:
    """A mouse click on the map where world point (x, y) is drawn."""
    u, v = page.evaluate(f"window.droneulatorUI.map.toCanvas({x}, {y})")
    box = page.query_selector("#map").bounding_box()
    width, height = page.eval_on_selector("#map", "c => [c.width, c.height]")
    page.mouse.click(box["x"] + u * box["width"] / width, box["y"] + v * box["height"] / height)


def colour_near(got: list[int], want: str) -> bool:
    rgb = [int(want[i : i + 2], 16) for i in (1, 3, 5)]
    return max(abs(a - b) for a, b in zip(got, rgb, strict=True)) < 40


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (scripts/setup.sh --dev)")
def test_ui_flies_the_second_vehicle_by_a_map_click() -> None:
    """Select uav1 in the selector: the camera views and telemetry follow it; a map click flies uav1
    there while uav0 stays put; both are drawn in their colours; a click on uav0's arrow selects it."""
    cfg = load_config(scene="default")
    cfg.vehicles = fleet(2)
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120)]
    cfg.render.shadows = False
    ready = "window.droneulatorUI.map.meta && window.droneulatorUI.cameras.count > 2"
    with ui_page(cfg, ["--realtime"], ready) as (run, client, page, errors):
        # both vehicles in the selector, the first selected; its cameras shown
        names = page.eval_on_selector_all("#vehicle-list button", "bs => bs.map(b => b.dataset.vehicle)")
        assert names == ["uav0", "uav1"]
        assert page.get_attribute("#vehicle-list [data-vehicle=uav0]", "aria-checked") == "true"
        assert "uav0" in page.inner_text("figure.camera.rgb figcaption")

        page.click("#vehicle-list [data-vehicle=uav1]")
        assert page.get_attribute("#vehicle-list [data-vehicle=uav1]", "aria-checked") == "true"
        page.wait_for_function(
            "window.droneulatorUI.cameras.shown.some(s => s.vehicle === 'uav1')", timeout=20000
        )
        assert "uav1" in page.inner_text("figure.camera.rgb figcaption")
        page.wait_for_function("window.droneulatorUI.state?.vehicle === 'uav1'", timeout=10000)
        assert "uav1" in page.inner_text("#telemetry")

        before = client.state(vehicle="*")["vehicles"]
        target = (-3.0, 4.0)  # clear of the meadow's trees, 4 m from uav1's start
        click_map(page, *target)
        goal = wait(lambda: page.evaluate("window.droneulatorUI.map.goal"), 10, "the goal", run.log)
        assert math.dist(goal[:2], target) < 0.25
        arrived = lambda: (s := client.state(vehicle="uav1"))["mode"] == "hold" and s  # noqa: E731
        uav1 = wait(arrived, 40, "uav1 to arrive", run.log)
        assert math.dist(uav1["position"][:2], target) < 0.3, uav1["position"]
        uav0 = client.state(vehicle="uav0")
        assert uav0["mode"] == "idle"
        assert math.dist(uav0["position"], before["uav0"]["position"]) < 0.05
        # every image shown since the selection is uav1's
        shown = page.evaluate("window.droneulatorUI.cameras.shown.map(s => s.vehicle)")
        assert shown[shown.index("uav1") :] == ["uav1"] * (len(shown) - shown.index("uav1"))

        # both drawn on the map, each in its colour, where the API says they are
        def drawn() -> bool:
            return all(
                colour_near(page.evaluate(MAP_PIXEL, s["position"][:2]), colour)
                for s, colour in ((uav0, "#00e5ff"), (uav1, "#ffb000"))
            )

        wait(drawn, 5, "both vehicles drawn on the map", run.log)
        page.screenshot(path=str(SHOTS / "ui_fleet.png"), full_page=True)

        # a click on the other vehicle's arrow selects it and flies nothing
        click_map(page, *uav0["position"][:2])
        page.wait_for_function("window.droneulatorUI.selected === 'uav0'", timeout=5000)
        time.sleep(0.5)
        assert client.state(vehicle="uav0")["mode"] == "idle"
        assert client.state(vehicle="uav1")["mode"] == "hold"
        assert not errors, f"JavaScript errors in the page: {errors}"
