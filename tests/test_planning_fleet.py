"""One planner per vehicle of a fleet: which names and PX4 instance a planner takes for its vehicle (from
the run's scene_info or its configuration, and through `droneulator plan`'s options), and the PX4
offboard link of instance k: port 14540+k, 14549 past 9, told apart by MAV_SYS_ID k+1, against
pymavlink peers playing PX4 (tests/test_offboard.FakePX4) over real UDP."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_offboard import HOME, FakePX4, fast_cfg, wait_until

from droneulator import frames
from droneulator.cli import build_parser
from droneulator.cli.plan import _px4_instance, resolve_vehicle
from droneulator.config import CameraConfig, VehicleSpec, fleet, load_config, to_dict
from droneulator.ros.publishers import fleet_names
from droneulator.runtime.launch import free_port
from droneulator.runtime.preflight import StartupError
from droneulator.workflows.planning.fleet import from_config, from_scene_info, single_vehicle
from droneulator.workflows.planning.node import PlanNodeConfig
from droneulator.workflows.planning.offboard import (
    OffboardConfig,
    OffboardLink,
    offboard_port,
    px4_system_id,
)


def fleet_config(n: int = 2, **px4: Any) -> Any:
    cfg = load_config(scene="planning")
    cfg.vehicles = fleet(n)
    cfg.render.cameras = [CameraConfig(name="front", width=160, height=120)]
    for key, value in px4.items():
        setattr(cfg.px4, key, value)
    return cfg


def scene_info(cfg: Any) -> dict[str, Any]:
    """``scene_info``'s vehicles as the run lists them (``runtime/api_host.py``'s ``_describe_vehicles``)."""
    instances = cfg.px4_instances()
    vehicles = []
    for name, names in fleet_names(cfg).items():
        entry = {"name": name, "cameras": ["front"], **names.describe(["front"])}
        if name in instances:
            entry |= {"px4_instance": instances[name], "px4_port": cfg.px4.base_port + instances[name]}
        vehicles.append(entry)
    return {"name": cfg.scene, "vehicles": vehicles}


# --------------------------------------------------------------------------- which vehicle, which names
def test_a_planner_takes_its_vehicles_names_from_scene_info_or_the_config() -> None:
    cfg = fleet_config()
    uav1 = from_config(cfg, "uav1")
    assert (uav1.names.namespace, uav1.names.odom_frame) == ("droneulator/uav1", "uav1/odom")
    assert uav1.names.topics()["position_cmd"] == "/droneulator/uav1/position_cmd"
    assert uav1.names.camera_topics("front")["depth"] == "/droneulator/uav1/front/depth/image_raw"
    assert (uav1.name, uav1.cameras, uav1.px4_instance) == ("uav1", ["front"], None)
    assert from_config(cfg).name == "uav0"  # the first by default
    info = scene_info(cfg)
    assert from_scene_info(info, "uav1").names == uav1.names
    assert from_scene_info(info).names == from_config(cfg, "uav0").names

    cfg.bridge.fleet_tf = "namespace"  # Nav2's convention: /droneulator/uav1/tf, unprefixed frames
    by_ns = from_scene_info(scene_info(cfg), "uav1").names
    assert (by_ns.tf, by_ns.odom_frame) == ("/droneulator/uav1/tf", "odom")

    one = load_config(scene="planning")  # one vehicle: today's names, whatever it is called
    assert from_config(one).names == single_vehicle().names
    assert single_vehicle().names.topics()["odom"] == "/droneulator/odom"

    with pytest.raises(ValueError, match="no vehicle 'uav7' in the run's scene_info: it has uav0, uav1"):
        from_scene_info(info, "uav7")
    info["vehicles"][1]["topics"]["odom"] = "/elsewhere/odom"
    with pytest.raises(ValueError, match=r"names the topics \['odom'\] of vehicle 'uav1' otherwise"):
        from_scene_info(info, "uav1")
    with pytest.raises(ValueError, match="vehicle 'uav1' has no camera 'down'"):
        PlanNodeConfig(camera="down", vehicle=uav1)


def test_plan_takes_the_vehicle_and_its_px4_instance_from_the_config_or_the_run(tmp_path: Path) -> None:
    """`droneulator plan --vehicle NAME [--px4]`: vehicle k of the list is PX4 instance px4.instance + k;
    the link then listens where that instance sends (14540 + k) for system k + 1."""
    cfg = fleet_config(3, enabled=True, instance=1)
    cfg.vehicles = [VehicleSpec("uav0"), VehicleSpec("uav1", controlled_by="px4"),
                    VehicleSpec("uav2", controlled_by="px4")]  # fmt: skip
    path = tmp_path / "run.json"
    path.write_text(json.dumps(to_dict(cfg)))
    parse = build_parser().parse_args

    args = parse(["plan", "--config", str(path), "--vehicle", "uav2", "--px4"])
    vehicle, run_cfg = resolve_vehicle(args)
    assert vehicle.names.namespace == "droneulator/uav2" and run_cfg is not None
    link = OffboardConfig(instance=_px4_instance(args, vehicle))
    assert (link.instance, link.port, link.px4_sysid) == (3, 14543, 4)  # instance 1 + index 2
    assert _px4_instance(parse(["plan", "--px4-instance", "7"]), vehicle) == 7
    args = parse(["plan", "--config", str(path), "--vehicle", "uav0", "--px4"])
    with pytest.raises(StartupError, match="PX4 does not fly vehicle 'uav0'"):
        _px4_instance(args, resolve_vehicle(args)[0])
    with pytest.raises(StartupError, match="no vehicle 'uav9' in the configuration"):
        resolve_vehicle(parse(["plan", "--config", str(path), "--vehicle", "uav9"]))
    with pytest.raises(StartupError, match="the planner needs depth at the camera rate"):
        resolve_vehicle(parse(["plan", "--config", str(path), "--set", "render.camera_trigger=command"]))

    nobody = f"ws://127.0.0.1:{free_port()}"  # no run answers: the single vehicle, unless one was named
    vehicle, run_cfg = resolve_vehicle(parse(["plan", "--url", nobody]))
    assert vehicle.names.topics()["odom"] == "/droneulator/odom" and run_cfg is None
    vehicle, _ = resolve_vehicle(parse(["plan", "--namespace", "sim"]))  # named: the run is not asked
    assert vehicle.names.topics()["odom"] == "/sim/odom"
    assert _px4_instance(parse(["plan", "--px4"]), vehicle) == 0
    with pytest.raises(StartupError, match=f"--vehicle uav1: the run's API at {nobody} does not answer"):
        resolve_vehicle(parse(["plan", "--url", nobody, "--vehicle", "uav1"]))


def test_plan_refuses_a_negative_yaw_lookahead_with_a_clear_error() -> None:
    """`droneulator plan --yaw-lookahead -1`: exit status 2 and a line that names the setting, before any
    connection is made."""
    with pytest.raises(ValueError, match="yaw_lookahead_s must be >= 0"):
        PlanNodeConfig(yaw_lookahead_s=-1.0)
    out = subprocess.run([sys.executable, "-m", "droneulator.cli", "plan", "--namespace", "sim",
                          "--yaw-lookahead", "-1"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 2 and "yaw_lookahead_s must be >= 0" in out.stderr, (out.returncode, out.stderr)


# --------------------------------------------------------------------------- PX4 instance k's offboard link
def test_px4_sitl_offboard_ports_and_system_ids() -> None:
    """px4-rc.mavlink: udp_offboard_port_remote = 14540 + instance, 14549 for every instance > 9;
    rcS: MAV_SYS_ID = instance + 1."""
    instances = (0, 1, 8, 9, 10, 11, 254)
    assert [offboard_port(k) for k in instances] == [14540, 14541, 14548, 14549, 14549, 14549, 14549]
    assert [px4_system_id(k) for k in instances] == [1, 2, 9, 10, 11, 12, 255]
    assert (OffboardConfig(instance=11).port, OffboardConfig(instance=11).px4_sysid) == (14549, 12)
    assert OffboardConfig(instance=11, system_id=40).px4_sysid == 40
    with pytest.raises(ValueError, match="system_id must be in"):
        OffboardConfig(system_id=0)
    with pytest.raises(ValueError, match="instance"):
        OffboardConfig(instance=255)


def _fly(link: OffboardLink, peer: FakePX4) -> None:
    """Engage the link and check that its setpoints reach ``peer``, addressed to the peer's system."""
    link.engage()
    assert link.engaged.wait(10), link.error
    wait_until(lambda: len(peer.messages("SET_POSITION_TARGET_LOCAL_NED")) > 5, what="setpoints")
    target = {m.target_system for m, _, _ in peer.messages("SET_POSITION_TARGET_LOCAL_NED")}
    assert target == {peer.conn.mav.srcSystem}
    assert {m.get_srcSystem() for m, _, _ in peer.messages("HEARTBEAT")} == {peer.conn.mav.srcSystem}


