"""Every script in ``examples/`` runs, as a user would run it, against a real simulator.

The WebSocket and Zenoh examples promise to need no droneulator import: they run here with
``droneulator`` made unimportable, against a ``droneulator run`` started by :func:`launch_run`.
``ros2_listener.py`` needs ROS 2 and zenoh-bridge-ros2dds, which are not installed: it is only
compiled; the RViz config is checked against the topic names the bridge really publishes.
"""

from __future__ import annotations

import ast
import json
import os
import py_compile
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from PIL import Image

from droneulator.config import CameraConfig, load_config
from droneulator.ros.topics import topic_names, vehicle_topics
from droneulator.runtime.launch import launch_run

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
CAM = CameraConfig(name="front", width=320, height=240)

#: runs an example as ``__main__`` with every ``import droneulator`` failing
_WITHOUT_DRONEULATOR = (
    "import runpy, sys; sys.modules['droneulator'] = None; "
    "sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')"
)


def run_example(name: str, *args: str, timeout: float, block_droneulator: bool = False):
    """Run ``examples/<name>`` with this interpreter; the finished process (output captured)."""
    path = str(EXAMPLES / name)
    cmd = [sys.executable, "-c", _WITHOUT_DRONEULATOR, path] if block_droneulator else [sys.executable, path]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [*cmd, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env, check=False
    )
    output = f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert proc.returncode == 0, f"{name} exited with {proc.returncode}:\n{output}"
    return proc


def test_ros2_listener_compiles(tmp_path):
    path = EXAMPLES / "ros2_listener.py"
    py_compile.compile(str(path), cfile=str(tmp_path / "ros2_listener.pyc"), doraise=True)
    tree = ast.parse(path.read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert imported == {"rclpy", "nav_msgs", "sensor_msgs"}  # ROS 2 only, no droneulator
    text = path.read_text()
    assert "/odom" in text and "/color/image_raw/compressed" in text


def test_standalone_examples_import_no_droneulator():
    """The two examples for users without droneulator import only the standard library and their package."""
    allowed = {"waypoints_ws.py": {"websockets"}, "subscribe_zenoh.py": {"zenoh", "rosbags"}}
    for name, packages in allowed.items():
        tree = ast.parse((EXAMPLES / name).read_text())
        mods = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        mods |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert mods - set(sys.stdlib_module_names) == packages, name


def test_rviz_config_matches_the_published_topics():
    cfg = load_config()
    ns, cam = cfg.bridge.namespace, cfg.render.cameras[0].name
    topics, vehicle = topic_names(ns, cam), vehicle_topics(ns)
    doc = yaml.safe_load((EXAMPLES / "rviz" / "droneulator.rviz").read_text())
    vm = doc["Visualization Manager"]
    displays = {d["Class"].split("/")[1]: d for d in vm["Displays"]}
    assert vm["Global Options"]["Fixed Frame"] == "odom"
    assert displays["TF"]["Enabled"]
    assert displays["Odometry"]["Topic"]["Value"] == vehicle["odom"] and displays["Odometry"]["Keep"] > 100
    assert displays["Image"]["Topic"]["Value"] == topics["rgb"]
    depth = displays["DepthCloud"]
    assert depth["Depth Map Topic"] == topics["depth"]
    assert depth["CameraInfo Topic"] == topics["info_depth"]
    assert all(d["Enabled"] for d in displays.values())


@pytest.mark.slow
def test_world_in_process(tmp_path):
    out = tmp_path / "out"
    args = ("--out", str(out), "--width", "160", "--height", "120")
    run_example("world_in_process.py", *args, timeout=400)
    s = json.loads((out / "summary.json").read_text())
    assert s["goto_error_m"] < 0.1
    assert s["frames_in_2s"] == 60  # 30 Hz camera in lockstep, none skipped
    assert s["landed"] and s["final_state"]["mode"] == "idle"
    assert {"GROUND", "SKY"} <= set(s["classes"])
    with Image.open(out / "front_rgb.png") as im:
        assert im.size == (160, 120)


@pytest.mark.slow
def test_gym_vineyard(tmp_path):
    summary_path = tmp_path / "episodes.json"
    run_example(
        "gym_vineyard.py", "--episodes", "1", "--steps", "60", "--summary", str(summary_path), timeout=400
    )
    (ep,) = json.loads(summary_path.read_text())
    assert ep["observation_shape"] == [35]
    assert ep["steps"] == 60 or ep["end"] in ("goal", "collision", "out_of_bounds", "time_limit")
    assert ep["sim_time_s"] == pytest.approx(ep["steps"] / 30.0, abs=0.02)  # one step per camera frame
    assert ep["path_distance_m"] < ep["start_path_distance_m"]  # the scripted policy makes progress


@pytest.fixture(scope="module")
def sim():
    """One ``droneulator run`` for the tests after it (they come last: it runs until the module ends)."""
    cfg = load_config(scene="default")
    cfg.render.cameras = [CAM]
    cfg.render.shadow_map_size = 1024
    with launch_run(cfg) as run:
        yield run


@pytest.mark.slow
def test_waypoints_ws(sim, tmp_path):
    summary_path = tmp_path / "summary.json"
    waypoints = "2,0,2 2,2,2.5 0,0,2"
    proc = run_example(
        "waypoints_ws.py",
        "--url",
        sim.url,
        "--waypoints",
        waypoints,
        "--summary",
        str(summary_path),
        timeout=300,
        block_droneulator=True,
    )
    s = json.loads(summary_path.read_text())
    with sim.client() as c:
        spawn = c.scene_info()["spawn_position"]
    expected = [[spawn[0] + x, spawn[1] + y, z] for x, y, z in ([2, 0, 2], [2, 2, 2.5], [0, 0, 2])]
    for sent, arrived, target in zip(s["waypoints"], s["arrived"], expected, strict=True):
        assert sent == pytest.approx(target, abs=1e-9)
        assert arrived == pytest.approx(target, abs=0.1)
    assert s["refused"] == "below_ground"  # the error reply it shows on purpose
    assert s["landed"][2] < 0.1 and s["final_state"]["mode"] == "idle"
    assert s["states_received"] > 0  # the pushed state stream arrived between the replies
    assert "refused as expected: below_ground" in proc.stdout


@pytest.mark.slow
def test_subscribe_zenoh(sim, tmp_path):
    out = tmp_path / "frames"
    summary_path = tmp_path / "summary.json"
    run_example(
        "subscribe_zenoh.py",
        "--connect",
        sim.zenoh_endpoint,
        "--frames",
        "20",
        "--seconds",
        "120",
        "--every",
        "5",
        "--out",
        str(out),
        "--summary",
        str(summary_path),
        timeout=180,
        block_droneulator=True,
    )
    s = json.loads(summary_path.read_text())
    assert s["images"] >= 20 and s["odometry"] > 0
    assert s["last_odometry"]["frame_id"] == "odom" and s["last_odometry"]["child_frame_id"] == "base_link"
    assert len(s["saved"]) >= 4
    for path in s["saved"]:
        with Image.open(path) as im:  # the published bytes are a complete JPEG of the camera's size
            assert im.format == "JPEG" and im.size == (CAM.width, CAM.height)
            im.load()
