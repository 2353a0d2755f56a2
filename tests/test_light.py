"""The light section: the sun's position against published values, shadows that follow it, overcast, haze
(Koschmieder) and the historical default, on the real renderer (llvmpipe); bad values through the config
and the API; and the level select's light options in a real Chromium against a real ``droneulator run``.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import shutil
import signal
import subprocess

import numpy as np
import pytest
from test_render import cylinder
from test_render import quad as render_quad

from droneulator import frames
from droneulator.commands.ops import RequestError, execute, make_request
from droneulator.config import CameraConfig, ConfigError, LightConfig, SiteConfig, load_config
from droneulator.render import Renderer
from droneulator.render.light import (
    AMBIENT_GROUND,
    AMBIENT_SKY,
    KOSCHMIEDER,
    REFERENCE_ELEVATION_DEG,
    SUN_COLOR,
    historical_lighting,
    resolve_lighting,
    solar_position,
)
from droneulator.scenes.base import CollisionModel, MeshPart, Scene, SemanticClass
from droneulator.sensors.camera import intrinsics

HOME = SiteConfig()  # the default site, the default place of the sun
GREY = np.full((4, 4, 4), 100, dtype=np.uint8)
DARK = np.full((4, 4, 4), 40, dtype=np.uint8)
GREY[..., 3] = DARK[..., 3] = 255


# ----------------------------------------------------------------------------------------- small scenes
def quad(corners, cls: SemanticClass, texture: str = "grey") -> MeshPart:
    return render_quad(corners, cls, texture)


def pole(height: float = 3.0, radius: float = 0.15, sides: int = 16) -> MeshPart:
    """A vertical cylinder on the origin (a tree trunk), grey."""
    return dataclasses.replace(
        cylinder((0.0, 0.0), radius, height, SemanticClass.TRUNK, sides), texture="grey"
    )


def ground(half: float = 40.0) -> MeshPart:
    return quad(
        [[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], SemanticClass.GROUND
    )


def scene(parts: list[MeshPart], light: dict | None = None) -> Scene:
    return Scene(
        name="light",
        seed=0,
        parts=parts,
        textures={"grey": GREY, "dark": DARK},
        collision=CollisionModel(np.ones((2, 2, 2)), np.zeros(3), 1.0),
        spawn_position=np.zeros(3),
        spawn_yaw=0.0,
        bounds_min=np.array([-10.0, -10.0, 0.0]),
        bounds_max=np.array([10.0, 10.0, 10.0]),
        light=light or {},
    )


def pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    return frames.transform_from_pose(np.array([x, y, z]), frames.quat_from_euler(0.0, 0.0, yaw))


#: straight down from 14 m over the pole (a 160x120 camera, positive pitch looks down)
DOWN = CameraConfig(name="down", width=160, height=120, hfov_deg=90.0, position=(0, 0, 0), rpy_deg=(0, 90, 0))


def render(sc: Scene, cam: CameraConfig, T_wb: np.ndarray, light=None, shadow_map_size: int = 1024):
    """RGB (int), depth and segmentation of one frame, copied out of the renderer."""
    with Renderer(sc, [cam], shadow_map_size=shadow_map_size, light=light) as r:
        f = r.render(T_wb)[cam.name]
        return f.rgb.astype(int), f.depth.copy(), f.seg.copy(), f.T_world_optical


def world_points(cam: CameraConfig, depth: np.ndarray, T_wo: np.ndarray) -> np.ndarray:
    """(H, W, 3) Z-up world point of every pixel from its optical depth."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(intrinsics(cam)).T
    return (rays * depth[..., None]) @ T_wo[:3, :3].T + T_wo[:3, 3]


def at(hours: float, **kw) -> LightConfig:
    return LightConfig(time_of_day_h=hours, date="2026-06-21", **kw)


