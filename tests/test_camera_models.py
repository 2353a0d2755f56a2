"""Camera realism models against the behaviour they model: depth noise laws measured on rendered planes,
stereo occlusion bands, thin-structure dropouts, ToF range loss, lens distortion undone with the published
camera_info, shot noise, auto-exposure, motion blur, seeding, config errors and the ideal default."""

from __future__ import annotations

import math
import threading
import time

import cv2
import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from test_render import body, cylinder, quad, scene

from droneulator.config import CameraConfig, load_config
from droneulator.config.camera_presets import AE_TARGET, DEPTH_PRESETS, REFERENCE_EXPOSURE_S, RGB_PRESETS
from droneulator.render import CameraFrame, Renderer
from droneulator.scenes.base import SemanticClass
from droneulator.sensors.camera_models import CameraModel, camera_rng, fleet_camera_models, is_ideal

TS = get_typestore(Stores.ROS2_JAZZY)
W, H = 320, 240
#: focal length (px) of a W-wide 90-degree camera
F = W / 2


def checker(size: int = 256, square: int = 8) -> np.ndarray:
    """An RGBA plaid: grey levels 30 + 90 (row band parity) + 90 (column band parity), so a horizontal
    blur leaves the vertical differences as they were, and the reverse."""
    i, j = np.mgrid[0:size, 0:size] // square
    tex = np.full((size, size, 4), 255, dtype=np.uint8)
    tex[..., :3] = (30 + 90 * (i % 2) + 90 * (j % 2))[..., None]
    return tex


def wall(x: float, cls: SemanticClass = SemanticClass.ROCK, y0: float = 50.0, texture: str = "white"):
    """A wall facing the camera (which looks along +x) at distance ``x``, spanning y in [-50, y0]."""
    return quad([[x, y0, -50], [x, -50, -50], [x, -50, 50], [x, y0, 50]], cls, texture)


def camera(**fields) -> CameraConfig:
    return CameraConfig(width=W, height=H, position=(0.0, 0.0, 0.0), **fields)


def plane_residual_std(depth: np.ndarray) -> float:
    """Std of the valid pixels about the least-squares plane z = a + b u + c v through them."""
    v, u = np.nonzero(np.isfinite(depth))
    A = np.stack([np.ones(len(u)), u, v], axis=1)
    z = depth[v, u].astype(np.float64)
    coef, *_ = np.linalg.lstsq(A, z, rcond=None)
    return float(np.std(z - A @ coef))


def neighbour_correlation(depth: np.ndarray) -> float:
    """Correlation of horizontally adjacent residuals (about the mean) over valid pairs."""
    r = depth - np.nanmean(depth)
    a, b = r[:, :-1].ravel(), r[:, 1:].ravel()
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def render_depth_at(cam: CameraConfig, distances: list[float]) -> dict[float, np.ndarray]:
    """Exact depth of a fronto-parallel wall at each distance (the camera backs away from a wall at x = 1)."""
    out = {}
    with Renderer(scene([wall(1.0)]), [cam], shadow_map_size=256) as r:
        for d in distances:
            out[d] = r.render(body(1.0 - d, 0, 2), rgb=False)[cam.name].depth.copy()
    return out


def test_d435_depth_noise_grows_with_the_square_of_depth_and_is_invalid_beyond_range() -> None:
    cam = camera(depth_model="d435")
    model = CameraModel(cam, camera_rng(0))
    p = DEPTH_PRESETS["d435"]
    assert math.isclose(model.K[0, 0], F)
    exact = render_depth_at(cam, [1, 2, 4, 6, 8, 10, 12])
    for d in (1, 2, 4, 6, 8, 10):
        np.testing.assert_allclose(exact[d], d, rtol=1e-5)
        measured = model.apply_depth(exact[d])
        valid = np.isfinite(measured)
        # only the left border strip the right imager cannot see (f B / z px wide) is lost
        assert valid.mean() > 1 - (F * p.baseline_m / d + 1) / W
        predicted = d**2 * p.subpixel / (F * p.baseline_m)  # Intel's depth RMS error formula
        assert plane_residual_std(measured) == pytest.approx(predicted, rel=0.15), d
        # smoothed like stereo matching's window, not white per pixel
        assert neighbour_correlation(measured) > 0.5
    assert np.isnan(model.apply_depth(exact[12])).all()  # beyond the 10 m range: no return


