"""Spraying in a run: the spray ops through a real WebSocket server (and their refusals, the flight going
on), the state that carries the spray system, a reset, and one end-to-end run whose spray state and
deposit grid arrive on ROS 2 over Zenoh."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from droneulator.api import ApiError, ApiServer, DroneulatorClient, handle_request
from droneulator.commands import CommandPath
from droneulator.config import load_config
from droneulator.ros.topics import SPRAY_FIELDS, spray_deposit_topic
from droneulator.spray.deposit import DEPOSIT_LOG_RANGE
from droneulator.world import World

TS = get_typestore(Stores.ROS2_JAZZY)
OVERRIDES = ["spray.enabled=true", "vehicle.params=sprayer10", "scene=default", "spray.parcels_per_s=300"]


class Rig:
    """A spraying world, its command path and a real API server, stepped by a thread."""

    def __init__(self) -> None:
        self.world = World(load_config(overrides=[*OVERRIDES, "spray.load_l=0.2"]), render=False)
        self.lock = threading.Lock()
        self.server = ApiServer(CommandPath(self.world, self.lock), port=0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                self.world.step(2)
                state = self.world.vehicle().state
            self.server.publish_state(state)
            time.sleep(0.002)

    def __enter__(self) -> Rig:
        self.server.start()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.server.stop()
        self.world.close()


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    with Rig() as r:
        yield r


def _code(c: DroneulatorClient, op: str, **args) -> str:
    with pytest.raises(ApiError) as err:
        c.request(op, **args)
    return err.value.code


def test_spray_ops_over_the_server_empty_the_tank_and_refuse_bad_input(rig):
    with DroneulatorClient(rig.server.url, timeout=10.0) as c:
        c.request("takeoff", altitude=2.0)
        before = c.request("state")
        assert before["spray"]["level_l"] == pytest.approx(0.2) and before["spray"]["on"] is False
        assert _code(c, "spray", rate=1.5) == "out_of_range"
        assert _code(c, "spray", rate="full") == "invalid_argument"
        assert _code(c, "spray", rate=1.0, nozzles=["boom"]) == "invalid_argument"
        assert _code(c, "spray", rate=1.0, nozzles=[]) == "invalid_argument"
        assert _code(c, "spray", rate=1.0, vehicle="nobody") == "invalid_argument"
        r = c.request("spray", rate=1.0, nozzles=["n0", "n1"])
        assert r["spray"]["on"] and r["spray"]["flow_l_min"] == pytest.approx(0.9)
        deadline = time.monotonic() + 60.0
        while c.request("state")["spray"]["level_l"] > 0.0:  # 0.2 L at 0.9 L/min: 13 s of sim time
            assert time.monotonic() < deadline, "the tank never emptied"
            time.sleep(0.2)
        state = c.request("state")
        assert state["spray"]["sprayed_l"] == pytest.approx(0.2) and not state["spray"]["on"]
        assert _code(c, "spray", rate=0.5) == "tank_empty"
        assert state["t"] > before["t"] and state["mode"] in ("hold", "takeoff")  # it flies on
        assert _code(c, "spray_refill", litres=11.0) == "out_of_range"
        refilled = c.request("spray_refill")
        assert refilled["spray"]["level_l"] == pytest.approx(0.2)
        with rig.lock:
            cloud = rig.world.spraying.cloud
            assert cloud.sprayed * 1000.0 == pytest.approx(0.2, rel=1e-9)
            assert rig.world.vehicle().quad_params["mass"] == pytest.approx(16.2, abs=0.011)


def test_spray_deposit_sends_the_picture_only_when_it_changed(rig):
    """Asked with the version it has, a client gets the picture only when more has landed (here the sim
    is held between the two asks); over the server the picture decodes to the grid's size."""
    with rig.lock:
        first = handle_request(rig.world, '{"op": "spray_deposit"}')["result"]
        again = handle_request(rig.world, json.dumps({"op": "spray_deposit", "since": first["version"]}))
        cloud = rig.world.spraying.cloud
    assert first["changed"] and again["result"] == {"version": first["version"], "changed": False}
    assert (first["width"], first["height"]) == cloud.ground_deposit().shape
    assert first["origin"] == pytest.approx(cloud.ground_origin.tolist())
    with DroneulatorClient(rig.server.url, timeout=10.0) as c:
        stale = c.request("spray_deposit", since=first["version"] + 1000)  # another run's version
        assert stale["changed"] and stale["version"] >= first["version"]
        assert _code(c, "spray_deposit", since=-1) == "out_of_range"