# ----------------------------------------------------------------------------------------- the sun
def test_solar_position_matches_published_values() -> None:
    """NREL's SPA paper example (Reda and Andreas 2004, table A5.1: zenith 50.11162, azimuth 194.34024 at
    2003-10-17 12:30:30 -07:00, 39.742476 N, 105.1786 W), solstice and equinox noons, and an equinox sunrise
    due east; elevations include refraction, as NOAA's calculator gives them."""
    tz = datetime.timezone(datetime.timedelta(hours=-7))
    el, az = solar_position(datetime.datetime(2003, 10, 17, 12, 30, 30, tzinfo=tz), 39.742476, -105.1786)
    assert abs(el - (90 - 50.11162)) < 0.05 and abs(az - 194.34024) < 0.05, (el, az)

    def noon(day: str, lat: float) -> tuple[float, float]:
        """The day's highest sun at ``lat`` (longitude 0), searched minute by minute around 12:00 UTC."""
        d = datetime.date.fromisoformat(day)
        t0 = datetime.datetime(d.year, d.month, d.day, 11, 30, tzinfo=datetime.UTC)
        return max(solar_position(t0 + datetime.timedelta(minutes=m), lat, 0.0) for m in range(60))

    el, az = noon("2026-06-21", HOME.latitude_deg)
    assert abs(el - (90 - HOME.latitude_deg + 23.44)) < 0.5 and abs(az - 180) < 2, (el, az)
    el, az = noon("2026-06-21", -33.87)  # Sydney's latitude: winter, the sun due north
    assert abs(el - (90 - 33.87 - 23.44)) < 0.5 and min(az, 360 - az) < 2, (el, az)
    el, _ = noon("2026-03-20", 45.0)
    assert abs(el - 45.0) < 0.5, el
    # equinox sunrise at the equator: due east, 06:00 local mean time give or take the equation of time
    light = LightConfig(time_of_day_h=6.0 + 7.5 / 60, date="2026-03-20", latitude_deg=0.0, longitude_deg=0.0)
    lighting = resolve_lighting(light, scene([ground()]))
    assert abs(lighting.azimuth_deg - 90.0) < 0.5 and abs(lighting.elevation_deg) < 0.6, lighting
    # the light's world frame is ENU: at noon the sun is south (-y) and up (+z), in the morning east (+x)
    noon_sun = resolve_lighting(at(12.0), scene([ground()]), HOME).sun
    morning_sun = resolve_lighting(at(7.0), scene([ground()]), HOME).sun
    assert noon_sun[1] < -0.4 and noon_sun[2] > 0.8 and abs(noon_sun[0]) < 0.05, noon_sun
    assert morning_sun[0] > 0.5, morning_sun


def test_the_sun_is_computed_at_the_site_and_on_its_clock() -> None:
    """The default site gives the sun the old PX4 home gave it (53.2281 N, 0.547 W, local mean solar
    time); the config's site moves it, ``site.utc_offset_h`` sets the clock, a light's own place wins."""
    from droneulator.render.renderer import config_lighting

    plain = scene([ground()])
    old_tz = datetime.timezone(datetime.timedelta(hours=-0.5470 / 15.0))
    old = solar_position(datetime.datetime(2026, 6, 21, 9, 30, tzinfo=old_tz), 53.2281, -0.5470)
    for lighting in (
        resolve_lighting(at(9.5), plain),
        config_lighting(plain, load_config(overrides=["light.time_of_day_h=9.5", "light.date=2026-06-21"])),
    ):
        assert (lighting.elevation_deg, lighting.azimuth_deg) == pytest.approx(old, abs=1e-9)
    sydney = SiteConfig(latitude_deg=-33.87, longitude_deg=151.21)
    assert resolve_lighting(at(12.0), plain, sydney).azimuth_deg == pytest.approx(0.0, abs=5.0)  # north
    cest = SiteConfig(utc_offset_h=2.0)  # 12:00 CEST is 10:00 UTC, two hours before solar noon near 0 E
    assert resolve_lighting(at(12.0), plain, cest).azimuth_deg == pytest.approx(
        resolve_lighting(at(10.0, utc_offset_h=0.0), plain, HOME).azimuth_deg, abs=1e-9
    )
    assert resolve_lighting(at(12.0), plain, cest).azimuth_deg < 150.0
    own = at(12.0, latitude_deg=0.0, longitude_deg=0.0, utc_offset_h=0.0)
    assert resolve_lighting(own, plain, sydney) == resolve_lighting(own, plain, cest)