def test_instance_1_is_followed_on_port_14541_by_its_system_id_2() -> None:
    base = free_port() - 1  # 14540 in SITL: instance 1 sends to base + 1
    with OffboardLink(fast_cfg(instance=1, base_port=base)) as link:
        assert link.address[1] == base + 1
        peer = FakePX4(base + 1, sysid=2)
        try:
            wait_until(lambda: link.connected, what="PX4 system 2")
            assert (link.sysid, link.compid) == (2, 1)
            _fly(link, peer)
        finally:
            peer.close()


def test_instances_past_9_share_14549_and_the_link_follows_its_system_id() -> None:
    """PX4 instances 10 (system 11) and 11 (system 12) both send to 14549: the link for instance 11
    follows system 12 only, placing itself at that PX4's estimate and sending only to it."""
    base = free_port() - 9
    with OffboardLink(fast_cfg(instance=11, base_port=base)) as link:
        assert link.address[1] == base + 9
        other = FakePX4(base + 9, sysid=11, local_ned=(1.0, 2.0, -3.0))
        ours = FakePX4(base + 9, sysid=12, local_ned=(4.0, -1.0, -2.5))
        try:
            wait_until(lambda: link.connected and link.other_systems, what="both PX4s heard")
            assert (link.sysid, link.other_systems) == (12, {11})
            _fly(link, ours)
            origin = frames.geodetic_to_enu(*HOME, *HOME)
            est = link.estimate().position
            want = origin + frames.ned_to_enu(np.array([4.0, -1.0, -2.5]))
            np.testing.assert_allclose(est, want, atol=1e-3)
            assert not other.messages("SET_POSITION_TARGET_LOCAL_NED") and not other.messages("COMMAND_LONG")
        finally:
            other.close()
            ours.close()


