"""A world of many vehicles: one vehicle is the simulator as it was; several fly, see and hit each other,
and feel each other's wakes."""

from __future__ import annotations

import itertools
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from droneulator import frames
from droneulator.commands import CommandError
from droneulator.config import CameraConfig, VehicleSpec, fleet, load_config
from droneulator.scenes import get_scene
from droneulator.scenes.base import SemanticClass
from droneulator.scenes.collision import sdf_lookup_many
from droneulator.state import STATE
from droneulator.vehicles.mesh import vehicle_mesh
from droneulator.world import World
from droneulator.world.contact import contacts
from droneulator.world.downwash import RHO, SPREAD

sys.path.insert(0, str(Path(__file__).parent))
import golden  # noqa: E402

#: the golden rows' columns
GROUPS = {"x": slice(1, 4), "v": slice(4, 7), "q": slice(7, 11), "w": slice(11, 14), "rotors": slice(14, 18),
          "specific force": slice(18, 21), "wind": slice(21, 24)}  # fmt: skip


@pytest.mark.parametrize("name", list(golden.SCENARIOS))
def test_one_vehicle_world_flies_the_single_vehicle_simulators_flights(name: str) -> None:
    """Each recorded flight of the simulator before World (tests/golden.py), step by step, through
    today's one-vehicle World. The same equations, evaluated without BLAS in one compiled
    step: the recording's BLAS fused multiply-adds differ in the last bit, so states agree to rounding,
    not bit for bit. The one exception is a single step of the hummingbird mission where a rotor is
    commanded near zero thrust and the speed's square root magnifies a 4e-13 difference to 3e-6 rad/s;
    the trajectory stays within 5e-12 m. Events are the same, at the same instants."""
    ref = np.load(golden.GOLDEN)
    states, events = golden.fly(name)
    assert events == list(ref[f"{name}__events"])
    assert states.shape == ref[name].shape
    assert np.array_equal(states[:, 0], ref[name][:, 0])  # the clock, exactly
    tolerance = {"x": 1e-11, "v": 1e-10, "q": 1e-10, "w": 1e-8, "rotors": 1e-5, "specific force": 1e-8,
                 "wind": 0.0}  # fmt: skip
    for group, cols in GROUPS.items():
        err = float(np.abs(states[:, cols] - ref[name][:, cols]).max())
        assert err <= tolerance[group], f"{name}: {group} differs by {err:.3g}"


def world(scene: str = "default", n: int = 2, render: bool = False, **kw: object) -> World:
    cfg = load_config(scene=scene)
    cfg.vehicles = fleet(n)
    for spec, (key, value) in itertools.product(cfg.vehicles, kw.items()):
        setattr(spec, key, value)
    return World(cfg, render=render)


def test_two_vehicles_on_crossing_gotos_both_arrive() -> None:
    """Their paths cross, 1 m apart in height: the lower one passes through the upper one's wake."""
    w = world()
    a, b = w.vehicle("uav0"), w.vehicle("uav1")
    a.place([0.0, 0.0, 2.0], 0.0)
    b.place([4.0, 4.0, 3.0], 0.0)
    a.goto([4.0, 4.0, 2.0])
    b.goto([0.0, 0.0, 3.0])
    events = []
    assert w.run_until(lambda _: a.mode.value == b.mode.value == "hold", 30.0, events)
    arrived = {e.vehicle: e for e in events if e.type == "arrived"}
    assert set(arrived) == {"uav0", "uav1"} and not [e for e in events if e.type == "collision"]
    np.testing.assert_allclose(a.s[STATE.x], [4.0, 4.0, 2.0], atol=0.05)
    np.testing.assert_allclose(b.s[STATE.x], [0.0, 0.0, 3.0], atol=0.05)


