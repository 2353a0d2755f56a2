"""The browser UI in a real Chromium (Debian's, driven by Playwright) against a real ``droneulator run --ui``.

One run serves the flight tests, in order: level select, loading vineyard, live RGB, click-to-fly,
keyboard flying, an out-of-bounds click, and last the simulator restarting under the open page. What the
page did is always checked through the API with the project's own client, never through the page alone.
Screenshots go to docs/img/ui_*.png.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from droneulator.config import CameraConfig, load_config
from droneulator.runtime.launch import LaunchedRun, LaunchError, free_port, launch_run
from droneulator.scenes import list_scenes
from droneulator.ui.images import pack_frame, unpack_frame

playwright = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="Chromium is not installed (scripts/setup.sh --dev)"
)
IMG = Path(__file__).resolve().parents[1] / "docs" / "img"

#: pixel statistics of an <img> drawn on a canvas: mean and standard deviation of the luminance
IMAGE_STATS = """(img) => {
  const c = document.createElement("canvas");
  c.width = img.naturalWidth; c.height = img.naturalHeight;
  if (!c.width) return null;
  const g = c.getContext("2d"); g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data;
  let s = 0, s2 = 0, n = d.length / 4, hash = 0;
  for (let i = 0; i < d.length; i += 4) {
    const y = 0.299 * d[i] + 0.587 * d[i + 1] + 0.114 * d[i + 2];
    s += y; s2 += y * y; hash = (hash * 31 + d[i] + 7 * d[i + 1]) % 1000000007;
  }
  const mean = s / n;
  return {mean, std: Math.sqrt(Math.max(0, s2 / n - mean * mean)), hash, src: img.src};
}"""


def run_config():
    cfg = load_config(scene="default")
    cfg.render.cameras = [CameraConfig(name="front", width=320, height=240)]
    cfg.render.shadow_map_size = 1024
    return cfg


def start_run(ui_port: int) -> LaunchedRun:
    # realtime: under a loaded CI machine lockstep may crawl; the UI behaves the same in both modes
    return launch_run(run_config(), ["--realtime", "--ui-port", str(ui_port)], start_timeout=120)


class Stack:
    """The run, its UI port, an API client, and one browser page kept open through the tests."""

    def __init__(self, ui_port: int, run: LaunchedRun, page) -> None:
        self.ui_port = ui_port
        self.run = run
        self.page = page
        self.client = run.client()

    def wait(self, predicate, timeout: float, what: str, poll: float = 0.1):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = predicate()
            if value:
                return value
            time.sleep(poll)
        raise AssertionError(f"timed out after {timeout} s waiting for {what}\n" + self.run.log.tail(25))


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (scripts/setup.sh --dev)")
    ui_port = free_port()
    run = start_run(ui_port)
    pw = playwright.sync_playwright().start()
    browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
    page = browser.new_page(viewport={"width": 1500, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    s = Stack(ui_port, run, page)
    try:
        yield s
    finally:
        s.client.close()
        browser.close()
        pw.stop()
        s.run.stop()
    assert not errors, f"JavaScript errors in the page: {errors}"


def rgb_stats(page) -> dict | None:
    img = page.query_selector('figure.camera.rgb[data-cam="front"] > img')
    return None if img is None else img.evaluate(IMAGE_STATS)


# ----------------------------------------------------------------------------------------------- no browser
def test_image_frames_round_trip_and_reject_truncation() -> None:
    blob = pack_frame({"cam": "front", "kind": "rgb", "stamp_ns": 5}, b"\xff\xd8jpeg")
    assert unpack_frame(blob) == ({"cam": "front", "kind": "rgb", "stamp_ns": 5}, b"\xff\xd8jpeg")
    with pytest.raises(ValueError, match="shorter than its header"):
        unpack_frame(blob[:10])


@pytest.mark.slow
def test_run_rejects_a_ui_port_in_use() -> None:
    """A taken UI port is a start-up error in words, and the simulator it started is stopped again."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        cfg = run_config()
        try:  # the run may exit before or after its API first answers
            run = launch_run(cfg, ["--realtime", "--ui-port", str(port)], start_timeout=60)
        except LaunchError as exc:
            said = str(exc)
        else:
            try:
                assert run.proc.wait(60) == 1
            finally:
                run.stop()
            said = run.log.tail(10)
    assert f"droneulator: error: cannot start the UI on 127.0.0.1:{port}" in said


@needs_chromium
def test_ui_without_a_simulator_says_so() -> None:
    """``droneulator ui`` against nothing: the page loads, says the simulator is unreachable, and a
    command gets an error in words instead of silence."""
    port = free_port()
    dead = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "droneulator.cli",
            "ui",
            "--url",
            f"ws://127.0.0.1:{dead}",
            "--zenoh",
            f"tcp/127.0.0.1:{dead}",
            "--port",
            str(port),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == f"UI: http://127.0.0.1:{port}"
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{port}/#fly")
            page.wait_for_function(
                "document.getElementById('conn').textContent.includes('unreachable')", timeout=20000
            )
            page.click("#btn-takeoff")
            page.wait_for_selector("#errors .error:has-text('not reachable')", timeout=10000)
            assert f"ws://127.0.0.1:{dead}" in page.inner_text("#errors")
            browser.close()
    finally:
        proc.terminate()
        assert proc.wait(15) == 0  # SIGTERM ends it cleanly, even while a preview renders