def test_default_light_is_the_historical_one() -> None:
    """Every light field null: the scene's fixed sun with the historical constants, lighting the ground as
    the historical shader did (albedo x (sky ambient + sun x cos)), and the historical zenith colour; a
    computed sun placed where the fixed one is renders the same picture."""
    sc = scene([ground(), pole()])
    default = resolve_lighting(LightConfig(), sc)
    assert default == historical_lighting(sc)
    assert (default.sun_color, default.ambient_ground, default.ambient_sky) == (SUN_COLOR, AMBIENT_GROUND,
                                                                                 AMBIENT_SKY)  # fmt: skip
    assert default.zenith == (0.53, 0.72, 0.92) and default.fog_beta == 0.0
    sun = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
    np.testing.assert_array_equal(default.sun, sun)

    look = CameraConfig(name="look", width=160, height=120, position=(0, 0, 0), rpy_deg=(0, 35, 0))
    T_wb = pose(-6.0, -1.0, 3.0, yaw=0.2)
    rgb, depth, seg, _ = render(sc, look, T_wb)
    expected = 100 / 255 * (AMBIENT_SKY[0] + SUN_COLOR[0] * sun[2]) * 255  # flat ground facing up, in sun
    ground_px = rgb[..., 0][seg == SemanticClass.GROUND]
    assert np.median(ground_px) == pytest.approx(expected, abs=1.0)
    up = CameraConfig(name="up", width=33, height=33, position=(0, 0, 0), rpy_deg=(0, -90, 0))
    sky, _, _, _ = render(sc, up, pose(0.0, 0.0, 5.0))
    np.testing.assert_allclose(sky[16, 16], np.array([0.53, 0.72, 0.92]) * 255, atol=1.0)

    # 10:16:49 UTC at 6.35 N, 0 E on midsummer day: the sun within 0.001 deg of the fixed one
    same_sun = LightConfig(
        time_of_day_h=10.2804, date="2026-06-21", latitude_deg=6.35, longitude_deg=0.0, utc_offset_h=0.0
    )
    computed = resolve_lighting(same_sun, sc)
    assert abs(computed.elevation_deg - REFERENCE_ELEVATION_DEG) < 0.01
    rgb2, depth2, seg2, _ = render(sc, look, T_wb, computed)
    np.testing.assert_array_equal(seg2, seg)
    np.testing.assert_array_equal(depth2, depth)
    assert np.abs(rgb2 - rgb).max() <= 2 and (rgb2 != rgb).mean() < 0.01


# ----------------------------------------------------------------------------------------- shadows
def shadow_direction(sc: Scene, light: LightConfig) -> tuple[np.ndarray, np.ndarray]:
    """The horizontal direction from the pole to its shadow's centroid, seen from straight above, and the
    sun's horizontal direction."""
    lighting = resolve_lighting(light, sc, HOME)
    rgb, depth, seg, T_wo = render(sc, DOWN, pose(0.0, 0.0, 14.0), lighting)
    lum = rgb.mean(axis=-1)
    lit = np.median(lum[seg == SemanticClass.GROUND])
    dark = (seg == SemanticClass.GROUND) & (lum < 0.8 * lit)
    assert dark.sum() > 20, "no shadow on the ground"
    centroid = world_points(DOWN, depth, T_wo)[dark].mean(axis=0)
    sun = np.asarray(lighting.sun)
    return centroid[:2] / np.linalg.norm(centroid[:2]), sun[:2] / np.linalg.norm(sun[:2])


def test_shadows_move_with_the_sun() -> None:
    """A pole's shadow points away from the sun and swings from west-north-west in the morning to
    east-north-east in the afternoon, as the sun's azimuth does."""
    sc = scene([ground(), pole()])
    directions = {}
    for hours in (8.0, 16.0):
        shadow, sun = shadow_direction(sc, at(hours))
        angle = math.degrees(math.acos(np.clip(np.dot(shadow, -sun), -1, 1)))
        assert angle < 10, f"{hours}: the shadow points {angle:.1f} deg off the anti-solar direction"
        directions[hours] = shadow
    assert directions[8.0][0] < -0.5 and directions[16.0][0] > 0.5, directions  # west, then east
    swing = math.degrees(math.acos(np.dot(directions[8.0], directions[16.0])))
    assert swing > 90, swing


def test_overcast_collapses_the_shadow_contrast() -> None:
    """At full cloud cover shadowed and lit ground look the same (no hard shadows), and the sky is grey."""
    sc = scene([ground(), pole(radius=0.5)])
    contrasts, skies = [], []
    shadow_mask = None
    for cover in (0.0, 0.5, 1.0):
        lighting = resolve_lighting(at(12.0, cloud_cover=cover), sc, HOME)
        rgb, _, seg, _ = render(sc, DOWN, pose(0.0, 0.0, 14.0), lighting)
        lum = rgb.mean(axis=-1)
        grd = seg == SemanticClass.GROUND
        if shadow_mask is None:  # the shadow where the clear sky puts it
            shadow_mask = grd & (lum < 0.8 * np.median(lum[grd]))
            assert shadow_mask.sum() > 20
        lit = np.median(lum[grd & ~shadow_mask])
        contrasts.append((lit - lum[shadow_mask].mean()) / lit)
        skies.append(np.ptp(np.array(lighting.zenith)))
    assert contrasts[0] > 0.3 and contrasts[0] > contrasts[1] > contrasts[2], contrasts
    assert contrasts[2] < 0.02, contrasts
    assert skies[2] < 0.1 < skies[0], skies  # a grey sky under full cover


