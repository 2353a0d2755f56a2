"""The spray deposit on the browser UI's map: a real Chromium (Playwright) against a real ``droneulator run
--ui`` with a sprayer. Before spraying the layer has no visible pixel; after, it has them round where
the API says the vehicle is; the toggle hides it; the telemetry shows the spray state; a malformed
reply is refused without breaking the page. Screenshot: out/screenshots/ui_spray_deposit.png.
"""

from __future__ import annotations

import math

import pytest
from screenshots import SHOTS
from ui_session import CHROMIUM, ui_page, wait

from droneulator.config import CameraConfig, load_config

#: the deposit layer's visible cells as world x, y (cell centres), from the layer's own canvas
WET_CELLS = """() => {
  const layer = window.droneulatorUI.deposit.layer;
  const {canvas, extent} = layer;
  const px = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
  const cell = (extent[2] - extent[0]) / canvas.width;
  const out = [];
  for (let i = 0; i < px.length; i += 4) {
    if (px[i + 3] === 0) continue;
    const c = (i / 4) % canvas.width, r = Math.floor(i / 4 / canvas.width);
    out.push([extent[0] + (c + 0.5) * cell, extent[1] + (r + 0.5) * cell]);
  }
  return out;
}"""

#: RGBA of the map's pixel where world point (x, y) is drawn
MAP_PIXEL = """([x, y]) => {
  const [u, v] = window.droneulatorUI.map.toCanvas(x, y);
  const c = document.getElementById("map");
  return [...c.getContext("2d").getImageData(Math.round(u), Math.round(v), 1, 1).data];
}"""

#: what the layer's decoder makes of replies that do not fit
BAD_REPLIES = """async () => {
  const {decodeDeposit} = await import("/static/deposit.js");
  const good = {version: 1, width: 2, height: 2, cell_m: 1, origin: [0, 0]};
  const one = "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVQI12NgAAAAAgAB4iG8MwAAAABJRU5ErkJggg==";
  const out = [];
  for (const bad of [null, {...good, png: "not base64!"}, {...good, png: one}, {...good, width: -1, png: one},
                     {...good, origin: [0, "x"], png: one}]) {
    try { await decodeDeposit(bad); out.push("accepted"); } catch (e) { out.push(e.message); }
  }
  return out;
}"""


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (scripts/setup.sh --dev)")
def test_the_map_draws_the_spray_deposit_where_the_vehicle_sprayed() -> None:
    sets = ["spray.enabled=true", "vehicle.params=sprayer10", "spray.parcels_per_s=200", "render.camera_hz=5"]
    cfg = load_config(scene="default", overrides=sets)
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120)]
    cfg.render.shadows = False
    ready = "window.droneulatorUI.map.meta && window.droneulatorUI.deposit.layer"
    with ui_page(cfg, [], ready) as (run, client, page, errors):
        # before spraying: the layer and its legend are there, with nothing drawn
        assert page.is_visible("#deposit-bar") and page.is_checked("#deposit-toggle")
        assert page.evaluate("window.droneulatorUI.deposit.layer.cells") == 0
        assert page.evaluate(WET_CELLS) == []
        page.wait_for_function("document.getElementById('telemetry').textContent.includes('spray')")
        assert "off, tank 10.00 / 10.00 L" in page.inner_text("#telemetry")

        client.request("takeoff", altitude=2.0)
        client.request("spray", rate=1.0)  # spraying as it climbs
        page.wait_for_function("window.droneulatorUI.deposit.layer.cells > 20", timeout=60000)
        page.wait_for_function(
            "document.getElementById('telemetry').textContent.includes('on at 100 %')", timeout=10000
        )
        x, y = client.state()["position"][:2]
        wet = page.evaluate(WET_CELLS)
        assert len(wet) > 20
        distances = sorted(math.dist((x, y), c) for c in wet)
        assert distances[0] < 0.5 and distances[len(distances) // 2] < 3.0, distances[:5]
        # a short pass, spraying: the deposit follows the vehicle to where it stops
        wait(lambda: client.state()["position"][2] > 1.5, 30, "the climb", run.log)
        client.request("goto", position=[6.0, -1.5, 2.0], speed=2.5)
        wait(lambda: client.state()["mode"] == "hold", 30, "the pass", run.log)
        x, y = client.state()["position"][:2]
        t = client.state()["t"]
        page.wait_for_function(f"window.droneulatorUI.deposit.layer.t > {t + 0.5}", timeout=20000)
        assert min(math.dist((x, y), c) for c in page.evaluate(WET_CELLS)) < 0.5
        page.screenshot(path=str(SHOTS / "ui_spray_deposit.png"), full_page=True)

        # the toggle hides the layer: a wet cell clear of the vehicle's arrow shows the map again
        spot = max((c for c in page.evaluate(WET_CELLS) if math.dist((x, y), c) < 4.0),
                   key=lambda c: math.dist((x, y), c))  # fmt: skip
        shown = page.evaluate(MAP_PIXEL, spot)
        page.click("#deposit-toggle")
        wait(lambda: page.evaluate(MAP_PIXEL, spot) != shown, 5, "the layer to go", run.log)
        hidden = page.evaluate(MAP_PIXEL, spot)
        page.click("#deposit-toggle")
        wait(lambda: page.evaluate(MAP_PIXEL, spot) != hidden, 5, "the layer to come back", run.log)

        refused = page.evaluate(BAD_REPLIES)
        assert "accepted" not in refused, refused
        assert not errors, f"JavaScript errors in the page: {errors}"