# ----------------------------------------------------------------------------------------------- the run
@pytest.mark.slow
def test_level_select_lists_every_scene_with_a_preview(stack: Stack) -> None:
    page = stack.page
    page.goto(f"http://127.0.0.1:{stack.ui_port}/")
    page.wait_for_function(
        "[...document.querySelectorAll('.card img')].length > 0 && "
        "[...document.querySelectorAll('.card img')].every(i => i.complete && i.naturalWidth > 0)",
        timeout=180000,
    )
    cards = page.query_selector_all(".card")
    assert [c.get_attribute("data-scene") for c in cards] == list(list_scenes())
    for card in cards:
        stats = card.query_selector("img").evaluate(IMAGE_STATS)
        assert stats["std"] > 10, f"{card.get_attribute('data-scene')}: blank preview {stats}"
        assert list_scenes()[card.get_attribute("data-scene")] in card.inner_text()
    page.screenshot(path=str(IMG / "ui_levels.png"))


@pytest.mark.slow
def test_choosing_vineyard_loads_it(stack: Stack) -> None:
    page = stack.page
    page.fill("#seed", "0")
    page.click(".card[data-scene=vineyard]")
    page.wait_for_selector("#fly:not([hidden])", timeout=120000)
    assert stack.client.scene_info()["name"] == "vineyard"
    page.wait_for_function("window.droneulatorUI.map.meta !== null", timeout=60000)


@pytest.mark.slow
def test_rgb_view_shows_a_changing_image(stack: Stack) -> None:
    page, client = stack.page, stack.client
    first = stack.wait(lambda: rgb_stats(page), 60, "the first RGB image")
    assert first["std"] > 10, f"blank RGB image: {first}"
    page.click("#btn-takeoff")  # the climb changes the view
    stack.wait(lambda: client.state()["position"][2] > 1.8, 60, "the take-off through the button")
    later = stack.wait(lambda: (s := rgb_stats(page)) and s["hash"] != first["hash"] and s, 30, "a new image")
    assert later["std"] > 10
    stack.wait(lambda: client.state()["mode"] == "hold", 30, "the climb to end")


@pytest.mark.slow
def test_map_click_flies_there(stack: Stack) -> None:
    page, client = stack.page, stack.client
    target = (-17.0, 0.0)  # the middle alley of the vineyard, 3 m ahead of the spawn
    u, v = page.evaluate(f"window.droneulatorUI.map.toCanvas({target[0]}, {target[1]})")
    box = page.query_selector("#map").bounding_box()
    width = page.evaluate("document.getElementById('map').width")
    height = page.evaluate("document.getElementById('map').height")
    page.mouse.click(box["x"] + u * box["width"] / width, box["y"] + v * box["height"] / height)
    z0 = client.state()["position"][2]
    goal = stack.wait(lambda: page.evaluate("window.droneulatorUI.map.goal"), 10, "the goal on the map")
    assert math.dist(goal[:2], target) < 0.25 and abs(goal[2] - z0) < 0.1  # at the current altitude
    stack.wait(lambda: client.state()["mode"] == "goto", 10, "the goto to start")
    state = stack.wait(lambda: (s := client.state())["mode"] == "hold" and s, 60, "the vehicle to arrive")
    assert math.dist(state["position"][:2], target) < 0.3, state["position"]
    page.screenshot(path=str(IMG / "ui_flight.png"), full_page=True)


@pytest.mark.slow
def test_keyboard_w_moves_forward(stack: Stack) -> None:
    page, client = stack.page, stack.client
    before = client.state()
    page.focus("#map")
    page.keyboard.down("w")
    stack.wait(lambda: client.state()["mode"] == "velocity", 10, "velocity mode")
    time.sleep(1.5)
    page.keyboard.up("w")
    after = stack.wait(
        lambda: (s := client.state())["mode"] == "hold" and s, 10, "hold after the key is released"
    )
    yaw = before["yaw"]
    dx, dy = (after["position"][i] - before["position"][i] for i in range(2))
    forward = dx * math.cos(yaw) + dy * math.sin(yaw)
    sideways = -dx * math.sin(yaw) + dy * math.cos(yaw)
    assert forward > 0.5 and abs(sideways) < 0.3 * forward, (forward, sideways)


@pytest.mark.slow
def test_out_of_bounds_click_shows_the_api_message(stack: Stack) -> None:
    page = stack.page
    page.click("#map", position={"x": 4, "y": 4})  # the dimmed margin outside the flyable box
    error = page.wait_for_selector("#errors .error:has-text('out of bounds')", timeout=10000)
    assert "is outside the scene bounds" in error.inner_text()  # the API's own words
    page.screenshot(path=str(IMG / "ui_error.png"))


@pytest.mark.slow
def test_page_survives_a_simulator_restart(stack: Stack) -> None:
    page = stack.page
    stack.client.close()
    stack.run.stop()
    page.wait_for_function(
        "document.getElementById('conn').textContent.includes('unreachable')", timeout=30000
    )
    stack.run = start_run(stack.ui_port)
    stack.client = stack.run.client()
    page.wait_for_function(
        "document.getElementById('conn').textContent.startsWith('simulator:')", timeout=60000
    )
    shown = page.evaluate("window.droneulatorUI.cameras.count")
    t0 = stack.client.state()["t"]
    page.wait_for_function(
        f"window.droneulatorUI.state && window.droneulatorUI.state.t > {t0}", timeout=30000
    )
    page.wait_for_function(f"window.droneulatorUI.cameras.count > {shown + 3}", timeout=60000)
    page.click("#btn-takeoff")  # and it flies the new simulator
    stack.wait(lambda: stack.client.state()["position"][2] > 0.5, 60, "the take-off after the restart")