# ----------------------------------------------------------------------------------------- haze
def test_haze_follows_koschmieder() -> None:
    """A dark wall fades to the haze colour as exp(-3.912 d / V) at two distances; the sky at the horizon
    is the haze colour; depth and segmentation are the same with and without haze."""
    walls = [
        quad([[20, 3, 0], [20, 0.5, 0], [20, 0.5, 4], [20, 3, 4]], SemanticClass.ROCK, "dark"),
        quad([[60, -1, 0], [60, -9, 0], [60, -9, 8], [60, -1, 8]], SemanticClass.POST, "dark"),
    ]
    sc = scene(walls)
    cam = CameraConfig(name="front", width=160, height=120, hfov_deg=60.0, position=(0, 0, 0))
    T_wb = pose(0.0, 0.0, 2.0)
    visibility = 150.0
    hazy = resolve_lighting(at(12.0, visibility_m=visibility), sc, HOME)
    assert hazy.fog_beta == pytest.approx(KOSCHMIEDER / visibility)
    clear = dataclasses.replace(hazy, fog_beta=0.0)  # the same sun and ambient, no haze
    rgb_fog, depth_fog, seg_fog, T_wo = render(sc, cam, T_wb, hazy)
    rgb, depth, seg, _ = render(sc, cam, T_wb, clear)
    np.testing.assert_array_equal(depth_fog, depth)
    np.testing.assert_array_equal(seg_fog, seg)
    fog = np.array(hazy.fog_color) * 255
    distance = np.linalg.norm(world_points(cam, depth, T_wo) - T_wo[:3, 3], axis=-1)
    for cls, d_nominal in ((SemanticClass.ROCK, 20.0), (SemanticClass.POST, 60.0)):
        mask = seg == cls
        assert mask.sum() > 30
        d = distance[mask]
        want = np.exp(-hazy.fog_beta * d)
        got = (rgb_fog[mask] - fog) / (rgb[mask] - fog)  # per channel: the wall's share left
        assert np.abs(got - want[:, None]).max() < 0.02, (d_nominal, got.mean(), want.mean())
        assert abs(want.mean() - math.exp(-KOSCHMIEDER * d_nominal / visibility)) < 0.03
    horizon_row = rgb_fog[cam.height // 2 - 1, 5:25]  # sky just above the horizon, left of the walls
    assert (seg_fog[cam.height // 2 - 1, 5:25] == SemanticClass.SKY).all()
    np.testing.assert_allclose(horizon_row, np.broadcast_to(fog, horizon_row.shape), atol=2.0)


def test_scene_light_is_the_default_the_config_overrides() -> None:
    """A scene's own light (e.g. a morning) applies to the fields the config leaves null."""
    morning = scene([ground()], light={"time_of_day_h": 8.0, "cloud_cover": 0.25})
    by_scene = resolve_lighting(LightConfig(), morning, HOME)
    plain = scene([ground()])
    assert by_scene.azimuth_deg == pytest.approx(resolve_lighting(at(8.0), plain, HOME).azimuth_deg, abs=1.0)
    noon = resolve_lighting(LightConfig(time_of_day_h=12.0), morning, HOME)
    assert abs(noon.azimuth_deg - 180.0) < 3.0
    clear_noon = resolve_lighting(LightConfig(time_of_day_h=12.0), plain, HOME)
    assert noon.sun_color[0] < clear_noon.sun_color[0]  # the scene's clouds stay
    with pytest.raises(ValueError, match="cloud_cover"):
        resolve_lighting(LightConfig(), scene([ground()], light={"cloud_cover": 2.0}))


# ----------------------------------------------------------------------------------------- bad values
@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"time_of_day_h": 24.0}, r"time_of_day_h must lie in \[0, 24\)"),
        ({"cloud_cover": 1.5}, r"cloud_cover must lie in \[0, 1\]"),
        ({"visibility_m": 0.0}, "visibility_m must be a positive number"),
        ({"date": "2026-02-30"}, "date must be an ISO day"),
        ({"latitude_deg": 91.0}, r"latitude_deg must lie in \[-90, 90\]"),
        ({"utc_offset_h": float("nan")}, "utc_offset_h must be a finite number"),
    ],
)
def test_bad_light_values_are_refused(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LightConfig(**fields)


def test_bad_light_through_config_and_api_keeps_the_simulator_running() -> None:
    with pytest.raises(ValueError, match="cloud_cover"):
        load_config(overrides=["light.cloud_cover=2"])
    with pytest.raises(ConfigError, match="light.bogus"):
        load_config(overrides=["light.bogus=1"])
    assert load_config(overrides=["light.time_of_day_h=8", "light.date=2026-03-20"]).light == LightConfig(
        time_of_day_h=8.0, date="2026-03-20"
    )
    from droneulator.world.world import World

    world = World(load_config(scene="default"), render=False)
    for fields, code, words in (
        ({"cloud_cover": 3}, "invalid_argument", "light.cloud_cover must lie in [0, 1]"),
        ({"time_of_day_h": -1}, "invalid_argument", "light.time_of_day_h must lie in [0, 24)"),
        ({"date": "21/06/2026"}, "invalid_argument", "light.date must be an ISO day"),
    ):
        reply = execute(world, make_request("reset", {"light": fields}, 7))
        assert not reply["ok"] and reply["error"]["code"] == code and words in reply["error"]["message"], (
            reply
        )
    for light, words in (({"bogus": 1}, "unknown `light` field(s) bogus"), ([1], "must be an object"),
                         ({"visibility_m": "far"}, "`light.visibility_m` must be a number")):  # fmt: skip
        with pytest.raises(RequestError, match=words.replace("(", r"\(").replace(")", r"\)")):
            make_request("reset", {"light": light}, 8)
    assert world.config.light == LightConfig()  # nothing changed
    reply = execute(world, make_request("reset", {"light": {"time_of_day_h": 9.5, "visibility_m": 500}}, 9))
    assert reply["ok"] and reply["result"]["light"]["time_of_day_h"] == 9.5, reply
    reply = execute(world, make_request("reset", {"light": {"visibility_m": None}}, 10))
    assert (
        reply["result"]["light"]["visibility_m"] is None and reply["result"]["light"]["time_of_day_h"] == 9.5
    )
    world.step(10)
    assert execute(world, make_request("scene_info", {}, 11))["result"]["light"]["time_of_day_h"] == 9.5


def test_world_reset_relights_the_rendered_world() -> None:
    """``reset`` with a light changes the world's RGB (here haze) and nothing else, without a new scene."""
    from droneulator.world.world import World

    cfg = load_config(scene="default")
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120)]
    cfg.render.shadow_map_size = 512
    world = World(cfg)
    try:
        before = world.render().cameras["uav0"]["front"]
        before = (before.rgb.astype(int), before.depth.copy(), before.seg.copy())
        scene_obj = world.scene
        reply = execute(world, make_request("reset", {"light": {"visibility_m": 30.0}}, 1))
        assert reply["ok"], reply
        assert world.scene is scene_obj and world.cameras.renderer.lighting.fog
        after = world.render().cameras["uav0"]["front"]
        np.testing.assert_array_equal(after.depth, before[1])
        np.testing.assert_array_equal(after.seg, before[2])
        # beyond 20 m (and the sky) everything is the haze's colour, which it was not before
        far = ~(before[1] < 20.0)
        fog = np.array(world.cameras.renderer.lighting.fog_color) * 255
        assert np.abs(after.rgb[far] - fog).max() < 4.0
        assert (np.abs(before[0][far] - fog).max(axis=-1) > 10.0).mean() > 0.9
    finally:
        world.close()