def test_d435_invalid_band_left_of_a_near_edge_has_the_stereo_occlusion_width() -> None:
    cam = camera(depth_model="d435")
    near, far = 2.0, 5.0
    # the near wall covers y < 0: the right half of the image, its left edge on the centre column
    parts = [wall(near, y0=0.0), wall(far, SemanticClass.GROUND)]
    with Renderer(scene(parts), [cam], shadow_map_size=256) as r:
        exact = r.render(body(0, 0, 2), rgb=False)[cam.name].depth.copy()
    edge = int(np.argmax(exact[H // 2] < 3.0))  # first column of the near wall
    assert abs(edge - W / 2) <= 1
    measured = CameraModel(cam, camera_rng(1)).apply_depth(exact)
    width = F * DEPTH_PRESETS["d435"].baseline_m * (1 / near - 1 / far)  # 2.4 px
    band = np.isnan(measured[:, edge - math.floor(width) : edge])
    assert band.all()  # every row loses the band
    beyond = np.isnan(measured[:, edge - math.ceil(width) - 6 : edge - math.ceil(width) - 1])
    assert beyond.mean() < 0.05  # the far wall further left is seen
    assert np.isnan(measured[:, edge + 2 : edge + 8]).mean() < 0.05  # no band on the near side
    # invalid pixels per row left of the edge (the border strip excluded): the band's width, rounded
    per_row = np.isnan(measured[:, 20:edge]).sum(axis=1)
    assert np.median(per_row) in (math.floor(width), math.ceil(width))


def test_d435_thin_structures_drop_out_far_more_than_wide_ones() -> None:
    cam = camera(depth_model="d435")
    wires = [cylinder((3.0, y), 0.006, 4.0, SemanticClass.WIRE) for y in (-1.6, -1.2, -0.8, 0.8, 1.2, 1.6)]
    post = cylinder((3.0, 0.0), 0.25, 4.0, SemanticClass.POST)
    with Renderer(scene([*wires, post, wall(6.0, SemanticClass.GROUND)]), [cam], shadow_map_size=256) as r:
        f = r.render(body(0, 0, 1.0), rgb=False)[cam.name]
        exact, seg = f.depth.copy(), f.seg.copy()
    measured = CameraModel(cam, camera_rng(2)).apply_depth(exact)
    thin = seg == SemanticClass.WIRE
    wide = seg == SemanticClass.POST
    wide_inside = cv2.erode(wide.astype(np.uint8), np.ones((1, 7), np.uint8)).astype(bool)
    assert thin.sum() > 300 and wide_inside.sum() > 3000
    thin_lost = np.isnan(measured[thin]).mean()
    assert thin_lost > 0.5  # the preset drops 70 % of thin stretches
    assert np.isnan(measured[wide_inside]).mean() < 0.02
    # ideal depth keeps every wire pixel
    assert np.isfinite(exact[thin]).all()


def test_tof_noise_is_linear_in_depth_and_returns_fade_with_range_and_incidence() -> None:
    cam = camera(depth_model="tof")
    model = CameraModel(cam, camera_rng(3))
    p = DEPTH_PRESETS["tof"]
    exact = render_depth_at(cam, [1, 2, 3, 4, 5, 6])
    for d in (1, 2, 3, 4, 5):
        measured = model.apply_depth(exact[d])
        # off-axis rays meet the wall obliquely: at 5 m only the middle of the image keeps its return
        centre = np.s_[H // 2 - 20 : H // 2 + 20, W // 2 - 20 : W // 2 + 20]
        assert np.isfinite(measured[centre]).all()
        assert np.isfinite(measured).mean() > (0.99 if d <= 4 else 0.2)
        predicted = p.noise_floor_m + p.noise_slope * d
        assert plane_residual_std(measured) == pytest.approx(predicted, rel=0.15), d
        assert abs(neighbour_correlation(measured)) < 0.1  # per-pixel, white
    assert np.isnan(model.apply_depth(exact[6])).all()  # beyond 5.46 m
    # the ground at grazing incidence is lost well inside the range a facing wall keeps
    ground = quad([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], SemanticClass.GROUND)
    with Renderer(scene([ground]), [cam], shadow_map_size=256) as r:
        flat = r.render(body(0, 0, 1.0), rgb=False)[cam.name].depth.copy()
    measured = model.apply_depth(flat)
    assert np.isnan(measured[(flat > 3.5) & (flat < 5.0)]).mean() > 0.95
    assert np.isfinite(measured[(flat > 1.0) & (flat < 1.5)]).mean() > 0.95


def frame_of(rgb: np.ndarray, depth_m: float = 3.0) -> CameraFrame:
    h, w = rgb.shape[:2]
    K = np.array([[w / 2, 0, (w - 1) / 2], [0, w / 2, (h - 1) / 2], [0, 0, 1.0]])
    depth = np.full((h, w), depth_m, np.float32)
    return CameraFrame("front", rgb, depth, np.ones((h, w), np.uint8), K, np.eye(4))


def test_rgb_shot_noise_variance_grows_with_signal_as_the_photon_transfer_curve() -> None:
    sensor = RGB_PRESETS["small_pixel"]
    model = CameraModel(camera(rgb_noise="small_pixel"), camera_rng(4))
    gain = 255.0 / sensor.full_well_e  # DN per electron
    means, variances = [], []
    for level in (20, 60, 120, 200):
        out = model.apply(frame_of(np.full((H, W, 3), level, np.uint8))).rgb.astype(np.float64)
        assert out.mean() == pytest.approx(level, abs=0.3)
        expected = gain**2 * (level / 255 * sensor.full_well_e + sensor.read_noise_e**2) + 1 / 12
        assert out.var() == pytest.approx(expected, rel=0.1), level
        means.append(out.mean())
        variances.append(out.var())
    slope = np.polyfit(means, variances, 1)[0]
    assert slope == pytest.approx(gain, rel=0.1)  # variance / mean = DN per electron: shot noise


def test_auto_exposure_brings_a_dark_image_to_the_target_and_fixed_exposure_does_not() -> None:
    rng = np.random.default_rng(5)
    dark = (checker(W)[:H, :W, :3] // 16 + rng.integers(0, 3, (H, W, 3))).astype(np.uint8)
    assert dark.mean() < 12
    fixed = CameraModel(camera(rgb_noise="machine_vision"), camera_rng(5))
    assert fixed.apply(frame_of(dark)).rgb.mean() == pytest.approx(dark.mean(), abs=0.5)
    auto = CameraModel(camera(rgb_noise="machine_vision", auto_exposure=True, exposure_s=0.05), camera_rng(5))
    bright = auto.apply(frame_of(dark)).rgb
    assert bright.mean() == pytest.approx(AE_TARGET * 255, rel=0.05)
    # the longest exposure caps it: 4 ms and 16x gain cannot lift a 500x darker image to the target
    capped = CameraModel(
        camera(rgb_noise="machine_vision", auto_exposure=True, exposure_s=0.004), camera_rng(5)
    )
    very_dark = (dark // 8).astype(np.uint8)
    assert capped.apply(frame_of(very_dark)).rgb.mean() < 0.5 * AE_TARGET * 255


def gradients(img: np.ndarray) -> tuple[float, float]:
    """Mean squared horizontal and vertical differences over the image's middle half (blur spreads an
    edge's step over several pixels, lowering the squares' sum; the absolute differences' sum would stay)."""
    h, w = img.shape[:2]
    g = img.astype(np.float64).mean(axis=2)[h // 4 : -h // 4, w // 4 : -w // 4]
    return float(np.square(np.diff(g, axis=1)).mean()), float(np.square(np.diff(g, axis=0)).mean())


def test_motion_blur_follows_a_yaw_horizontally_and_leaves_a_still_vehicle_sharp() -> None:
    base = camera()
    # 8 m square at 3 m: 32 checker squares of 0.25 m, 13 px each
    board = quad([[3, 4, -2], [3, -4, -2], [3, -4, 6], [3, 4, 6]], SemanticClass.ROCK, "checker")
    textured = scene([board], {"checker": checker()})
    with Renderer(textured, [base], shadow_map_size=256) as r:
        f = r.render(body(0, 0, 2), rgb=True)[base.name]
        sharp = CameraFrame(f.name, f.rgb // 8, f.depth.copy(), f.seg.copy(), f.K, f.T_world_optical)
    # a dim scene at an 8x longer exposure: as bright as the render, with blur over 16 ms
    exposure = 8 * REFERENCE_EXPOSURE_S
    blurred = CameraModel(camera(exposure_s=exposure, motion_blur=True), camera_rng(6))
    plain = CameraModel(camera(exposure_s=exposure), camera_rng(6))
    still = blurred.apply(sharp, np.zeros(3), np.zeros(3)).rgb
    np.testing.assert_array_equal(still, plain.apply(sharp).rgb)
    gx0, gy0 = gradients(still)
    yawing = blurred.apply(sharp, np.zeros(3), np.array([0.0, 0.0, 2.0])).rgb  # 2 rad/s about body z
    gx, gy = gradients(yawing)
    # 2 rad/s * 16 ms * 160 px = 5 px of horizontal smear over 13 px checker squares
    assert gx < 0.5 * gx0
    assert gy > 0.85 * gy0
    # flying forward at 5 m/s blurs radially: the centre stays sharp, the sides smear
    forward = blurred.apply(sharp, np.array([5.0, 0.0, 0.0]), np.zeros(3)).rgb
    centre = np.s_[H // 2 - 20 : H // 2 + 20, W // 2 - 20 : W // 2 + 20]
    np.testing.assert_allclose(forward[centre].astype(float), still[centre].astype(float), atol=8)
    assert gradients(forward)[0] < 0.9 * gx0


class _Listener:
    """A plain Zenoh client session recording the last payload of every key (decoding is rosbags')."""

    def __init__(self, endpoint: str) -> None:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
        self.session = zenoh.open(cfg)
        self.got: dict[str, bytes] = {}
        self.lock = threading.Lock()
        self.sub = self.session.declare_subscriber("**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.got[str(sample.key_expr)] = sample.payload.to_bytes()

    def wait(self, suffixes: list[str], timeout: float = 10.0) -> dict[str, bytes]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                found = {s: v for s in suffixes for k, v in self.got.items() if k.endswith(s)}
            if len(found) == len(suffixes):
                return found
            time.sleep(0.05)
        raise TimeoutError(f"no {suffixes} among {sorted(self.got)}")

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def test_distorted_images_undistort_to_the_render_with_the_published_camera_info() -> None:
    from droneulator.ros.publishers import FramePublisher
    from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig
    from droneulator.runtime.launch import free_port
    from droneulator.world import World

    D = (-0.28, 0.09, 0.0012, -0.0008, -0.012)
    cfg = load_config(scene="default")
    cfg.render.shadows = False
    cfg.render.cameras = [
        CameraConfig("front", 320, 240, 80.0, rpy_deg=(0.0, 20.0, 0.0), distortion=D),
        CameraConfig("plain", 160, 120, 80.0, rpy_deg=(0.0, 20.0, 0.0)),
    ]
    ep = f"tcp/127.0.0.1:{free_port()}"
    node = RosZenohNode(ZenohNodeConfig(mode="router", listen=(ep,), connect=()))
    listener = _Listener(ep)
    try:
        frames = FramePublisher(node, cfg, zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)  # declarations reach the subscriber
        with World(cfg) as world:
            world.reset(position=world.scene.spawn_position + [0.0, 0.0, 2.5])
            assert set(world.cameras.models["uav0"]) == {"front"}  # the ideal camera gets no model
            shot = world.render()
            poses = {name: st.T_world_body for name, st in shot.states.items()}
            drawn = world.cameras.renderer.render_rigs(poses)["uav0"]
            ideal = {c: (f.rgb.copy(), f.depth.copy(), f.seg.copy()) for c, f in drawn.items()}
            frames.publish(shot.states, shot.cameras)
        keys = ["front/color/camera_info", "front/color/image_raw/compressed", "plain/depth/camera_info"]
        got = listener.wait(keys)
    finally:
        listener.close()
        node.close()
    info = TS.deserialize_cdr(got["front/color/camera_info"], "sensor_msgs/msg/CameraInfo")
    assert info.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(info.d, D)
    plain_info = TS.deserialize_cdr(got["plain/depth/camera_info"], "sensor_msgs/msg/CameraInfo")
    np.testing.assert_array_equal(plain_info.d, np.zeros(5))
    K, Dp = info.k.reshape(3, 3), info.d
    jpeg = TS.deserialize_cdr(got["front/color/image_raw/compressed"], "sensor_msgs/msg/CompressedImage")
    published = cv2.cvtColor(cv2.imdecode(jpeg.data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    front = shot.cameras["uav0"]["front"]
    ideal_rgb, ideal_depth, ideal_seg = ideal["front"]
    inner = np.s_[30:-30, 40:-40]  # away from the border, where the distorted image has no data
    for distorted, tol in ((front.rgb, 3.0), (published, 4.0)):
        restored = cv2.undistort(distorted, K, Dp)
        err = np.abs(restored.astype(float) - ideal_rgb.astype(float))[inner].mean()
        unrestored = np.abs(distorted.astype(float) - ideal_rgb.astype(float))[inner].mean()
        assert err < tol and unrestored > 2.5 * err
    # depth and segmentation are distorted alike (nearest): rectified with the same maps they register
    m1, m2 = cv2.initUndistortRectifyMap(K, Dp, None, K, (320, 240), cv2.CV_32FC1)
    seg_back = cv2.remap(front.seg, m1, m2, cv2.INTER_NEAREST)
    assert (seg_back[inner] == ideal_seg[inner]).mean() > 0.97
    depth_back = cv2.remap(front.depth, m1, m2, cv2.INTER_NEAREST)
    close = np.isclose(depth_back[inner], ideal_depth[inner], rtol=0.02) | (
        np.isnan(depth_back[inner]) & np.isnan(ideal_depth[inner])
    )
    assert close.mean() > 0.97
    # the ideal camera's images are the renderer's, bit for bit
    plain = shot.cameras["uav0"]["plain"]
    for got_image, want in zip((plain.rgb, plain.depth, plain.seg), ideal["plain"], strict=True):
        np.testing.assert_array_equal(got_image, want)
    assert plain.D is None and front.D is not None


def test_lens_inversion_and_remap_match_opencv() -> None:
    """The lens module's plain numpy / numba functions (the base install has no OpenCV) against OpenCV's
    undistortPoints and remap, the implementations ROS consumers rectify with."""
    from droneulator.sensors.lens import remap, undistort_points

    K = np.array([[300.0, 0, 161.5], [0, 302.0, 118.0], [0, 0, 1]])
    D = np.array([-0.28, 0.09, 0.001, -0.0008, 0.01])
    rng = np.random.default_rng(3)
    uv = rng.uniform([-10, -10], [330, 250], size=(500, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    want = cv2.undistortPoints(uv[:, None, :], K, D, P=K, criteria=criteria).reshape(-1, 2)
    np.testing.assert_allclose(undistort_points(uv, K, D), want, atol=1e-6)
    # remap: a smooth colour image, float depth with NaN fill, class ids nearest, an edge-replicating blur
    image = rng.integers(0, 256, size=(60, 80, 3), dtype=np.uint8)
    mu = rng.uniform(-3, 83, size=(50, 70)).astype(np.float32)
    mv = rng.uniform(-3, 63, size=(50, 70)).astype(np.float32)
    for replicate, border in ((False, cv2.BORDER_CONSTANT), (True, cv2.BORDER_REPLICATE)):
        ours = remap(image, mu, mv, replicate=replicate).astype(float)
        theirs = cv2.remap(image, mu, mv, cv2.INTER_LINEAR, borderMode=border).astype(float)
        # OpenCV's bilinear weights are quantised to 1/32 px: within 1/32 of the pixels' span, plus rounding
        span = 255 / 32 + 1
        assert np.abs(ours - theirs).max() <= span and np.abs(ours - theirs).mean() < 1.0
    depth = rng.uniform(1, 10, size=(60, 80)).astype(np.float32)
    ours = remap(depth, mu, mv, nearest=True, fill=float("nan"))
    theirs = cv2.remap(depth, mu, mv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    same = (ours == theirs) | (np.isnan(ours) & np.isnan(theirs))
    assert same.mean() > 0.999  # but for a sample exactly half-way between two pixels
    ours = remap(depth, mu, mv, replicate=True)
    theirs = cv2.remap(depth, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(ours, theirs, atol=9 / 32 + 1e-4)


def test_models_are_seeded_and_apply_to_batches() -> None:
    cam = camera(depth_model="d435", rgb_noise="machine_vision")
    exact = render_depth_at(cam, [3.0])[3.0]
    a = CameraModel(cam, camera_rng(7)).apply_depth(exact)
    b = CameraModel(cam, camera_rng(7)).apply_depth(exact)
    c = CameraModel(cam, camera_rng(8)).apply_depth(exact)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.nan_to_num(a), np.nan_to_num(c))
    rgb = np.full((H, W, 3), 100, np.uint8)
    x = CameraModel(cam, camera_rng(7)).apply(frame_of(rgb)).rgb
    y = CameraModel(cam, camera_rng(7)).apply(frame_of(rgb)).rgb
    np.testing.assert_array_equal(x, y)
    # a (B, H, W) batch: each image gets its own noise, with the same statistics
    batch = CameraModel(cam, camera_rng(9)).apply_depth(np.stack([exact] * 3))
    assert batch.shape == (3, H, W) and not np.array_equal(np.nan_to_num(batch[0]), np.nan_to_num(batch[1]))
    for img in batch:
        assert plane_residual_std(img) == pytest.approx(plane_residual_std(a), rel=0.15)
    # every vehicle's camera has its own stream; the same config builds the same streams
    cfg = load_config(None, ['render.cameras=[{"depth_model": "d435"}]', 'vehicles=[{}, {"name": "uav1"}]'])
    m1, m2 = fleet_camera_models(cfg), fleet_camera_models(cfg)
    assert set(m1) == {"uav0", "uav1"}
    draws = [m["front"].rng.random() for m in (m1["uav0"], m1["uav1"], m2["uav0"])]
    assert draws[0] != draws[1] and draws[0] == draws[2]


def test_ideal_defaults_build_no_model_and_leave_frames_untouched() -> None:
    cfg = load_config()
    assert all(is_ideal(c) for c in cfg.render.cameras)
    assert fleet_camera_models(cfg) == {}
    model = CameraModel(camera(), camera_rng(0))
    rgb = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    f = frame_of(rgb)
    out = model.apply(f)
    for a, b in ((out.rgb, f.rgb), (out.depth, f.depth), (out.seg, f.seg)):
        np.testing.assert_array_equal(a, b)
    assert out.D is None


def test_rl_vector_env_observes_through_the_depth_model() -> None:
    from droneulator.workflows.rl.env import env_config, runtime_overrides
    from droneulator.workflows.rl.vector import VineyardNavVectorEnv

    assert 'depth_model": "d435"' in runtime_overrides(env_config(depth_model="d435"))[0]
    assert "depth_model" not in runtime_overrides(env_config())[0]
    noisy = VineyardNavVectorEnv(num_envs=3, depth="raycast", depth_model="d435")
    ideal = VineyardNavVectorEnv(num_envs=3, depth="raycast")
    try:
        a, _ = noisy.reset(seed=11)
        b, _ = ideal.reset(seed=11)
    finally:
        noisy.close()
        ideal.close()
    np.testing.assert_array_equal(a[:, 32:], b[:, 32:])  # same tasks and states
    assert np.all((a[:, :32] >= 0) & (a[:, :32] <= 1))
    assert np.abs(a[:, :32] - b[:, :32]).max() > 0.01  # the strips see the noise


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ('render.cameras=[{"depth_model": "kinect"}]', "depth_model must be one of ideal, d435, tof"),
        ('render.cameras=[{"rgb_noise": "film"}]', "rgb_noise must be one of"),
        ('render.cameras=[{"exposure_s": -0.01}]', "exposure_s must lie in"),
        ('render.cameras=[{"exposure_s": 0}]', "exposure_s must lie in"),
        ('render.cameras=[{"distortion": [0.1, 0.0, 0.0, 0.0]}]', "expected 5 values"),
        ('render.cameras=[{"distortion": [-1.5, 0.0, 0.0, 0.0, 0.0]}]', "folds the image over"),
        ('render.cameras=[{"auto_exposure": "sometimes"}]', "not a boolean"),
        ("rl.depth_model=lidar", "rl.depth_model must be one of"),
        ('render.cameras=[{"depth_noise_scale": -1}]', r"depth_noise_scale must lie in \[0, 10\]"),
        ("randomize.depth_dropout_scale=[2, 1]", "randomize.depth_dropout_scale must be"),
    ],
)
def test_bad_camera_model_settings_are_clear_errors(override: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        load_config(None, [override])


def test_camera_model_settings_load_from_overrides() -> None:
    cfg = load_config(
        None,
        [
            'render.cameras=[{"depth_model": "tof", "rgb_noise": "small_pixel", '
            '"distortion": [-0.2, 0.05, 0, 0, 0], "exposure_s": 0.01, "auto_exposure": true, '
            '"motion_blur": true}]'
        ],
    )
    (cam,) = cfg.render.cameras
    assert (cam.depth_model, cam.rgb_noise, cam.exposure_s, cam.auto_exposure, cam.motion_blur) == (
        "tof",
        "small_pixel",
        0.01,
        True,
        True,
    )
    assert cam.distortion == (-0.2, 0.05, 0.0, 0.0, 0.0) and not is_ideal(cam)
