"""What a touch of the scene or another vehicle does, by contact model (docs/contact.md): ``stop`` (held),
``physical`` (foliage pushes and slows, a strike on wood costs the struck rotors), ``crash`` (rotors stop).

Real Worlds on the default scene's first tree (its trunk is bare below 1.2 m, its crown's leaves start
2.6 m from the trunk at 4.4 m), flown the way an autopilot flies a vehicle: rotor speeds set from outside
(``set_rotor_speeds``, mode ``external``), here the hover speed with a push towards the tree.
"""

import numpy as np
import pytest

from droneulator.commands.errors import CommandError
from droneulator.config import ConfigError, VehicleSpec, load_config
from droneulator.state import STATE
from droneulator.vehicles.dynamics import CONTACT_PHYSICAL, GRAVITY
from droneulator.world import World


def flown_at_the_tree(model: str, height: float, start: float, speed: float = 2.0, seconds: float = 3.0,
                      extra: tuple[str, ...] = ()) -> tuple[World, np.ndarray, np.ndarray, list]:  # fmt: skip
    """A hummingbird under contact model ``model`` at ``start`` m from the first tree's trunk (-x side) at
    ``height``, hover rotor speeds and ``speed`` m/s towards the trunk, flown for ``seconds``: the world, the
    trunk, rows ``(t, x, y, z, vx, vy, vz, rotor speeds...)`` per control period and the events."""
    overrides = ["vehicle.params=hummingbird", f"vehicle.contact_model={model}", *extra]
    world = World(scene="default", render=False, config=load_config(overrides=overrides))
    uav = world.vehicle()
    trunk = np.asarray(world.scene.landmarks["trunks"][0], dtype=float)
    world.reset(position=trunk + [start, 0.0, height], yaw=0.0)
    uav.set_rotor_speeds([uav.hover_speed] * 4)
    uav.s[STATE.v] = [speed, 0.0, 0.0]
    rows, events = [], []
    while world.t < seconds:
        events += world.step().events
        rows.append([world.t, *uav.s[0:6], *uav.s[STATE.rotor_speeds]])
    return world, trunk, np.array(rows), events


def collisions(events: list) -> list:
    return [e for e in events if e.type == "collision"]


def test_a_brush_with_foliage_slows_and_pushes_the_vehicle_out_and_it_flies_on():
    world, trunk, rows, events = flown_at_the_tree("physical", 4.4, -4.0)
    col = world.scene.collision
    radius = world.config.vehicle.collision_radius
    [hit] = collisions(events)
    assert hit.data["contact"] == "foliage" and hit.data["model"] == "physical"
    assert hit.data["rotors_lost"] == []
    k = np.searchsorted(rows[:, 0], hit.t)
    assert rows[k - 1, 4] > 1.2  # it came in at speed
    deepest = rows[np.argmax(rows[:, 1])]
    assert radius - col.distance(deepest[1:4]) < 0.2  # held in the leaves' skin, nowhere near the trunk
    assert col.wood_distance(deepest[1:4]) > 0.6
    assert rows[-1, 4] < -0.1  # pushed back: moving away from the tree
    assert col.distance(rows[-1, 1:4]) > radius  # out of the leaves again
    uav = world.vehicle()
    assert uav.mode.value == "external" and world.active[0, 0]
    np.testing.assert_array_equal(world.rotor_efficiency[0, 0], 1.0)  # leaves cost no rotor
    before = uav.state.position
    world.run(0.2)
    assert np.linalg.norm(uav.state.position - before) > 0.01  # never frozen


def test_stop_holds_the_vehicle_where_it_touched_the_leaves_as_before():
    world, trunk, rows, events = flown_at_the_tree("stop", 4.4, -4.0, seconds=2.0)
    [hit] = collisions(events)
    assert hit.data["contact"] == "foliage" and hit.data["model"] == "stop"
    assert world.vehicle().mode.value == "collided" and not world.active[0, 0]
    k = np.searchsorted(rows[:, 0], hit.t)
    np.testing.assert_array_equal(rows[k + 1 :, 1:7], np.repeat(rows[-1:, 1:7], len(rows) - k - 1, axis=0))
    assert np.all(rows[-1, 4:7] == 0.0)


