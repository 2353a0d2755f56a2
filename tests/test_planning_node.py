"""The planner process end to end: `droneulator run` (lockstep) + the plan node, talking only over Zenoh."""

from __future__ import annotations

import time

import numpy as np
import pytest

from droneulator.config import CameraConfig, load_config
from droneulator.ros import messages as M
from droneulator.ros.topics import ODOM_FRAME
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.launch import launch_run
from droneulator.workflows.planning.node import GOAL_TYPE, PlanNode, PlanNodeConfig

CAM = CameraConfig(name="front", width=320, height=240)


def _run_config():
    cfg = load_config(scene="tree_inspection")
    cfg.render.cameras = [CAM]
    cfg.render.shadow_map_size = 512
    return cfg


@pytest.mark.slow
def test_plan_node_flies_to_a_goal_sent_over_zenoh_and_refuses_an_occupied_or_far_goal():
    cfg = _run_config()
    ns = cfg.bridge.namespace
    with launch_run(cfg) as run:
        client = run.client()
        node = PlanNode(PlanNodeConfig(zenoh=run.zenoh_endpoint, namespace=ns, camera=CAM.name))
        # a second, independent session sends the goals, like RViz through a bridge would
        sender = RosZenohNode.from_config(run.config.bridge, listen=(), connect=(run.zenoh_endpoint,))
        goals = sender.publisher(node.topics["goal"], GOAL_TYPE)
        try:
            client.reset(position=[0.0, -8.0, 0.0], yaw=0.0)
            client.subscribe(["events"])
            client.takeoff(altitude=2.0)
            client.wait_for_event("arrived", timeout=60)
            start = np.array(client.state()["position"])

            # far outside the 20 m local map: refused, nothing commanded
            goals.publish(M.serialize(M.pose_stamped(0, ODOM_FRAME, [0.0, 40.0, 2.0], [0, 0, 0, 1])))
            deadline = time.monotonic() + 20
            while node.failures == 0:
                assert time.monotonic() < deadline, "the bad goal was never answered"
                time.sleep(0.05)
            assert "outside the local map" in node.last_failure
            assert node.commands == 0

            goal = start + [3.0, 0.0, 0.0]
            goals.publish(M.serialize(M.pose_stamped(0, ODOM_FRAME, goal, [0, 0, 0, 1])))
            assert node.reached.wait(timeout=45), f"goal not reached; last failure: {node.last_failure!r}"
            state = client.state()
            assert np.linalg.norm(np.array(state["position"]) - goal) < 0.3
            assert state["mode"] == "track"
            assert node.plans >= 1 and node.commands > 100
            collisions = [
                m for m in client.messages(timeout=0.5)
                if m.get("type") == "event" and m["event"].get("type") == "collision"
            ]  # fmt: skip
            assert not collisions
        finally:
            sender.close()
            node.close()
            client.close()
