"""The battery (docs/battery.md): a LiPo pack's sag and drain under known loads, the hover power against
momentum theory, the top rotor speed and thrust falling with the voltage, a spent pack dropping the
vehicle, and the battery on the API's state and on ROS 2 as sensor_msgs/BatteryState."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from droneulator.api import handle_request
from droneulator.config import BatteryConfig, ConfigError, fleet, load_config
from droneulator.ros.publishers import StatePublisher
from droneulator.ros.topics import TYPES, battery_state_topic
from droneulator.state import STATE
from droneulator.vehicles.battery import AIRFRAME_BATTERIES, Battery, pack_for
from droneulator.vehicles.dynamics import GRAVITY, PARAM_WMAX
from droneulator.vehicles.params import get_params
from droneulator.world import World

TS = get_typestore(Stores.ROS2_JAZZY)


def world(*overrides: str, n: int = 1) -> World:
    cfg = load_config(overrides=list(overrides))
    if n > 1:
        cfg.vehicles = fleet(n)
    return World(cfg, render=False)


def top_speed(w: World, i: int = 0) -> float:
    """The top rotor speed (rad/s) the physics holds vehicle ``i`` to now."""
    return float(w.table.params[w._pidx[i], PARAM_WMAX])


# --------------------------------------------------------------------------- the pack alone
def test_a_constant_current_sags_the_voltage_by_i_r_and_drains_i_t():
    """3S 2100 mAh, 35 mOhm (the hummingbird's pack) at SoC 0.5 (3.84 V a cell on the LiPo curve): 10 A
    for a minute, one second at a time."""
    bat = Battery(BatteryConfig(initial_soc=0.5), "hummingbird")
    assert (bat.cells, bat.capacity_mah, bat.resistance) == (3, 2100.0, 0.035)
    assert bat.voltage == pytest.approx(3 * 3.84) and bat.current == 0.0  # at rest: the OCV
    soc = 0.5
    for _ in range(60):
        ocv = bat.ocv(soc)
        bat.draw_current(10.0, 1.0)
        assert bat.voltage == pytest.approx(ocv - 10.0 * 0.035, abs=1e-12)
        assert bat.power == pytest.approx(bat.voltage * 10.0)
        soc -= 10.0 * 1.0 / (2100.0 * 3.6)
        assert bat.soc == pytest.approx(soc, abs=1e-12)
    assert bat.state()["remaining_mah"] == pytest.approx(2100.0 * 0.5 - 10_000.0 * 60 / 3600)  # 1050 - 166.7
    assert bat.ocv(1.0) == pytest.approx(12.6) and bat.ocv(0.0) == pytest.approx(3 * 3.27)


def test_a_constant_power_load_and_an_overload():
    """The current that delivers P at the terminals (V I = P), and at most the pack's maximum power,
    OCV^2 / (4 R), at half the OCV."""
    bat = Battery(BatteryConfig(), "hummingbird")
    bat.draw_power(200.0, 0.01)
    assert bat.voltage * bat.current == pytest.approx(200.0, rel=1e-12)
    assert bat.voltage == pytest.approx(12.6 - 0.035 * bat.current, rel=1e-12)
    bat.reset()
    bat.draw_power(5000.0, 0.01)  # more than 12.6^2 / 0.14 = 1134 W
    assert bat.current == pytest.approx(12.6 / 0.07) and bat.voltage == pytest.approx(6.3)


def test_the_speed_scale_is_the_voltage_over_nominal_below_it():
    """Above the nominal 3.7 V a cell the airframe's own top speed; below it, in proportion."""
    assert Battery(BatteryConfig(), "hummingbird").speed_scale == 1.0
    low = Battery(BatteryConfig(initial_soc=0.05), "hummingbird")  # 3.61 V a cell at rest
    assert low.speed_scale == pytest.approx(3.61 / 3.7)
    low.draw_current(20.0, 0.0)
    assert low.speed_scale == pytest.approx((3 * 3.61 - 20.0 * 0.035) / (3 * 3.7))


# --------------------------------------------------------------------------- in a world
@pytest.mark.parametrize("params", ["hummingbird", "px4_quadx", "sprayer10"])
def test_hover_power_is_momentum_theorys(params: str):
    """In a steady hover each rotor carries a quarter of the weight, so the rotors' electrical power is
    (m g)^1.5 / sqrt(2 rho A) / (FM eta) (A the four disks' area): the battery's measured power agrees
    within 0.5 %; its current is P / V and its charge falls by that current."""
    w = world(f"vehicle.params={params}")
    v = w.vehicle()
    w.reset(position=[0.0, 0.0, 3.0])
    w.run(4.0)
    bat = w.batteries["uav0"]
    weight = float(v.quad_params["mass"]) * GRAVITY
    ideal = weight**1.5 / math.sqrt(2.0 * 1.225 * v.disk_area)
    expected = ideal / (0.6 * AIRFRAME_BATTERIES[params].efficiency)
    assert bat.power == pytest.approx(expected, rel=5e-3)
    assert bat.current == pytest.approx(bat.power / bat.voltage)
    used_as = (1.0 - bat.soc) * bat.capacity_as
    assert used_as == pytest.approx(bat.current * 4.0, rel=0.02)  # the steady current over the 4 s
    print(f"\n{params}: hover {bat.power:.1f} W, {bat.current:.2f} A at {bat.voltage:.2f} V, "
          f"{bat.capacity_as / bat.current / 60:.1f} min to empty")  # fmt: skip


def test_a_full_battery_leaves_a_hover_and_the_airframes_top_speed_alone():
    """A charged pack sags less than to the nominal voltage in hover: the physics keeps the airframe's
    own top speed, and the flight is the one without a battery, to the last bit."""
    flights = []
    for enabled in ("true", "false"):
        w = world(f"battery.enabled={enabled}")
        v = w.vehicle()
        w.reset(position=[0.0, 0.0, 2.0])
        v.goto([3.0, 1.0, 2.5])
        w.run(6.0)
        flights.append(v.s.copy())
        assert top_speed(w) == v.quad_params["rotor_speed_max"]
    assert np.array_equal(flights[0], flights[1])


def test_available_thrust_falls_with_the_voltage():
    """Full throttle from a hover: a charged pack sags under the load, a nearly spent one (SoC 5 %) more,
    and the rotors reach the top speed the voltage leaves them, so the low pack climbs slower."""
    reached = {}
    for soc in (1.0, 0.05):
        w = world(f"battery.initial_soc={soc}")
        v = w.vehicle()
        w.reset(position=[0.0, 0.0, 2.0])
        for _ in range(50):
            v.rotors([1.0, 1.0, 1.0, 1.0], normalized=True)
            held_to = top_speed(w)  # what the physics holds the rotors to in the next period
            w.step()
        assert np.all(v.s[STATE.rotor_speeds] <= held_to + 1e-9)
        bat = w.batteries["uav0"]
        wmax = float(v.quad_params["rotor_speed_max"])
        assert top_speed(w) == pytest.approx(bat.top_speed * wmax)
        assert bat.voltage < bat.nominal_v
        assert bat.top_speed == pytest.approx(bat.voltage / bat.nominal_v, rel=0.02)  # settled on its lag
        reached[soc] = (float(v.s[STATE.rotor_speeds].mean()), float(v.s[STATE.x][2]))
    (w_full, z_full), (w_low, z_low) = reached[1.0], reached[0.05]
    assert w_low < 0.95 * w_full and z_low < z_full
    print(f"\nfull throttle: {w_full:.0f} rad/s charged, {w_low:.0f} rad/s at 5 % "
          f"(thrust x {(w_low / w_full) ** 2:.2f})")  # fmt: skip


def test_a_spent_pack_stops_the_rotors_and_the_vehicle_falls():
    """A 1 mAh pack lasts about a second of hover: a ``battery_empty`` event, the top speed 0, and the
    vehicle falls to the ground (impact) instead of holding its altitude."""
    w = world("battery.capacity_mah=1.0")
    v = w.vehicle()
    w.reset(position=[0.0, 0.0, 5.0])
    res = w.run(1.5)
    empty = [e for e in res.events if e.type == "battery_empty"]
    assert len(empty) == 1 and empty[0].vehicle == "uav0" and 0.5 < empty[0].t < 1.5
    assert top_speed(w) == 0.0 and v.state.battery["empty"] and v.state.battery["voltage"] == 0.0
    res = w.run(2.0)
    assert v.s[STATE.x][2] < 0.1 and any(e.type == "impact" for e in res.events)
    w.reset(position=[0.0, 0.0, 2.0])  # a reset charges it again
    assert not v.state.battery["empty"] and v.state.battery["soc"] == 1.0
    assert top_speed(w) == v.quad_params["rotor_speed_max"]


def test_each_vehicle_has_its_own_pack_and_parameter_row():
    """Two vehicles of one airframe: the one with the spent pack falls, the other hovers."""
    cfg = load_config()
    cfg.vehicles = fleet(2)
    cfg.vehicles[1].spawn = (3.0, 0.0, 0.0)
    cfg.vehicles[0].battery = BatteryConfig(capacity_mah=1.0)
    w = World(cfg, render=False)
    a, b = w.vehicle("uav0"), w.vehicle("uav1")
    a.place([0.0, 0.0, 3.0], 0.0)
    b.place([3.0, 0.0, 3.0], 0.0)
    w.run(2.5)
    assert w._pidx[0] != w._pidx[1]
    assert a.s[STATE.x][2] < 1.0 and abs(b.s[STATE.x][2] - 3.0) < 0.05
    assert w.batteries["uav0"].capacity_mah == 1.0 and w.batteries["uav1"].capacity_mah == 2100.0


def test_a_payload_change_keeps_the_top_speed_the_battery_leaves():
    """A spray tank's liquid changes the vehicle's parameter row (World.set_payload): the new row keeps the
    battery's top speed, not the airframe's."""
    w = world("vehicle.params=sprayer10", "battery.initial_soc=0.05")
    v = w.vehicle()
    w.reset(position=[0.0, 0.0, 2.0])
    w.run(0.5)
    bat = w.batteries["uav0"]
    wmax = float(v.quad_params["rotor_speed_max"])
    assert bat.top_speed < 0.95
    w.set_payload("uav0", 6.0)
    assert top_speed(w) == pytest.approx(bat.top_speed * wmax)


# --------------------------------------------------------------------------- state, ROS, config
def test_the_state_op_carries_the_battery():
    w = world()
    w.reset(position=[0.0, 0.0, 2.0])
    w.run(1.0)
    state = handle_request(w, '{"op": "state"}')["result"]
    b = state["battery"]
    assert set(b) == {"voltage", "current", "power", "soc", "remaining_mah", "capacity_mah", "cells", "ocv",
                      "empty", "top_speed"}  # fmt: skip
    assert 12.0 < b["voltage"] < b["ocv"] <= 12.6 and 3.0 < b["current"] < 4.0
    assert b["remaining_mah"] == pytest.approx(b["soc"] * 2100.0) and b["cells"] == 3
    json.dumps(state)
    assert "battery" not in world("battery.enabled=false").vehicle().state.to_dict()


class _Node:
    """A ROS node that keeps what is published, by topic."""

    def __init__(self) -> None:
        self.sent: dict[str, list[tuple[str, Any, int]]] = {}

    def publisher(self, topic: str, typename: str) -> Any:
        node = self

        class Pub:
            def publish(self, payload: Any, t: int) -> None:
                node.sent.setdefault(topic, []).append((typename, bytes(payload), t))

        return Pub()


def test_ros_carries_each_vehicles_battery_state():
    """sensor_msgs/BatteryState on /<ns>/<vehicle>/battery, decoded by rosbags: the state's voltage, the
    current negative (discharging, as the message defines it), charge and capacity in Ah, the SoC, three
    cells of a third of the voltage, a LiPo, stamped with the state."""
    w = world(n=2)
    w.vehicle("uav1").place([3.0, 0.0, 2.0], 0.0)
    w.vehicle("uav0").place([0.0, 0.0, 2.0], 0.0)
    w.run(0.5)
    node = _Node()
    pub = StatePublisher(node, w.config)  # type: ignore[arg-type]
    states = w.states_now()
    pub.publish_states(states)
    for name in ("uav0", "uav1"):
        topic = battery_state_topic(f"droneulator/{name}")
        ((typename, raw, t),) = node.sent[topic]
        assert typename == TYPES["battery"] == "sensor_msgs/msg/BatteryState"
        msg = TS.deserialize_cdr(raw, typename)
        b = states[name].battery
        assert t == states[name].stamp_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert msg.header.frame_id == f"{name}/base_link"
        assert msg.voltage == pytest.approx(b["voltage"], rel=1e-6)
        assert msg.current == pytest.approx(-b["current"], rel=1e-6) and msg.current < 0.0
        assert msg.charge == pytest.approx(b["remaining_mah"] / 1000.0, rel=1e-6)
        assert msg.capacity == msg.design_capacity == pytest.approx(2.1)
        assert msg.percentage == pytest.approx(b["soc"], rel=1e-6)
        assert np.allclose(msg.cell_voltage, [b["voltage"] / 3] * 3, rtol=1e-6)
        assert msg.power_supply_technology == 3 and msg.power_supply_status == 2 and msg.present
        assert math.isnan(msg.temperature)


def test_bad_battery_config_is_a_clear_error():
    for bad, key in (
        (["battery.cells=0"], "battery.cells"),
        (["battery.capacity_mah=-5"], "battery.capacity_mah"),
        (["battery.internal_resistance_ohm=-0.1"], "battery.internal_resistance_ohm"),
        (["battery.efficiency=1.5"], "battery.efficiency"),
        (["battery.initial_soc=0"], "battery.initial_soc"),
        (["battery.figure_of_merit=nan"], "battery.figure_of_merit"),
    ):
        with pytest.raises((ValueError, ConfigError), match=key):
            load_config(overrides=bad)
    with pytest.raises(ValueError, match="SoC must rise strictly from 0 to 1"):
        BatteryConfig(ocv_curve=[(0.0, 3.3), (0.6, 3.8), (0.5, 3.9), (1.0, 4.2)])
    with pytest.raises(ValueError, match="voltages must be positive and never fall"):
        BatteryConfig(ocv_curve=[(0.0, 3.3), (0.5, 3.2), (1.0, 4.2)])
    with pytest.raises(ValueError, match="no default battery for airframe 'mystery'"):
        pack_for("mystery", BatteryConfig())
    assert pack_for("mystery", BatteryConfig(cells=6, capacity_mah=5000, internal_resistance_ohm=0.02,
                                             efficiency=0.8)) == (6, 5000.0, 0.02, 0.8)  # fmt: skip
    with pytest.raises(ValueError, match="finite current"):
        Battery(BatteryConfig(), "hummingbird").draw_current(-1.0, 0.01)


def test_a_custom_curve_and_pack_from_a_config_file(tmp_path):
    """A 6S pack of another chemistry's curve (a flat LiFePO4-like one), set in a YAML file."""
    path = tmp_path / "b.yaml"
    path.write_text("battery:\n  cells: 6\n  capacity_mah: 4000\n"
                    "  ocv_curve: [[0, 2.8], [0.5, 3.3], [1, 3.4]]\n")
    cfg = load_config(path)
    bat = Battery(cfg.battery, "px4_quadx")
    assert (bat.cells, bat.capacity_mah, bat.resistance) == (6, 4000.0, 0.03)
    assert bat.ocv(0.25) == pytest.approx(6 * 3.05) and bat.ocv(1.0) == pytest.approx(6 * 3.4)
    fleet_file = tmp_path / "fleet.yaml"  # a vehicle of the list with its own pack
    fleet_file.write_text("vehicles:\n  - name: uav0\n    battery: {capacity_mah: 1000, initial_soc: 0.5}\n"
                          "  - name: uav1\n")  # fmt: skip
    specs = load_config(fleet_file).vehicle_specs()
    assert (specs[0].battery.capacity_mah, specs[0].battery.initial_soc) == (1000.0, 0.5)
    assert specs[1].battery == BatteryConfig()


def test_px4_parameters_resemble_the_pack():
    """PX4's own simulated battery set from the pack: its cells, capacity, curve ends, resistance, and a
    linear drain lasting the hover endurance the world measures (capacity over the hover current)."""
    w = world("vehicle.params=px4_quadx")
    v = w.vehicle()
    w.reset(position=[0.0, 0.0, 2.0])
    w.run(3.0)
    bat = w.batteries["uav0"]
    p = bat.px4_params(float(v.quad_params["mass"]) * GRAVITY, v.disk_area)
    assert {k: p[k] for k in ("BAT1_N_CELLS", "BAT1_CAPACITY", "BAT1_V_CHARGED", "BAT1_V_EMPTY",
                              "BAT1_R_INTERNAL", "SIM_BAT_MIN_PCT")} == {
        "BAT1_N_CELLS": 3, "BAT1_CAPACITY": 3000.0, "BAT1_V_CHARGED": 4.2, "BAT1_V_EMPTY": 3.27,
        "BAT1_R_INTERNAL": 0.03, "SIM_BAT_MIN_PCT": 0.0}  # fmt: skip
    assert p["SIM_BAT_DRAIN"] == pytest.approx(bat.capacity_as / bat.current, rel=0.01)


def test_the_batched_rows_of_many_worlds_fly_without_a_battery():
    w = World(load_config(), render=False, worlds=2)
    assert w.batteries == {} and "battery" not in w.vehicle().state.to_dict()


def test_the_docs_px4_example_is_what_px4_params_gives():
    """docs/battery.md's `param set` lines for px4_quadx are Battery.px4_params' values."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "battery.md").read_text()
    lines = dict(re.findall(r"^param set (\w+) ([\d.]+)$", doc, flags=re.M))
    q = get_params("px4_quadx")
    arm = float(np.hypot(*q["rotor_pos"]["r1"][:2]))
    area = 4.0 * math.pi * (0.45 * arm) ** 2  # px4_quadx has no rotor_radius: Vehicle.disk_area's rule
    want = Battery(BatteryConfig(), "px4_quadx").px4_params(float(q["mass"]) * GRAVITY, area)
    assert {k: float(v) for k, v in lines.items()} == {k: float(v) for k, v in want.items()}