def test_a_strike_on_the_trunk_costs_the_front_rotors_and_the_vehicle_falls_to_the_ground():
    world, trunk, rows, events = flown_at_the_tree("physical", 1.0, -2.0)
    first = collisions(events)[0]
    assert first.data["contact"] == "wood" and first.data["model"] == "physical"
    assert first.data["rotors_lost"] == [0, 1]  # heading +x: r1 and r2 sit forward
    lost = set().union(*(e.data["rotors_lost"] for e in collisions(events)))
    np.testing.assert_array_equal(world.rotor_efficiency[0, 0, sorted(lost)], 0.0)
    assert rows[-1, 3] < 0.1 and abs(rows[-1, 6]) < 0.05  # down on the ground, at rest
    assert any(e.type == "impact" for e in events)  # it fell: the legs took a hard touchdown
    assert world.vehicle().mode.value == "external"  # still the autopilot's, never held
    assert world.scene.collision.wood_distance(rows[-1, 1:4]) > 0.0


def test_a_crash_stops_every_rotor_and_the_vehicle_falls_as_a_ballistic_body():
    """A crash on the leaves: the rotors spin down, the leaves let it go, and from there it falls as a body
    under gravity and its own quadratic drag (the airframe's c_D), integrated here apart."""
    world, trunk, rows, events = flown_at_the_tree("crash", 4.4, -4.0, seconds=2.5)
    uav = world.vehicle()
    first = collisions(events)[0]
    assert first.data["contact"] == "foliage" and first.data["model"] == "crash"
    assert first.data["rotors_lost"] == [0, 1, 2, 3]
    assert uav.mode.value == "crashed" and world.dead[0, 0]
    k = np.searchsorted(rows[:, 0], first.t)
    assert np.all(rows[k + 5 :, 7:11] < 0.01 * uav.hover_speed)  # spun down within 0.05 s (tau_m 5 ms)
    col, radius = world.scene.collision, world.config.vehicle.collision_radius
    free = k + 1 + np.flatnonzero([col.distance(x) < radius for x in rows[k:, 1:4]]).max()
    fall = rows[free:][rows[free:, 3] > uav.contact.foot_depth + 0.05]
    assert len(fall) > 40  # 0.4 s and more of free fall
    drag = np.array([uav.quad_params[f"c_D{a}"] for a in "xyz"]) / uav.quad_params["mass"]
    x, v, h = fall[0, 1:4].copy(), fall[0, 4:7].copy(), 1e-3
    ballistic = [x.copy()]
    for _ in range(len(fall) - 1):
        for _ in range(10):  # 10 ms a row
            a = -np.linalg.norm(v) * drag * v - [0.0, 0.0, GRAVITY]
            v += h * a
            x += h * v
        ballistic.append(x.copy())
    np.testing.assert_allclose(fall[:, 1:4], ballistic, atol=0.015)
    world.run(0.5)
    assert uav.state.position[2] < 0.1
    # dead until reset: an autopilot's outputs and flight commands change nothing
    uav.set_rotor_speeds([uav.hover_speed] * 4)
    assert uav.mode.value == "crashed"
    with pytest.raises(CommandError) as err:
        uav.takeoff(2.0)
    assert err.value.code == "crashed"
    world.run(0.3)
    assert np.all(uav.state.rotor_speeds < 1e-6)
    world.reset()
    assert uav.mode.value == "idle" and not world.dead[0, 0]
    uav.takeoff(1.0)
    world.run(2.5)
    assert uav.state.position[2] > 0.5


def test_an_autopilot_vehicle_defaults_to_physical_and_the_others_to_stop():
    cfg = load_config(overrides=["vehicle.params=hummingbird"])
    cfg.vehicles = [VehicleSpec(name="a", controlled_by="px4"), VehicleSpec(name="b"),
                    VehicleSpec(name="c", contact_model="crash")]  # fmt: skip
    assert [s.contact_model for s in cfg.vehicle_specs()] == ["physical", "stop", "crash"]
    cfg.vehicle.contact_model = "physical"
    assert [s.contact_model for s in cfg.vehicle_specs()] == ["physical", "physical", "crash"]
    px4 = load_config(overrides=["px4.enabled=true"])
    assert px4.vehicle_specs()[0].contact_model == "physical"
    world = World(config=load_config(overrides=["ardupilot.enabled=true"]), render=False)
    assert world.vehicle().contact_model == "physical" and world.contact_model[0, 0] == CONTACT_PHYSICAL