# ----------------------------------------------------------------------------------------- the UI
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


#: colourfulness of a camera view's <canvas>: mean of max(r, g, b) - min(r, g, b) (haze greys the picture),
#: and mean brightness
CHROMA = """(c) => {
  const t = document.createElement("canvas");
  t.width = c.width; t.height = c.height;
  const g = t.getContext("2d"); g.drawImage(c, 0, 0);
  const px = g.getImageData(0, 0, t.width, t.height).data;
  let chroma = 0, mean = 0;
  for (let i = 0; i < px.length; i += 4) {
    chroma += Math.max(px[i], px[i + 1], px[i + 2]) - Math.min(px[i], px[i + 1], px[i + 2]);
    mean += (px[i] + px[i + 1] + px[i + 2]) / 3;
  }
  const n = px.length / 4;
  return n ? {chroma: chroma / n, mean: mean / n} : null;
}"""


def render_server(run_pid: int) -> int:
    """The pid of the render server among a run's child processes."""
    out = subprocess.run(["ps", "-o", "pid=,args=", "--ppid", str(run_pid)], capture_output=True, text=True)
    pids = [int(line.split(None, 1)[0]) for line in out.stdout.splitlines() if "render_server" in line]
    assert len(pids) == 1, out.stdout
    return pids[0]


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (scripts/setup.sh --dev)")
def test_level_select_light_options_change_the_view() -> None:
    """In Chromium: load the default scene, then again with dense fog picked in the level select: the RGB
    view turns grey and lighter, the API and the telemetry report the light, a restarted render server
    draws the new light, and a bad light from a client is refused in words while the run keeps going."""
    playwright = pytest.importorskip("playwright.sync_api")
    from droneulator.api.client import ApiError
    from droneulator.runtime.launch import free_port, launch_run

    cfg = load_config(scene="default")
    cam = CameraConfig(
        name="front", width=160, height=120, position=(0.12, 0.0, 1.0), rpy_deg=(0.0, 15.0, 0.0)
    )
    cfg.render.cameras = [cam]
    cfg.render.shadow_map_size = 512
    ui_port = free_port()
    run = launch_run(cfg, ["--realtime", "--ui-port", str(ui_port)], start_timeout=120)
    pw = playwright.sync_playwright().start()
    try:
        client = run.client()
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1300, "height": 900})
        page.goto(f"http://127.0.0.1:{ui_port}/")
        page.wait_for_selector(".card[data-scene=default]", timeout=60000)
        canvas = 'figure.camera.rgb[data-cam="front"] > canvas'

        def view(condition: str) -> dict:
            """The view's stats once ``condition`` (JavaScript on ``s``, the stats) holds."""
            handle = page.wait_for_function(
                f"(() => {{ const c = document.querySelector('{canvas}'); if (!c || !c.width) return null;"
                f" const s = ({CHROMA})(c); return s && s.mean > 0 && ({condition}) ? s : null; }})()",
                timeout=60000,
            )
            return handle.json_value()

        page.click(".card[data-scene=default]")
        page.wait_for_selector("#fly:not([hidden])", timeout=120000)
        clear = view("true")
        assert clear["chroma"] > 30, clear  # blue sky, green grass
        page.click("#nav-levels")
        page.select_option("#light-haze", "60")
        page.select_option("#light-time", "12")
        page.click(".card[data-scene=default]")
        page.wait_for_selector("#fly:not([hidden])", timeout=120000)
        light = client.scene_info()["light"]
        assert light["visibility_m"] == 60.0 and light["time_of_day_h"] == 12.0, light
        foggy = view(f"s.chroma < {0.6 * clear['chroma']}")
        assert foggy["mean"] > clear["mean"], (clear, foggy)
        page.wait_for_selector("#telemetry dd:has-text('12:00, visibility 60 m')", timeout=10000)

        # a render server restarted now starts from the run's config: the hub hands it the new light
        shown = page.evaluate("window.droneulatorUI.cameras.count")
        os.kill(render_server(run.pid), signal.SIGKILL)
        page.wait_for_function(f"window.droneulatorUI.cameras.count > {shown + 5}", timeout=90000)
        assert view("true")["chroma"] < 0.6 * clear["chroma"]
        with pytest.raises(ApiError, match=r"light.cloud_cover must lie in \[0, 1\]"):
            client.reset(light={"cloud_cover": 3})
        assert client.scene_info()["light"]["visibility_m"] == 60.0
        client.state()  # still answering
        # a sparser canopy: the hub has both servers build the scene again, the views go on
        shown = page.evaluate("window.droneulatorUI.cameras.count")
        assert client.reset(vegetation=0.3)["vegetation"] == 0.3
        assert client.scene_info()["vegetation"] == 0.3 and client.scene_info()["light"]["visibility_m"] == 60
        page.wait_for_function(f"window.droneulatorUI.cameras.count > {shown + 5}", timeout=90000)
        browser.close()
    finally:
        pw.stop()
        run.stop()