def partner_px4(port: int, sysid: int) -> FakePX4:
    """A FakePX4 sending to ``port`` that, like PX4's UDP MAVLink on localhost, takes the first sender
    as its partner and talks only to it from then on (pymavlink's ``udpbcast`` behaviour)."""
    peer = FakePX4(port, sysid=sysid)
    peer.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    peer.conn.broadcast = True
    wait_until(lambda: peer.conn.port.getsockname()[1] != 0, what="the peer's port")
    return peer


def test_a_second_link_for_14549_announces_itself_to_its_px4s_own_port() -> None:
    """One planner per vehicle past 9: the link for instance 10 holds 14549; the one for instance 11
    binds another port and sends its HEARTBEAT to PX4's own 14580 + 11, which PX4 then answers."""
    base = free_port() - 9
    px4_10 = FakePX4(base + 9, sysid=11)
    px4_11 = partner_px4(base + 9, sysid=12)
    own = px4_11.conn.port.getsockname()[1]  # PX4's udp_offboard_port_local, 14580 + 11
    links = []
    try:
        links.append(OffboardLink(fast_cfg(instance=10, base_port=base)))
        wait_until(lambda: links[0].connected, what="PX4 system 11")
        links.append(OffboardLink(fast_cfg(instance=11, base_port=base, px4_local_base_port=own - 11)))
        link10, link11 = links
        assert link10.address[1] == base + 9 and link10.announce_to is None
        assert link11.address[1] != base + 9 and link11.announce_to == ("127.0.0.1", own)
        wait_until(lambda: link11.connected, what="PX4 system 12 answering the announced link")
        assert (link10.sysid, link11.sysid) == (11, 12)
        _fly(link10, px4_10)
        _fly(link11, px4_11)
        time.sleep(0.2)
        assert link11.other_systems == set()  # system 11 never sent to the announced port
    finally:
        for link in links:
            link.close()
        px4_10.close()
        px4_11.close()


def test_no_px4_with_the_system_id_names_those_heard() -> None:
    base = free_port() - 9
    with OffboardLink(fast_cfg(instance=11, base_port=base, connect_timeout_s=1.0)) as link:
        peer = FakePX4(base + 9, sysid=11)
        try:
            wait_until(lambda: link.error is not None, what="the error")
            assert "instance 11 (system 12) running? (heard PX4 system 11" in link.error
            assert link.sysid is None
        finally:
            peer.close()