def test_a_bad_contact_model_is_refused_with_the_choices():
    with pytest.raises((ConfigError, ValueError), match="must be auto, stop, physical, crash; got 'bounce'"):
        load_config(overrides=["vehicle.contact_model=bounce"])
    with pytest.raises(ValueError, match="contact_model must be one of stop, physical, crash"):
        VehicleSpec(name="a", contact_model="auto")


def test_two_physical_vehicles_that_meet_lose_the_rotors_facing_each_other_and_fly_on():
    cfg = load_config(overrides=["vehicle.params=hummingbird", "vehicle.contact_model=physical"])
    cfg.vehicles = [VehicleSpec(name=n, spawn=(x, 0.0, 0.0)) for n, x in (("a", 0.0), ("b", 3.0))]
    world = World(config=cfg, render=False)
    a, b = world.vehicle("a"), world.vehicle("b")
    for v, x, speed in ((a, 0.0, 1.5), (b, 3.0, -1.5)):
        v.place([x, 0.0, 2.0], 0.0)
        v.set_rotor_speeds([v.hover_speed] * 4)
        v.s[STATE.v] = [speed, 0.0, 0.0]
    events = []
    world.run_until(lambda w: False, 1.5, events)
    hit = collisions(events)[0]
    assert hit.data["contact"] == "vehicle" and hit.data["vehicles"] == ["a", "b"]
    assert hit.data["models"] == ["physical", "physical"]
    assert hit.data["rotors_lost"] == [[0, 1], [2, 3]]  # a's front pair, b's back pair (it faces away)
    assert a.mode.value == b.mode.value == "external" and world.active[0].all()  # never held
    assert a.state.position[2] < 1.6 and b.state.position[2] < 1.6  # falling on what they have left
    assert a.s[3] < 0.0 < b.s[3]  # bounced apart


def test_a_hard_touchdown_crashes_a_vehicle_under_crash_only():
    """Motors cut at 4 m (an autopilot's outputs gone): under crash the touchdown is a crash on the ground,
    under physical the legs take it and the vehicle flies again when told."""
    for model in ("crash", "physical"):
        overrides = ["vehicle.params=hummingbird", f"vehicle.contact_model={model}"]
        world = World(scene="default", render=False, config=load_config(overrides=overrides))
        uav = world.vehicle()
        world.reset(position=world.scene.spawn_position + [0.0, 0.0, 4.0])
        uav.set_rotor_speeds([0.0] * 4)
        events = []
        world.run_until(lambda w: False, 1.5, events)
        assert [e.type for e in events][:1] == ["impact"]
        hits = collisions(events)
        if model == "crash":
            assert [(e.data["contact"], e.data["model"]) for e in hits] == [("ground", "crash")]
            assert uav.mode.value == "crashed" and world.dead[0, 0]
        else:
            assert hits == [] and not world.dead[0, 0]
            uav.set_rotor_speeds([uav.hover_speed * 1.2] * 4)
            world.run(0.5)
            assert uav.state.position[2] > 0.2


def test_many_worlds_step_their_rows_by_the_contact_model_and_never_freeze_a_physical_one():
    """The batched rows (learning's path): world 0's row flies into the crown under velocity commands and
    is flagged once and flies on; under stop the same row is held and inactive, as the envs expect."""
    for model in ("physical", "stop"):
        overrides = ["vehicle.params=hummingbird", f"vehicle.contact_model={model}"]
        world = World(scene="default", render=False, worlds=2, config=load_config(overrides=overrides))
        trunk = np.asarray(world.scene.landmarks["trunks"][0], dtype=float)
        world.place(None, [trunk + [-3.5, 0.0, 4.4], trunk + [-3.5, -8.0, 4.4]], [0.0, 0.0])
        world.velocity(None, [[1.5], [1.5]], [[0.0], [0.0]])
        flagged = []
        for _ in range(40):  # 40 frames, 1.3 s at 30 Hz
            _, hit = world.step_frame()
            flagged.append(hit[:, 0].copy())
        flagged = np.array(flagged)
        assert flagged[:, 0].sum() == 1 and not flagged[:, 1].any()
        before = world.states[0, 0, 0:3].copy()
        world.step_frame()
        moved = np.linalg.norm(world.states[0, 0, 0:3] - before)
        if model == "physical":
            assert world.active[0, 0] and moved > 1e-3
        else:
            assert not world.active[0, 0] and moved == 0.0
