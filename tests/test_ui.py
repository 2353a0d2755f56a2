"""The browser UI in a real Chromium (Debian's, driven by Playwright) against a real ``droneulator run --ui``.

One run serves the flight tests, in order: level select, loading vineyard, live RGB, click-to-fly,
keyboard flying, an out-of-bounds click, and last the simulator restarting under the open page. What the
page did is always checked through the API with the project's own client, never through the page alone.
Screenshots go to out/screenshots/ui_*.png (tests/screenshots.py).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from screenshots import SHOTS

from droneulator.config import CameraConfig, load_config
from droneulator.imaging import depth_to_rgb
from droneulator.runtime.launch import LaunchedRun, LaunchError, free_port, launch_run
from droneulator.scenes import list_scenes
from droneulator.threads import DaemonWorker
from droneulator.ui.images import pack_frame, unpack_frame

playwright = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="Chromium is not installed (scripts/setup.sh --dev)"
)

#: pixel statistics of an <img> or a camera view's <canvas> drawn on a canvas: mean and standard
#: deviation of the luminance
IMAGE_STATS = """(img) => {
  const c = document.createElement("canvas");
  c.width = img.naturalWidth ?? img.width; c.height = img.naturalHeight ?? img.height;
  if (!c.width) return null;
  const g = c.getContext("2d"); g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data;
  let s = 0, s2 = 0, n = d.length / 4, hash = 0;
  for (let i = 0; i < d.length; i += 4) {
    const y = 0.299 * d[i] + 0.587 * d[i + 1] + 0.114 * d[i + 2];
    s += y; s2 += y * y; hash = (hash * 31 + d[i] + 7 * d[i + 1]) % 1000000007;
  }
  const mean = s / n;
  return {mean, std: Math.sqrt(Math.max(0, s2 / n - mean * mean)), hash};
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
        try:
            self.client = run.client()
        except OSError as exc:  # say why: one fresh-clone CI run found the API gone at this point
            raise RuntimeError(
                f"the run stopped answering ({exc}); running: {run.running()}; log:\n{run.log.tail(40)}"
            ) from exc

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
    img = page.query_selector('figure.camera.rgb[data-cam="front"] > canvas')
    return None if img is None else img.evaluate(IMAGE_STATS)


# ----------------------------------------------------------------------------------------------- no browser
def test_image_frames_round_trip_and_reject_truncation() -> None:
    blob = pack_frame({"cam": "front", "kind": "rgb", "stamp_ns": 5}, b"\xff\xd8jpeg")
    assert unpack_frame(blob) == ({"cam": "front", "kind": "rgb", "stamp_ns": 5}, b"\xff\xd8jpeg")
    with pytest.raises(ValueError, match="shorter than its header"):
        unpack_frame(blob[:10])


@pytest.mark.slow
def test_depth_colours_follow_the_colour_map() -> None:
    """The UI's depth view: the table lookup gives the colour map's colours to within one level, and no
    depth (NaN, an infinity) is black."""
    depth = np.linspace(-1.0, 25.0, 4000, dtype=np.float32).reshape(40, 100)
    depth[3, 7], depth[4, 8], depth[5, 9] = np.nan, np.inf, -np.inf
    x = 1.0 - np.clip(np.where(np.isfinite(depth), depth, 20.0) / 20.0, 0.0, 1.0)
    r, g = np.clip(1.6 * x - 0.2, 0, 1), np.clip(1.4 * x * x, 0, 1)
    want = np.stack([r, g, np.clip(0.6 - 0.6 * x, 0, 1) * x + 0.15 * x], -1)
    want = (want * 255).astype(np.uint8)
    want[3, 7] = want[4, 8] = want[5, 9] = 0
    got = depth_to_rgb(depth, 20.0)
    assert got.shape == (40, 100, 3) and got.dtype == np.uint8
    assert np.abs(got.astype(int) - want).max() <= 2
    assert (got[3:6, 7:10].diagonal(axis1=0, axis2=1) == 0).all()  # NaN and both infinities: black
    far = np.isfinite(depth) & (depth >= 20.0)
    assert (got[far] == got[-1, -1]).all()


def test_ui_threads_run_at_a_lower_priority() -> None:
    """A UI worker thread takes the configured nice value on top of the process's (Linux: per thread)."""
    base = os.getpriority(os.PRIO_PROCESS, 0)
    worker = DaemonWorker("test-ui-nice", nice=5)
    try:
        tid = worker.submit(threading.get_native_id).result(5)
        nice = int(Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()[16])
        assert nice == min(19, base + 5)
        assert os.getpriority(os.PRIO_PROCESS, 0) == base  # the calling thread keeps its own
    finally:
        worker.close()


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


def ui_beyond_loopback(port: int, dead: int) -> subprocess.Popen[str]:
    """``droneulator ui --host 0.0.0.0`` on ``port``, its API and Zenoh at ``dead`` (nothing there);
    its first lines (the token, the URL) are on its stdout."""
    return subprocess.Popen(
        [sys.executable, "-m", "droneulator.cli", "ui", "--host", "0.0.0.0", "--port", str(port),
         "--url", f"ws://127.0.0.1:{dead}", "--zenoh", f"tcp/127.0.0.1:{dead}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )  # fmt: skip


@needs_chromium
def test_ui_beyond_loopback_asks_for_the_token_and_connects_with_it() -> None:
    """``droneulator ui --host 0.0.0.0``: a token is generated and printed once; an /api/ route without
    it is 401 and a WebSocket without it gets one ``unauthorized`` reply and a close; the page asks for
    the token, refuses a wrong one, keeps the right one in sessionStorage and connects with it."""
    import json
    import urllib.error
    import urllib.request

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    port = free_port()
    dead = free_port()
    proc = ui_beyond_loopback(port, dead)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        assert line.startswith("access token: ") and "0.0.0.0 is beyond loopback" in line, line
        token = line.split()[2]
        assert proc.stdout.readline().strip() == f"UI: http://0.0.0.0:{port}"
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/api/config", timeout=10)
        assert refused.value.code == 401
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/config?token={token}", timeout=10) as r:
            assert json.loads(r.read())["api_url"] == f"ws://127.0.0.1:{dead}"
        with connect(f"ws://127.0.0.1:{port}/ws", close_timeout=1.0) as ws:
            got = []
            with pytest.raises(ConnectionClosed) as closed:
                while True:
                    got.append(json.loads(ws.recv(timeout=10.0)))
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
            assert [m["error"]["code"] for m in got] == ["unauthorized"]
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"http://127.0.0.1:{port}/#fly")
            page.wait_for_selector("#token-dialog[open]", timeout=20000)
            assert "access token needed" in page.inner_text("#conn")
            page.fill("#token-input", "wrong-token-wrong-token")
            page.click("#token-submit")
            page.wait_for_selector("#token-dialog[open] #token-why:has-text('refused')", timeout=20000)
            page.fill("#token-input", token)
            page.click("#token-submit")
            # connected to the UI server: it reports the simulator (not running here) as unreachable
            page.wait_for_function(
                "document.getElementById('conn').textContent.includes('simulator unreachable')", timeout=20000
            )
            assert not page.is_visible("#token-dialog")
            assert page.evaluate("sessionStorage.getItem('droneulator.token')") == token
            # the page's set-up, refused too until then, ran again with the token: the level select is built
            page.wait_for_function(
                "document.querySelectorAll('#scene-cards .card').length > 0", timeout=20000
            )
            preview = page.get_attribute("#scene-cards .card img", "data-src") or page.get_attribute(
                "#scene-cards .card img", "src"
            )
            assert preview is not None and f"token={token}" in preview
            page.click("#btn-takeoff")
            page.wait_for_selector("#errors .error:has-text('not reachable')", timeout=10000)
            # a reload reconnects with the stored token, without asking again
            page.reload()
            page.wait_for_function(
                "document.getElementById('conn').textContent.includes('simulator unreachable')", timeout=20000
            )
            assert not page.is_visible("#token-dialog")
            assert not errors, errors
            browser.close()
    finally:
        proc.terminate()
        assert proc.wait(15) == 0


@needs_chromium
def test_a_late_refusal_of_an_older_token_reconnects_with_the_newer_one() -> None:
    """The UI server's refusal of a wrong token can reach the page after the user entered the right one
    (seen on a loaded machine: the page's set-up was refused first, the user typed the right token, then
    the connection's refusal came). The page then connects with the token it holds instead of asking
    again. The late refusal is made here by holding the UI server's reply to the wrong token's
    connection (Playwright's WebSocket route) until the right token is in."""
    port = free_port()
    dead = free_port()
    proc = ui_beyond_loopback(port, dead)
    held: list[tuple[Any, ...]] = []
    routes: list[Any] = []

    def hold(ws: Any) -> None:
        server = ws.connect_to_server()
        server.on_message(lambda m: held.append(("message", m)))
        server.on_close(lambda code, reason: held.append(("close", code, reason)))
        routes.append(ws)

    try:
        assert proc.stdout is not None
        token = proc.stdout.readline().split()[2]
        assert proc.stdout.readline().strip() == f"UI: http://0.0.0.0:{port}"
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.route_web_socket(re.compile(r".*/ws\?token=wrong-token.*"), hold)
            page.goto(f"http://127.0.0.1:{port}/#fly")
            page.wait_for_selector("#token-dialog[open]", timeout=20000)
            page.fill("#token-input", "wrong-token-wrong-token")
            page.click("#token-submit")
            # the set-up's request with the wrong token is refused (HTTP 401); the connection's refusal
            # is held
            page.wait_for_selector("#token-dialog[open] #token-why:has-text('refused')", timeout=20000)
            deadline = time.monotonic() + 20.0
            while not any(h[0] == "close" for h in held):
                assert time.monotonic() < deadline, "the wrong token's connection was not refused"
                page.wait_for_timeout(50)
            assert len(routes) == 1 and held[-1][1] == 1008
            page.fill("#token-input", token)
            page.click("#token-submit")
            for h in held:  # now the refusal of the wrong token arrives
                if h[0] == "message":
                    routes[0].send(h[1])
                else:
                    routes[0].close(code=h[1], reason=h[2])
            page.wait_for_function(
                "document.getElementById('conn').textContent.includes('simulator unreachable')", timeout=20000
            )
            assert not page.is_visible("#token-dialog")
            assert page.evaluate("sessionStorage.getItem('droneulator.token')") == token
            assert not errors, errors
            browser.close()
    finally:
        proc.terminate()
        assert proc.wait(15) == 0


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
    page.screenshot(path=str(SHOTS / "ui_levels.png"))


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


#: in a page of the UI's origin: a fresh CameraViews fed three JPEGs, each header's ``more`` from ``mores``,
#: 40 ms apart or (``stepwise``) each once the one before is painted; the paint that showed each image
BURST = """async ([mores, stepwise]) => {
  const { CameraViews } = await import("/static/cameras.js");
  const until = async (done) => {
    for (const t0 = performance.now(); !done() && performance.now() - t0 < 20000; )
      await new Promise((r) => setTimeout(r, 10));
  };
  const root = document.createElement("div");
  document.body.append(root);
  // a burst's next image is waited for up to 20 s: the hold is judged, not this machine's timers
  const views = new CameraViews(root, { depth_max_m: 20, legend: [], burst_wait_ms: 20000 });
  const c = document.createElement("canvas");
  c.width = 64; c.height = 48;
  c.getContext("2d").fillRect(8, 8, 20, 20);
  const bytes = new Uint8Array(await (await new Promise((r) => c.toBlob(r, "image/jpeg"))).arrayBuffer());
  const kinds = ["rgb", "depth", "seg"];
  for (let i = 0; i < 3; i++) {
    views.show({ cam: "burst", kind: kinds[i], stamp_ns: 1, mime: "image/jpeg", more: mores[i] }, bytes);
    if (stepwise) await until(() => views.shown.length > i);  // this one painted before the next comes
    else await new Promise((r) => setTimeout(r, 40));
  }
  await until(() => views.shown.length === 3);
  return views.shown.map((s) => s.paint);
}"""


@pytest.mark.slow
def test_a_round_of_images_is_painted_at_once(stack: Stack) -> None:
    """The UI server sends a round's images back to back, each saying how many follow (``more``); the
    page paints the round once its last image is decoded: one compositor frame per round, not one per
    image (the largest part of the browser's CPU, docs/ui.md). An image that says nothing follows is
    painted without waiting for another (each before the next is sent: three paints); the same three
    sent 40 ms apart as one round are painted together."""
    page = stack.page.context.browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{stack.ui_port}/static/style.css")
        apart = page.evaluate(BURST, [[0, 0, 0], True])
        together = page.evaluate(BURST, [[2, 1, 0], False])
    finally:
        page.close()
    assert len(apart) == len(together) == 3
    assert len(set(apart)) == 3, f"paints of separate images: {apart}"
    assert len(set(together)) == 1, f"paints of one round: {together}"


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
    # no spraying in this run: no deposit layer, and the page never asked for one
    assert page.is_hidden("#deposit-bar") and page.evaluate("window.droneulatorUI.deposit.askedT") is None
    page.screenshot(path=str(SHOTS / "ui_flight.png"), full_page=True)


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
    page.screenshot(path=str(SHOTS / "ui_error.png"))


@pytest.mark.slow
def test_a_collision_is_logged_and_flashes_the_views(stack: Stack) -> None:
    page, client = stack.page, stack.client
    page.evaluate(
        """() => {
      const flash = document.getElementById("flash");
      window.flashed = false;
      new MutationObserver(() => { if (flash.classList.contains("on")) window.flashed = true; })
        .observe(flash, { attributes: true });
    }"""
    )
    info = client.scene_info()
    assert info["name"] == "vineyard"
    x, y, _ = client.state()["position"]
    row = min(info["landmarks"]["row_y"], key=lambda r: abs(r - y))
    client.goto([x + 1.0, row, 1.2])  # into the nearest vine row's hedge
    page.wait_for_selector("#events li.event.collision", timeout=60000)
    assert page.evaluate("window.flashed")


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


@pytest.mark.slow
def test_px4_status_and_flight_controls_locked_while_px4_flies(stack: Stack) -> None:
    """With ``--px4``, the page shows PX4's status; while PX4 is armed the flight buttons are off with
    the reason shown, and they come back when it disarms. PX4 is played by a pymavlink peer. (A second
    simulator, in a new tab of the module's browser.)"""
    from test_px4 import Peer

    cfg = run_config()
    cfg.px4.base_port = free_port()
    ui_port = free_port()
    run = launch_run(cfg, ["--realtime", "--px4", "--ui-port", str(ui_port)], start_timeout=120)
    stop, armed = threading.Event(), threading.Event()

    def px4() -> None:
        peer = Peer(cfg.px4.base_port)
        peer.hello()
        peer.next(timeout=60)
        while not stop.is_set():
            peer.actuators((0.0,) * 4, armed=armed.is_set())
            peer.next(timeout=60)  # like PX4 in lockstep, wait for the sensors (the renderer may be booting)
            time.sleep(0.004)
        peer.close()

    flying = threading.Thread(target=px4, daemon=True)
    page = stack.page.context.browser.new_page(viewport={"width": 1500, "height": 1000})
    try:
        deadline = time.monotonic() + 60  # the UI starts once the simulator is up, after the API
        while not any(line.startswith("UI: http") for line in run.log.lines()):
            assert time.monotonic() < deadline, "the UI never started\n" + run.log.tail(25)
            time.sleep(0.1)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"http://127.0.0.1:{ui_port}/#fly")
        page.wait_for_selector("#px4:not([hidden])", timeout=60000)
        page.wait_for_function("window.droneulatorUI.state !== null", timeout=60000)  # subscribed
        assert "waiting for PX4" in page.inner_text("#px4-status")
        assert not page.is_disabled("#btn-takeoff")
        flying.start()
        page.wait_for_function(
            "document.getElementById('px4-status').textContent.includes('PX4 connected')", timeout=60000
        )
        page.wait_for_function("document.getElementById('btn-takeoff').disabled", timeout=30000)
        armed.set()
        page.wait_for_function(
            "document.getElementById('px4-status').textContent.includes('is armed')", timeout=30000
        )
        assert page.is_disabled("#btn-takeoff") and page.is_disabled("#btn-land")
        assert "PX4 is armed" in page.inner_text("#lock-reason")
        page.wait_for_function(
            "window.droneulatorUI.map.meta && window.droneulatorUI.cameras.count > 3", timeout=60000
        )
        page.screenshot(path=str(SHOTS / "ui_px4.png"), full_page=True)
        stop.set()  # PX4 goes away: the simulator takes over and the UI may fly again
        page.wait_for_function(
            "document.getElementById('px4-status').textContent.includes('disconnected')", timeout=30000
        )
        # PX4 was lost with the vehicle on the ground: the link's px4_lost event says so after it
        page.wait_for_function(
            "document.getElementById('px4-status').textContent.includes('the vehicle rests on the ground')",
            timeout=30000,
        )
        assert not page.is_disabled("#btn-takeoff")
        assert page.is_hidden("#lock-reason")
        assert not errors, f"JavaScript errors in the page: {errors}"
    except BaseException:
        print(run.log.tail(40))  # shown by pytest with the failure
        raise
    finally:
        stop.set()
        if flying.is_alive():
            flying.join(10)
        page.close()
        run.stop()


def test_a_closed_tab_closes_its_api_connection_cleanly() -> None:
    """Found by benchmarks/soak.py: a tab that went away left its API connection closed with 1011
    (internal error), the connection being cancelled inside ``connect``; it closes with 1000."""
    import json

    from websockets.sync.client import connect
    from websockets.sync.server import serve

    from droneulator.config import UIConfig
    from droneulator.ui.server import UIServer

    codes: list[int | None] = []

    def api(ws) -> None:  # answers everything; records how each connection ended
        for raw in ws:
            msg = json.loads(raw)
            ws.send(json.dumps({"id": msg.get("id"), "ok": True, "result": {"vehicles": []}}))
        codes.append(ws.close_code)

    with serve(api, "127.0.0.1", 0) as fake:
        threading.Thread(target=fake.serve_forever, daemon=True).start()
        api_url = f"ws://127.0.0.1:{fake.socket.getsockname()[1]}"
        ui = UIServer(api_url, zenoh=f"tcp/127.0.0.1:{free_port()}", config=UIConfig(port=0, nice=0))
        url = ui.start_in_thread()
        try:
            with connect(url.replace("http", "ws") + "/ws") as tab:
                while '"connected": true' not in tab.recv(timeout=10):  # the tab's API link is up
                    pass
            deadline = time.monotonic() + 10
            while len(codes) < 2:  # scene_info's own connection, then the tab's
                assert time.monotonic() < deadline, codes
                time.sleep(0.05)
        finally:
            ui.stop()
            fake.shutdown()
    assert codes == [1000, 1000]