def test_a_head_on_pair_raises_one_collision_naming_both_and_neither_passes_through() -> None:
    w = world()
    a, b = w.vehicle("uav0"), w.vehicle("uav1")
    a.place([0.0, 0.0, 2.0], 0.0)
    b.place([6.0, 0.0, 2.0], math.pi)
    a.goto([6.0, 0.0, 2.0], speed=2.0)
    b.goto([0.0, 0.0, 2.0], speed=2.0)
    events, gaps = [], []
    for _ in range(600):
        events += w.step().events
        gaps.append(b.s[0] - a.s[0])
    collisions = [e for e in events if e.type == "collision"]
    assert len(collisions) == 1, collisions
    (c,) = collisions
    assert sorted(c.data["vehicles"]) == ["uav0", "uav1"]
    assert a.mode.value == b.mode.value == "collided" and a.collisions == b.collisions == 1
    assert min(gaps) > 0.0  # b stayed ahead of a: no one passed through the other
    gap = float(np.linalg.norm(b.s[STATE.x] - a.s[STATE.x]))
    assert 0.5 - 0.05 < gap <= 0.5 + 0.05  # stopped where the 0.25 m bodies met (at most one period early)
    np.testing.assert_allclose(c.data["position"], 0.5 * (a.s[STATE.x] + b.s[STATE.x]), atol=1e-9)