def test_a_reset_refills_the_tanks_and_clears_the_cloud():
    world = World(load_config(overrides=OVERRIDES), render=False)
    v = world.vehicle()
    v.takeoff(2.0)
    world.step(200)
    world.spraying.system(None).set(1.0)
    world.step(100)
    assert world.spraying.cloud.sprayed > 0 and v.quad_params["mass"] < 26.0
    sprayed = world.spraying.deposit_image()
    world.reset()
    cleared = handle_request(world, json.dumps({"op": "spray_deposit", "since": sprayed.version}))["result"]
    assert cleared["changed"] and cleared["version"] > sprayed.version and cleared["png"] != sprayed.png
    assert world.spraying.cloud.sprayed == 0.0 and world.spraying.cloud.count == 0
    assert world.spraying.system(None).level_l == 10.0 and not world.spraying.system(None).on
    assert v.quad_params["mass"] == pytest.approx(26.0)


def test_spray_ops_without_spray_systems_are_refused():
    world = World(scene="default", render=False)
    r = handle_request(world, '{"op": "spray", "rate": 1}')
    assert not r["ok"] and r["error"]["code"] == "no_spray_system"
    r = handle_request(world, '{"op": "spray_deposit"}')
    assert not r["ok"] and r["error"]["code"] == "no_spray_system"
    assert "spray" not in handle_request(world, '{"op": "state"}')["result"]


def _collect(into: list, typename: str):
    def cb(sample: zenoh.Sample) -> None:
        into.append(TS.deserialize_cdr(sample.payload.to_bytes(), typename))

    return cb


@pytest.mark.slow
def test_a_run_publishes_the_spray_state_and_the_deposit_on_ros(tmp_path):
    from mcap.reader import make_reader

    from droneulator.recording.recorder import Recorder, RecorderConfig
    from droneulator.runtime.launch import launch_run

    cfg = load_config(overrides=[*OVERRIDES, "render.camera_hz=2"])
    cfg.render.cameras = cfg.render.cameras[:1]
    launched = launch_run(cfg, ())
    got: dict[str, list] = {"state": [], "deposit": []}
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([launched.zenoh_endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    keys = {"state": "droneulator/spray/state", "deposit": spray_deposit_topic("droneulator").lstrip("/")}
    types = {"state": "std_msgs/msg/Float64MultiArray", "deposit": "nav_msgs/msg/OccupancyGrid"}
    subs = [session.declare_subscriber(keys[k], _collect(got[k], types[k])) for k in keys]
    recorder = Recorder(tmp_path / "spray.mcap", RecorderConfig(connect=(launched.zenoh_endpoint,)))
    recorder.start()
    stats = None
    try:
        with launched.client() as c:
            c.request("takeoff", altitude=2.5)
            c.request("spray", rate=1.0)
            deadline = time.monotonic() + 120.0
            while True:
                grids = list(got["deposit"])
                if grids and np.asarray(grids[-1].data).max() > 0:
                    break
                assert time.monotonic() < deadline, "no deposit arrived\n" + "\n".join(
                    launched.log.lines()[-20:]
                )
                time.sleep(0.2)
            state = got["state"][-1]
            assert [d.label for d in state.layout.dim] == list(SPRAY_FIELDS)
            rate, level, tank = state.data[:3]
            assert rate == 1.0 and 0.0 < level < tank == 10.0
            grid = grids[-1]
            assert grid.header.frame_id == "map" and grid.info.resolution == pytest.approx(
                cfg.spray.grid_cell_m
            )
            values = np.asarray(grid.data).reshape(grid.info.height, grid.info.width)
            # the deposit lies under the vehicle, round the scene's spawn (the origin)
            iy, ix = np.unravel_index(np.argmax(values), values.shape)
            x = grid.info.origin.position.x + (ix + 0.5) * grid.info.resolution
            y = grid.info.origin.position.y + (iy + 0.5) * grid.info.resolution
            assert np.hypot(x, y) < 2.0
            assert values.max() <= 100 and DEPOSIT_LOG_RANGE[0] < DEPOSIT_LOG_RANGE[1]
        stats = recorder.close()
        assert stats.written.get("/droneulator/spray/state", 0) > 0
        assert stats.written.get("/droneulator/spray/deposit", 0) > 0
        with open(tmp_path / "spray.mcap", "rb") as f:
            channels = {c.topic: c for c in make_reader(f).get_summary().channels.values()}
        assert {"/droneulator/spray/state", "/droneulator/spray/deposit"} <= set(channels)
    finally:
        if stats is None:
            recorder.close()
        for s in subs:
            s.undeclare()
        session.close()
        launched.stop()
