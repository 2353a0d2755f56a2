"""Start-up failures a user can cause: ``droneulator run`` / ``demo`` / ``snapshot`` as real subprocesses
end in one ``droneulator: error:`` line and a non-zero exit before any simulator process starts.

Ports are taken by real listening sockets; EGL is made unavailable to the command for real (glvnd finds
no vendor library). While a command runs, its process tree is sampled from ``/proc`` so a simulator
child (``droneulator.runtime.*``) that starts at all is seen.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from droneulator.config import load_config
from droneulator.runtime import preflight
from droneulator.runtime.preflight import Listen, StartupError
from droneulator.runtime.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[1]
#: every port the run would use left to the OS (port 0 is not checked), so only the one under test counts
FREE_PORTS = ["--api-port", "0", "--set", 'bridge.listen=["tcp/127.0.0.1:0"]']
NO_EGL = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent"}
#: wall-clock bound for a failed start-up (no child started is checked apart): 15 s held on a 2-core machine
#: with a core busy, up to 21 s were seen with a dozen jobs beside the suite
QUICK_S = 40.0


@dataclass
class Outcome:
    code: int
    stdout: str
    stderr: str
    wall_s: float
    children: list[str]


def _descendants(root: int) -> dict[int, str]:
    """pid -> command line of every live descendant of ``root``."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found: dict[int, str] = {}
    frontier = [root]
    while frontier:
        pid = frontier.pop()
        for child, parent in parents.items():
            if parent == pid and child not in found:
                try:
                    cmd = Path(f"/proc/{child}/cmdline").read_bytes().replace(b"\0", b" ").decode()
                except OSError:
                    cmd = ""
                found[child] = cmd
                frontier.append(child)
    return found


def droneulator(*args: str, env: dict[str, str] | None = None, timeout: float = 60.0) -> Outcome:
    """Run ``python -m droneulator.cli ARGS`` and watch its process tree until it exits."""
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "droneulator.cli", *args],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    children: set[str] = set()
    try:
        while proc.poll() is None and time.monotonic() - t0 < timeout:
            children.update(_descendants(proc.pid).values())
            time.sleep(0.02)
        stdout, stderr = proc.communicate(timeout=max(1.0, timeout - (time.monotonic() - t0)))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return Outcome(proc.returncode, stdout, stderr, time.monotonic() - t0, sorted(children))


def assert_one_line_error(out: Outcome, code: int, *needles: str) -> str:
    """Exit ``code``, stderr exactly one ``droneulator: error:`` line holding every needle, no traceback,
    no simulator child, and quickly."""
    lines = out.stderr.splitlines()
    assert len(lines) == 1, out.stderr
    line = lines[0]
    assert line.startswith("droneulator: error: "), line
    for needle in needles:
        assert needle in line, (needle, line)
    assert out.code == code, (out.code, line)
    assert "Traceback" not in out.stdout + out.stderr
    assert "[dynamics]" not in out.stdout and "[render]" not in out.stdout, out.stdout
    assert not [c for c in out.children if "droneulator.runtime." in c], out.children
    assert out.wall_s < QUICK_S, out.wall_s
    return line


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A port held by a real listening socket (SO_REUSEADDR, as the servers set: still reported)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


# --------------------------------------------------------------------------- ports (droneulator run)
def test_a_demo_on_any_api_port_is_refused(tmp_path: Path) -> None:
    """``run --demo`` flies through the API, so it must know the port: 0 (any free one) is refused."""
    out = droneulator("run", "--demo", "--out", str(tmp_path / "demo"), *FREE_PORTS)
    assert_one_line_error(out, 2, "--demo", "--api-port N")


def test_run_api_port_taken(taken_port: int) -> None:
    out = droneulator("run", *FREE_PORTS, "--api-port", str(taken_port))
    line = assert_one_line_error(
        out, 1, f"API port {taken_port} on 127.0.0.1", "already in use", "--api-port"
    )
    assert "--set runtime.api_port=N" in line