def _ray_mesh_depth(origin: np.ndarray, direction: np.ndarray, tris: np.ndarray) -> float:
    """Nearest hit of a ray on triangles (Moller-Trumbore), or inf."""
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - tris[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    return float(t[hit].min()) if hit.any() else math.inf


def test_each_vehicle_sees_the_other_in_rgb_depth_and_segmentation() -> None:
    """Two vehicles 2.5 m apart facing each other, 0.4 m apart in height (different airframes): each camera
    shows the other body as class vehicle, at the depth a ray cast onto the body's triangles gives."""
    cfg = load_config(scene="default")
    cam = CameraConfig(name="front", width=160, height=120)
    cfg.vehicles = [VehicleSpec(name="uav0", cameras=[cam]),
                    VehicleSpec(name="uav1", params="px4_quadx", cameras=[cam])]  # fmt: skip
    w = World(cfg)
    try:
        a, b = w.vehicle("uav0"), w.vehicle("uav1")
        a.place([0.0, 0.0, 2.0], 0.0)
        b.place([2.5, 0.2, 2.4], math.pi - 0.2)
        f = w.render()
        for me, other in ((a, b), (b, a)):
            fr = f.cameras[me.name]["front"]
            seen = fr.seg == SemanticClass.VEHICLE
            assert seen.sum() > 20, (me.name, seen.sum())
            mesh = vehicle_mesh(other.quad_params)
            T = f.states[other.name].T_world_body
            tris = frames.transform_points(T, mesh.positions.astype(float))[mesh.indices]
            K, T_wo = fr.K, fr.T_world_optical
            rows, cols = np.nonzero(seen)
            for r, c in list(zip(rows, cols, strict=True))[:: max(1, len(rows) // 40)]:
                ray_opt = np.linalg.solve(K, [c, r, 1.0])  # K puts pixel centres at integers
                d = T_wo[:3, :3] @ (ray_opt / np.linalg.norm(ray_opt))
                t = _ray_mesh_depth(T_wo[:3, 3], d, tris)
                z = t * (ray_opt / np.linalg.norm(ray_opt))[2]  # the optical z of the hit
                assert fr.depth[r, c] == pytest.approx(z, abs=2e-3), (me.name, r, c)
        # moved out of the camera's view, the other vehicle leaves the colour changed exactly where its body
        # was and nowhere else (vehicles cast no shadow: the scene's shadow map is static)
        for me, other in ((a, b), (b, a)):
            here = other.s[STATE.x].copy(), frames.yaw_of(other.s[STATE.q])
            mask = f.cameras[me.name]["front"].seg == SemanticClass.VEHICLE
            behind = me.s[STATE.x] - 3.0 * frames.quat_to_matrix(me.s[STATE.q])[:, 0]
            other.place(behind, 0.0)
            gone = w.render().cameras[me.name]["front"]
            other.place(*here)
            changed = np.any(f.cameras[me.name]["front"].rgb != gone.rgb, axis=2)
            assert changed[mask].mean() > 0.9 and not changed[~mask].any(), me.name
            assert not np.any(gone.seg == SemanticClass.VEHICLE)
    finally:
        w.close()


@pytest.mark.parametrize("params", ["hummingbird", "crazyflie", "px4_quadx"])
def test_mixed_airframes_fly_their_own_dynamics_equal_to_a_single_vehicle_run(params: str) -> None:
    """Three airframes in one world, 10 m apart (no wake reaches another), each flying a take-off and a
    goto: each equals a one-vehicle simulator of that airframe flying the same from the same start."""
    cfg = load_config(scene="default")
    cfg.vehicles = [VehicleSpec(name=f"v{i}", params=p, spawn=(10.0 * i, 0.0, 0.0), yaw=0.3)
                    for i, p in enumerate(["hummingbird", "crazyflie", "px4_quadx"])]  # fmt: skip
    w = World(cfg, render=False)
    alone = load_config(scene="default", overrides=[f"vehicle.params={params}"])
    single = World(alone, render=False)
    lone = single.vehicle()
    i = ["hummingbird", "crazyflie", "px4_quadx"].index(params)
    mine = w.vehicle(f"v{i}")
    single.reset(position=[10.0 * i, 0.0, 0.0], yaw=0.3)
    for v in w.vehicles.values():
        v.takeoff(1.5 + 0.1 * (v is mine))
    lone.takeoff(1.6)
    track_w, track_s = [], []
    for k in range(700):
        if k == 350:
            for v in w.vehicles.values():
                v.goto(v.s[STATE.x] + [1.0, 0.5, 0.3], yaw=1.0)
            lone.goto(lone.s[STATE.x] + [1.0, 0.5, 0.3], yaw=1.0)
        w.step()
        single.step()
        track_w.append(mine.s.copy())
        track_s.append(lone.s.copy())
    np.testing.assert_allclose(np.array(track_w), np.array(track_s), rtol=0, atol=1e-9)
    assert np.linalg.norm(mine.s[STATE.x] - [10.0 * i + 1.0, 0.5, 1.9]) < 0.05


def test_an_old_single_vehicle_config_file_loads(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text(
        'scene = "orchard"\n[vehicle]\nparams = "crazyflie"\ncollision_radius = 0.1\n'
        "[flight]\ntakeoff_altitude = 3.0\n"
        '[[render.cameras]]\nname = "down"\nwidth = 64\nheight = 48\nrpy_deg = [0.0, 90.0, 0.0]\n'
    )
    w = World(load_config(path), render=False)
    (v,) = w.vehicles.values()
    assert v.name == "uav0" and v.quad_params["mass"] == pytest.approx(0.03)
    assert v.collision_radius == 0.1 and [c.name for c in v.cameras] == ["down"]
    np.testing.assert_array_equal(v.state.position, get_scene("orchard", 0).spawn_position)
    v.takeoff()
    assert w.run_until(lambda _: v.mode.value == "hold", 20.0)
    assert v.state.position[2] == pytest.approx(3.0, abs=0.05)


def _wake_speed(thrust: float, area: float, z: float, r: float) -> float:
    """The module docstring's wake, written out again."""
    r0 = math.sqrt(area / math.pi)
    rw = r0 / math.sqrt(2)
    vh = math.sqrt(thrust / (2 * RHO * area))
    b = rw + SPREAD * z
    centre = min(vh * (1 + z / math.hypot(z, r0)), 2 * math.sqrt(2) * vh * rw / b)
    return centre * math.exp(-((r / b) ** 2))


def test_a_vehicle_below_another_feels_its_wake_as_the_model_says() -> None:
    w = world()
    up, down = w.vehicle("uav0"), w.vehicle("uav1")
    up.place([0.0, 0.0, 5.0], 0.0)
    down.place([0.15, 0.1, 3.2], 0.0)
    thrust = up.thrust
    assert thrust == pytest.approx(up.quad_params["mass"] * 9.81, rel=1e-9)  # hovering
    w.step()
    z, r = 5.0 - 3.2, math.hypot(0.15, 0.1)
    want = _wake_speed(thrust, up.disk_area, z, r)
    assert want > 1.0  # a strong wake at 1.8 m
    np.testing.assert_allclose(w.states[0, 1, STATE.wind], [0.0, 0.0, -want], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(up.s[STATE.wind], 0.0)  # nothing blows upwards
    # the lower vehicle sinks under it and works harder to hold: its thrust exceeds its weight
    w.run(1.0)
    assert down.thrust > 1.02 * down.quad_params["mass"] * 9.81


@pytest.mark.parametrize("spread", [10.0, 2000.0])  # a dense grid of cells; too thin for one: sweep and prune
def test_contacts_are_every_overlapping_pair(spread: float) -> None:
    rng = np.random.default_rng(3)
    n = 300
    pos = rng.uniform([-spread / 2, -spread / 2, 0], [spread / 2, spread / 2, 3], (n, 3))
    pos[n // 2 :] = pos[: n - n // 2] + rng.normal(0.0, 0.3, (n - n // 2, 3))  # close pairs, also when thin
    radius = rng.uniform(0.1, 0.4, n)
    active = rng.random(n) > 0.1
    brute = sorted(
        (i, j)
        for i, j in itertools.combinations(range(n), 2)
        if active[i] and active[j] and np.linalg.norm(pos[i] - pos[j]) < radius[i] + radius[j]
    )
    assert brute and contacts(pos, radius, active) == brute


def test_a_fleet_on_tree_inspection_stands_in_a_row_across_the_line_to_the_tree() -> None:
    """Either side of the spawn in turn, 2 m apart: each vehicle about as far from the tree as the first (an
    orbit's halves start level), on free ground."""
    w = world("tree_inspection", n=5)
    pts = np.array([v.s[STATE.x] for v in w.vehicles.values()])
    tree = np.asarray(w.scene.landmarks["tree"])[:2]
    to_tree = (tree - pts[0, :2]) / np.linalg.norm(tree - pts[0, :2])
    rel = pts[:, :2] - pts[0, :2]
    along, across = rel @ to_tree, rel @ [-to_tree[1], to_tree[0]]
    np.testing.assert_allclose(along, 0.0, atol=1e-9)
    np.testing.assert_allclose(across, [0.0, 2.0, -2.0, 4.0, -4.0], atol=1e-9)
    dist = np.linalg.norm(pts[:, :2] - tree, axis=1)
    assert np.all(dist[1:3] - dist[0] < 0.3)  # the neighbours: 8.7 m against 8.5 m at seed 0
    col = w.scene.collision
    assert sdf_lookup_many(col.sdf, col.origin, col.resolution, pts + [0, 0, 1.0]).min() >= 1.5


def test_fleets_spawn_on_free_points_and_bad_names_are_refused() -> None:
    w = world("orchard", n=6)
    pts = np.array([v.s[STATE.x] for v in w.vehicles.values()])
    np.testing.assert_array_equal(pts[0], w.scene.spawn_position)
    d = np.linalg.norm(pts[:, None, :2] - pts[None, :, :2], axis=2) + np.eye(6) * 99
    assert d.min() >= 2.0 - 1e-9 and np.all(pts[:, 2] == 0.0)
    col = w.scene.collision
    assert sdf_lookup_many(col.sdf, col.origin, col.resolution, pts + [0, 0, 1.0]).min() >= 1.5
    with pytest.raises(CommandError, match="no vehicle 'uav9'; the vehicles are uav0, uav1"):
        w.vehicle("uav9")
    with pytest.raises(ValueError, match="vehicle names must be unique: a given more than once"):
        load_config(overrides=['vehicles=[{"name": "a"}, {"name": "a"}]'])
    with pytest.raises(ValueError, match="must start with a letter"):
        load_config(overrides=['vehicles=[{"name": "2fast"}]'])