def test_run_zenoh_port_taken(taken_port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{taken_port}"
    out = droneulator("run", *FREE_PORTS, "--set", f'bridge.listen=["udp/127.0.0.1:9", "{endpoint}"]')
    assert_one_line_error(out, 1, f"Zenoh port {taken_port}", endpoint, "already in use", "bridge.listen")


def test_run_px4_port_taken(taken_port: int) -> None:
    out = droneulator("run", *FREE_PORTS, "--px4", "--set", f"px4.base_port={taken_port}")
    assert_one_line_error(
        out, 1, f"PX4 SITL port {taken_port}", "already in use", "--px4-instance", "px4.base_port"
    )
    # instance N listens on base_port + N
    out = droneulator("run", *FREE_PORTS, "--px4-instance", "2", "--set", f"px4.base_port={taken_port - 2}")
    assert_one_line_error(out, 1, f"PX4 SITL port {taken_port}", "px4.instance 2", "already in use")


def test_run_ardupilot_udp_port_taken() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        # instance N answers on base_port + 10 N
        base = f"ardupilot.base_port={port - 10}"
        out = droneulator("run", *FREE_PORTS, "--ardupilot-instance", "1", "--set", base)
        assert_one_line_error(
            out, 1, f"ArduPilot SITL port {port}", "already in use", "--ardupilot-instance", "base_port"
        )


def test_run_port_free_without_px4_is_not_checked(taken_port: int) -> None:
    cfg = load_config(None, [f"px4.base_port={taken_port}", 'bridge.listen=["tcp/127.0.0.1:0"]'])
    assert [p.what for p in preflight.run_ports(cfg)] == ["API", "Zenoh"]


def test_run_same_port_twice_is_a_usage_error() -> None:
    out = droneulator("run", "--api-port", "7448", "--set", 'bridge.listen=["tcp/127.0.0.1:7448"]')
    assert_one_line_error(
        out, 2, "API port 7448", "Zenoh port 7448", "same port", "--api-port", "bridge.listen"
    )


# --------------------------------------------------------------------------- scene and config (every command)
def _sim_args(command: str, tmp_path: Path) -> list[str]:
    return [command, *FREE_PORTS] if command == "run" else [command, "--out", str(tmp_path / "out")]


@pytest.mark.parametrize("command", ["run", "demo", "snapshot"])
def test_unknown_scene(command: str, tmp_path: Path) -> None:
    out = droneulator(*_sim_args(command, tmp_path), "--scene", "moon")
    assert_one_line_error(out, 2, "unknown scene 'moon'", "default", "vineyard", "tree_inspection", "--scene")


BAD_FILES = {
    "missing": ("missing.json", None, "no such file"),
    "json": ("bad.json", '{"runtime": {"api_port": 1,}}', "not valid JSON"),
    "toml": ("bad.toml", "[runtime\napi_port = 1\n", "not valid TOML"),
    "yaml": ("bad.yaml", "runtime:\n  api_port: [1\n", "not valid YAML"),
    "unknown key": ("unknown.toml", "[render]\nshadowz = false\n", "render.shadowz"),
    "wrong type": ("type.json", '{"runtime": {"api_port": [8765]}}', "runtime.api_port"),
    "not a table": ("list.json", "[1, 2]", "expected a table"),
}


@pytest.mark.parametrize("kind", list(BAD_FILES))
@pytest.mark.parametrize("command", ["run", "demo", "snapshot"])
def test_bad_config_file(command: str, kind: str, tmp_path: Path) -> None:
    name, text, needle = BAD_FILES[kind]
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    out = droneulator(*_sim_args(command, tmp_path), "--config", str(path))
    assert_one_line_error(out, 2, f"--config {path}", needle)


@pytest.mark.parametrize(
    ("override", "needles"),
    [
        ("runtime.api_port=eighty", ("runtime.api_port", "expected int", "'eighty'")),
        ("bridge.listen=tcp/127.0.0.1:7448", ("bridge.listen", "expected a list")),
        ("render.shadows=maybe", ("render.shadows", "not a boolean")),
        ('render.cameras=[{"widht": 5}]', ("render.cameras[0].widht",)),
        ("vehicle.wind=gale", ("vehicle.wind", "dryden")),
        ("vehicle.params=zeppelin", ("vehicle parameter set 'zeppelin'", "hummingbird", "vehicle.params")),
        ("no_equals_sign", ("section.key=value",)),
        ('vehicle.sensors=["imu", "lidar"]', ("vehicle.sensors", "unknown sensor kind 'lidar'")),
        ('vehicles=[{"name": "a", "sensors": ["camera"]}]', ("vehicle 'a': sensors", "under 'cameras'")),
    ],
)
def test_bad_set_value(override: str, needles: tuple[str, ...]) -> None:
    out = droneulator("run", *FREE_PORTS, "--set", override)
    assert_one_line_error(out, 2, *needles)


def test_tls_files_that_cannot_be_loaded_are_a_one_line_error(tmp_path: Path) -> None:
    bad = tmp_path / "cert.pem"
    bad.write_text("not a certificate\n")
    tls = ["--set", f"access.tls_cert={bad}", "--set", f"access.tls_key={bad}"]
    out = droneulator("run", *FREE_PORTS, *tls)
    assert_one_line_error(out, 2, "access.tls_cert", str(bad), "cannot be loaded")
    assert "access token" not in out.stdout  # on loopback: no token generated
    out = droneulator("run", *FREE_PORTS, "--set", "access.tls_cert=cert.pem")
    assert_one_line_error(out, 2, "access.tls_cert and access.tls_key go together")


def test_a_px4_vehicle_without_a_magnetometer_is_caught_before_the_children() -> None:
    out = droneulator("run", *FREE_PORTS, "--px4", "--set", 'vehicle.sensors=["imu", "baro", "gps"]')
    assert_one_line_error(out, 2, "vehicle.sensors", "PX4 needs imu, mag, baro", "mag missing")


def test_px4_instance_out_of_range_is_caught_before_the_children() -> None:
    out = droneulator("run", *FREE_PORTS, "--px4-instance", "300")
    assert_one_line_error(out, 2, "px4.instance")


def test_ardupilot_with_px4_or_out_of_range_or_without_an_imu_is_caught_before_the_children() -> None:
    out = droneulator("run", *FREE_PORTS, "--px4", "--ardupilot")
    assert_one_line_error(out, 2, "--px4 and --ardupilot")
    out = droneulator("run", *FREE_PORTS, "--ardupilot-instance", "7000")
    assert_one_line_error(out, 2, "ardupilot.instance")
    out = droneulator("run", *FREE_PORTS, "--ardupilot", "--set", 'vehicle.sensors=["baro", "gps"]')
    assert_one_line_error(out, 2, "vehicle.sensors", "ArduPilot's JSON interface needs an imu")


# --------------------------------------------------------------------------- EGL
def test_egl_probe_succeeds_here() -> None:
    """The no-EGL tests below are meaningful only if EGL works without the sabotage."""
    preflight.check_egl()


@pytest.mark.parametrize("command", ["run", "demo", "snapshot"])
def test_no_egl(command: str, tmp_path: Path) -> None:
    out = droneulator(*_sim_args(command, tmp_path), env=NO_EGL)
    assert_one_line_error(
        out,
        1,
        "no OpenGL context through EGL",
        "libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri",
        "scripts/setup.sh",
    )


# --------------------------------------------------------------------------- preflight units
def _time_wait_port() -> int:
    """A port whose only socket is in TIME_WAIT (the server side closed first), as after an earlier run."""
    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        accepted, _ = server.accept()
        accepted.close()
        time.sleep(0.05)
        client.close()
    time.sleep(0.05)
    return port


def test_time_wait_port_is_not_reported_but_a_listening_one_is(taken_port: int) -> None:
    port = _time_wait_port()
    with socket.socket() as plain, pytest.raises(OSError):
        plain.bind(("127.0.0.1", port))  # the TIME_WAIT socket is really there
    preflight.check_port(Listen("API", "127.0.0.1", port, "--api-port", "--set runtime.api_host=HOST"))
    with pytest.raises(StartupError, match=f"API port {taken_port} on 127.0.0.1 is already in use"):
        preflight.check_port(Listen("API", "127.0.0.1", taken_port, "--api-port", "-"))


def test_wildcard_host_sees_a_port_taken_on_loopback(taken_port: int) -> None:
    with pytest.raises(StartupError, match="already in use"):
        preflight.check_port(Listen("API", "0.0.0.0", taken_port, "--api-port", "-"))


@pytest.mark.parametrize(
    ("endpoint", "parsed"),
    [
        ("tcp/127.0.0.1:7448", ("127.0.0.1", 7448)),
        ("tcp/[::1]:7449", ("::1", 7449)),
        ("tcp/localhost:7450?rel=1#iface=lo", ("localhost", 7450)),
        ("tls/0.0.0.0:7447", ("0.0.0.0", 7447)),
        ("udp/127.0.0.1:7448", None),
        ("unixsock-stream//tmp/z.sock", None),
    ],
)
def test_parse_tcp_endpoint(endpoint: str, parsed: tuple[str, int] | None) -> None:
    assert preflight.parse_tcp_endpoint(endpoint) == parsed


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1", "tcp/:7448", "tcp/host:port", "tcp"])
def test_malformed_tcp_endpoint(endpoint: str) -> None:
    with pytest.raises(StartupError, match="not tcp/HOST:PORT") as err:
        preflight.parse_tcp_endpoint(endpoint)
    assert err.value.exit_code == preflight.USAGE


def test_zenoh_config_file_endpoints_are_checked(tmp_path: Path, taken_port: int) -> None:
    conf = tmp_path / "zenoh.json5"
    conf.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": [f"tcp/127.0.0.1:{taken_port}"]}}))
    # the API on any free port: the default 8765 may be another test's, which made this check fail on it
    cfg = load_config(None, ["bridge.listen=[]", f"bridge.zenoh_config={conf}", "runtime.api_port=0"])
    with pytest.raises(StartupError, match=f"Zenoh port {taken_port}.*already in use"):
        preflight.check_ports(preflight.run_ports(cfg))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ listen: ")
    cfg = load_config(None, [f"bridge.zenoh_config={bad}"])
    with pytest.raises(StartupError, match="bridge.zenoh_config") as err:
        preflight.run_ports(cfg)
    assert err.value.exit_code == preflight.USAGE


# --------------------------------------------------------------------------- the supervisor's own start-up
def failed_start(overrides: list[str]) -> tuple[str, Supervisor]:
    """Start a Supervisor that must fail; its one-line message (checked) and the supervisor."""
    sup = Supervisor(load_config(None, [*overrides, 'bridge.listen=["tcp/127.0.0.1:0"]']))
    try:
        with pytest.raises(RuntimeError) as err:
            sup.start()
    finally:
        sup.stop()
    message = str(err.value)
    assert "\n" not in message and "Traceback" not in message
    assert sup.children["render"].proc is None and sup.children["bridge"].proc is None
    return message, sup


def test_supervisor_start_failure_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """A dynamics server that dies while starting (here: a parameter set preflight would have refused)
    gives one line naming its error; its traceback goes to the log file the line names."""
    message, _ = failed_start(["vehicle.params=zeppelin", "runtime.api_port=0"])
    assert "the dynamics server stopped while starting (exit code 1)" in message
    assert "unknown vehicle parameter set 'zeppelin'" in message
    log_file = Path(message.rsplit("its full output: ", 1)[1])
    try:
        assert "Traceback" in log_file.read_text()
    finally:
        log_file.unlink()
    assert "Traceback" not in capsys.readouterr().out


def test_a_port_taken_after_the_checks_is_still_one_line() -> None:
    """The race preflight cannot close (the API port taken between the check and the bind): the
    dynamics server binds every port before its hub socket appears, so the supervisor still reports
    one line and never starts the render server or the bridge."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        message, _ = failed_start([f"runtime.api_port={port}"])
    assert "the dynamics server stopped while starting" in message
    assert "address already in use" in message.lower() and str(port) in message
    Path(message.rsplit("its full output: ", 1)[1]).unlink(missing_ok=True)


def test_reconstruct_help_states_the_dense_scale_default() -> None:
    """``reconstruct --help`` names the dense scale that runs when the option is left out."""
    from droneulator.cli import build_parser
    from droneulator.workflows.photogrammetry.mvs import MvsOptions

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    action = next(a for a in sub.choices["reconstruct"]._actions if a.dest == "dense_scale")
    assert action.default is None and f"{MvsOptions().scale}" in action.help


# --------------------------------------------------------------------------- --vehicles N
def test_vehicles_shorthand_names_a_fleet_that_inherits_the_single_vehicle_sections() -> None:
    out = droneulator("config", "--vehicles", "3", "--set", "vehicle.params=crazyflie")
    assert out.code == 0, out.stderr
    cfg = json.loads(out.stdout)
    assert [v["name"] for v in cfg["vehicles"]] == ["uav0", "uav1", "uav2"]
    assert all(v["params"] is None and v["spawn"] is None for v in cfg["vehicles"])
    specs = load_config(overrides=["vehicle.params=crazyflie", f"vehicles={json.dumps(cfg['vehicles'])}"])
    assert [s.params for s in specs.vehicle_specs()] == ["crazyflie"] * 3


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (("--vehicles", "0"), ("--vehicles 0", "at least one")),
        (("--vehicles", "2", "--set", 'vehicles=[{"name": "a"}]'), ("--vehicles 2", "'vehicles' list")),
        (("--vehicles", "2000"), ("room near its spawn", "not 2000")),
    ],
)
def test_bad_vehicle_count(args: tuple[str, ...], needles: tuple[str, ...], tmp_path: Path) -> None:
    out = droneulator("snapshot", "--out", str(tmp_path / "out"), *args)
    assert_one_line_error(out, 2, *needles)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_snapshot_of_a_fleet_writes_each_vehicles_cameras_from_its_own_start(tmp_path: Path) -> None:
    out = droneulator("snapshot", "--vehicles", "2", "--out", str(tmp_path), "--set", "render.shadows=false")
    assert out.code == 0, out.stderr
    optical = {}
    for name in ("uav0", "uav1"):
        files = {p.name for p in (tmp_path / name).iterdir()}
        assert {"front_rgb.png", "front_depth.npy", "front_seg_ids.png", "front_camera_info.json"} <= files
        info = json.loads((tmp_path / name / "front_camera_info.json").read_text())
        optical[name] = info["optical_position"]
    (x0, y0, z0), (x1, y1, z1) = optical.values()
    assert math.hypot(x1 - x0, y1 - y0) >= 2.0 - 1e-9  # the scene's spawn pattern: 2 m apart
    assert z0 == pytest.approx(z1)
