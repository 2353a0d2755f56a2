"""The PyInstaller bundle: ``bash scripts/package.sh`` builds it, and it flies the demo on its own.

The first tests check :mod:`droneulator.runtime.spawn`, how every process starts a child, without a
bundle (``sys.frozen`` set by hand where the frozen branch is meant); the slow ones build the bundle.

The bundle is built from this checkout into a temporary folder, then run the way a user without
Python runs it: an empty environment (no venv on PATH, no PYTHONPATH, a fresh HOME) and only the
system's EGL/Mesa libraries. ``droneulator run --demo`` must start its three children from the
bundle's own executable (``droneulator _child <module>``), compile the numba kernels into the
user's cache, fly the mission over WebSocket and save the frames it received over Zenoh.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import pytest
from PIL import Image

from droneulator.runtime import spawn

ROOT = Path(__file__).resolve().parents[1]
CHILDREN = ("dynamics_server", "render_server", "bridge")


def clean_env(home: Path) -> dict[str, str]:
    """What ``env -i HOME=<home> PATH=/usr/bin:/bin`` leaves."""
    return {"HOME": str(home), "PATH": "/usr/bin:/bin"}


def test_commands_in_a_venv_run_python():
    assert spawn.child_command("droneulator.runtime.bridge") == [
        sys.executable,
        "-m",
        "droneulator.runtime.bridge",
    ]
    assert spawn.cli_command(["run", "--demo"]) == [sys.executable, "-m", "droneulator.cli", "run", "--demo"]
    assert spawn.code_command("pass") == [sys.executable, "-c", "pass"]


def test_commands_when_frozen_run_the_program_itself(monkeypatch):
    monkeypatch.setattr(sys, "frozen", True, raising=False)
    exe = sys.executable
    assert spawn.child_command("droneulator.runtime.bridge", ["-v"]) == [
        exe,
        "_child",
        "droneulator.runtime.bridge",
        "-v",
    ]
    assert spawn.cli_command(["run", "--demo"]) == [exe, "run", "--demo"]
    assert spawn.code_command("pass") == [exe, "_child", "-c", "pass"]
    with pytest.raises(ValueError, match="not a module name"):
        spawn.child_command("-m")


def test_hidden_child_command_runs_a_module_or_code(tmp_path):
    """``droneulator _child`` does what ``python -m`` / ``python -c`` do, exit status included."""
    data = tmp_path / "in.json"
    data.write_text('{"b": 1, "a": [2]}')
    cli = [sys.executable, "-m", "droneulator.cli", "_child"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    mod = subprocess.run(
        [*cli, "json.tool", "--sort-keys", str(data)], env=env, capture_output=True, text=True
    )
    assert mod.returncode == 0 and mod.stdout.index('"a"') < mod.stdout.index('"b"')
    bad = subprocess.run(
        [*cli, "json.tool", str(tmp_path / "missing")], env=env, capture_output=True, text=True
    )
    assert bad.returncode == 2  # the module's own SystemExit
    code = subprocess.run(
        [*cli, "-c", "import sys; print(__name__, sys.argv); sys.exit(3)"],
        env=env,
        capture_output=True,
        text=True,
    )
    assert code.returncode == 3 and code.stdout.strip() == "__main__ ['-c']"
    empty = subprocess.run(cli, env=env, capture_output=True, text=True)
    assert empty.returncode == 2 and "expected a module name" in empty.stderr
    help_text = subprocess.run(
        [sys.executable, "-m", "droneulator.cli", "--help"], env=env, capture_output=True, text=True
    ).stdout
    assert "run" in help_text and "_child" not in help_text


def test_a_server_process_that_crashes_in_native_code_leaves_its_python_stack():
    """A segfault in EGL, Zenoh or a kernel must say where: the servers enable faulthandler."""
    code = (
        "from droneulator.runtime.spawn import start_server_process\n"
        "import ctypes\n"
        "def render_frame():\n"
        "    ctypes.string_at(0)\n"
        "start_server_process()\n"
        "render_frame()\n"
    )
    out = subprocess.run(spawn.code_command(code), capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == -signal.SIGSEGV
    assert "Fatal Python error: Segmentation fault" in out.stderr
    assert "in render_frame" in out.stderr, out.stderr


def test_frozen_numba_cache_falls_back_when_unusable(monkeypatch, tmp_path, capsys):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setattr(sys, "frozen", True, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))  # <file>/numba cannot be created
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    spawn.configure_frozen()
    fallback = Path(os.environ["XDG_CACHE_HOME"])
    assert fallback == tmp_path / f"droneulator-cache-{os.getuid()}" and (fallback / "numba").is_dir()
    assert "is unusable" in capsys.readouterr().err

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    spawn.configure_frozen()
    assert os.environ["XDG_CACHE_HOME"] == str(tmp_path / "cache") and (tmp_path / "cache" / "numba").is_dir()


class Build:
    """``bash scripts/package.sh`` into a temporary folder, started when the suite's tests are collected
    (:func:`start_build`, from conftest.py) so that PyInstaller's two to three minutes overlap the tests
    before this module's, at a lower CPU priority (nice 10: it takes what they leave).

    One build serves the whole test run: pytest-xdist's workers share it through its folder
    (:func:`build_root`), which the first to get there creates; the build writes its exit code to
    ``rc`` when done, which is what every worker waits for."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.dist, self.work = root / "dist", root / "build"
        self.log_path, self.rc_path = root / "package.log", root / "rc"

    def start(self) -> None:
        package = shlex.join(
            ["bash", str(ROOT / "scripts" / "package.sh"), "--dist", str(self.dist), "--work", str(self.work)]
        )
        script = f"nice -n 10 {package} > package.log 2>&1; echo $? > rc.part && mv rc.part rc"
        self.proc = subprocess.Popen(
            ["bash", "-c", script],
            cwd=self.root,
            env={**os.environ, "PYTHON": sys.executable},
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # its own process group: stop_build ends all of it
        )
        (self.root / "pid").write_text(str(self.proc.pid))

    def wait(self, timeout: float) -> tuple[int, str]:
        """The build's exit code and output, once it is done."""
        deadline = time.monotonic() + timeout
        while not self.rc_path.exists():
            if time.monotonic() > deadline:
                raise TimeoutError(f"the bundle build in {self.root} did not finish within {timeout:g} s")
            time.sleep(0.5)
        return int(self.rc_path.read_text()), self.log_path.read_text()

    def close(self) -> None:
        """Stop the build if it still runs and remove its folder."""
        pid = self.root / "pid"
        if pid.exists() and not self.rc_path.exists():
            with contextlib.suppress(ProcessLookupError, PermissionError, ValueError):
                os.killpg(int(pid.read_text()), signal.SIGKILL)
        shutil.rmtree(self.root, ignore_errors=True)


_started: list[Build] = []


def build_root() -> Path:
    """This test run's bundle folder: named by ``DRONEULATOR_TEST_RUN``, which conftest.py sets once per
    run (pytest-xdist's workers inherit it), else by this process."""
    run = os.environ.get("DRONEULATOR_TEST_RUN", str(os.getpid()))
    return Path(tempfile.gettempdir()) / f"droneulator-bundle-{run}"


def start_build() -> Build:
    """The run's bundle build, started in the background by the first process to ask."""
    build = Build(build_root())
    try:
        build.root.mkdir()
    except FileExistsError:
        return build  # another worker started it
    build.start()
    _started.append(build)  # its Popen stays referenced while the build runs (a dropped one warns)
    return build


def stop_build() -> None:
    """Stop the run's build if it still runs and remove its folder (the suite's end, in the process that
    owns the run: pytest-xdist's controller, or pytest itself)."""
    Build(build_root()).close()


@pytest.fixture(scope="module")
def bundle() -> Path:
    """The bundle built with this interpreter's environment (started in the background when the tests
    were collected, or now); the path of its ``droneulator`` program."""
    build = start_build()
    code, output = build.wait(timeout=1500)
    assert code == 0, f"package.sh failed:\n{output[-6000:]}"
    print(output.strip().splitlines()[-1])  # sizes and build time, for the test log
    dist = build.dist
    tarballs = list(dist.glob("droneulator-*-linux-*.tar.gz"))
    assert len(tarballs) == 1, tarballs
    with tarfile.open(tarballs[0]) as tar:
        assert "droneulator/droneulator" in tar.getnames()
    exe = dist / "droneulator" / "droneulator"
    assert os.access(exe, os.X_OK)
    return exe


def _watch_children(pid: int, seen: dict[str, str], stop: threading.Event) -> None:
    """Record the command line of each child process of ``pid`` as it appears."""
    while not stop.is_set():
        out = subprocess.run(["ps", "-ww", "-o", "args=", "--ppid", str(pid)], capture_output=True, text=True)
        for args in out.stdout.splitlines():
            for name in CHILDREN:
                if f"droneulator.runtime.{name}" in args:
                    seen.setdefault(name, args.strip())
        stop.wait(0.2)


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_demo_runs_from_the_bundle_in_a_clean_environment(bundle, tmp_path):
    home, out = tmp_path / "home", tmp_path / "out"
    home.mkdir()
    started = time.monotonic()
    # a 320x240 camera without shadows: the same processes, kernels and streams, a quarter of llvmpipe's work
    small = ['render.cameras=[{"name": "front", "width": 320, "height": 240}]', "render.shadows=false"]
    # the API on a port that is free now and Zenoh on any: the defaults (8765, 7448) may be another test's
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        api_port = probe.getsockname()[1]
    ports = ["--api-port", str(api_port), "--set", 'bridge.listen=["tcp/127.0.0.1:0"]']
    proc = subprocess.Popen(
        [
            str(bundle),
            "run",
            "--scene",
            "default",
            "--demo",
            "--out",
            str(out),
            "--set",
            small[0],
            "--set",
            small[1],
            *ports,
        ],
        env=clean_env(home),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    seen: dict[str, str] = {}
    stop = threading.Event()
    watcher = threading.Thread(target=_watch_children, args=(proc.pid, seen, stop), daemon=True)
    watcher.start()
    try:
        output, _ = proc.communicate(timeout=900)
    finally:
        stop.set()
        watcher.join()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output[-5000:]
    print(f"demo from the bundle: {time.monotonic() - started:.0f} s wall")

    # three children, each started from the bundle's own executable, none from a Python interpreter
    assert set(seen) == set(CHILDREN), (seen, output[-3000:])
    for name, args in seen.items():
        assert args == f"{bundle} _child droneulator.runtime.{name}", args
    for tag in ("[dynamics]", "[render]", "[bridge]"):
        assert tag in output

    # the mission flew to the end and frames received over Zenoh were saved
    assert "event landed" in output and "demo finished" in output, output[-3000:]
    rgb = sorted(out.glob("*_front_rgb.jpg"))
    assert len(rgb) >= 10, sorted(p.name for p in out.iterdir())
    with Image.open(rgb[-1]) as im:
        assert im.format == "JPEG" and im.size == (320, 240)
    assert len(list(out.glob("*_front_depth.npy"))) == len(rgb)
    assert len(list(out.glob("*_front_seg.png"))) == len(rgb)

    # numba compiled into the user's cache (the bundle itself stays untouched)
    assert list((home / ".cache" / "numba").rglob("*.nbi")), "no numba cache index written"


@pytest.mark.slow
def test_pip_only_commands_say_so(bundle, tmp_path):
    for command, extra in (("train", "rl"), ("evaluate", "rl"), ("reconstruct", "colmap")):
        args = [str(bundle), command] + (["x"] if command != "train" else [])
        proc = subprocess.run(args, env=clean_env(tmp_path), capture_output=True, text=True, timeout=60)
        assert proc.returncode == 1
        assert "needs the pip install" in proc.stderr and f"droneulator[{extra}]" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_bundled_commands_run(bundle, tmp_path):
    """Commands that need no simulator answer from the bundle: the scene list, the config, a start-up
    error that names the setting to change; and the bundled data files load."""
    env = clean_env(tmp_path)
    scenes = subprocess.run([str(bundle), "scenes"], env=env, capture_output=True, text=True, timeout=120)
    assert scenes.returncode == 0
    assert {line.split()[0] for line in scenes.stdout.splitlines()} >= {"default", "orchard", "vineyard"}
    config = subprocess.run(
        [str(bundle), "config", "--set", "vehicle.params=crazyflie"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert config.returncode == 0 and '"params": "crazyflie"' in config.stdout
    bad = subprocess.run(
        [str(bundle), "run", "--scene", "nowhere"], env=env, capture_output=True, text=True, timeout=120
    )
    assert bad.returncode == 2 and bad.stderr.startswith("droneulator: error:") and "nowhere" in bad.stderr
    # data files collected: the WMM coefficients of wmm-calculator give the venv's field exactly
    from droneulator.sensors.mag import wmm_field_ned_gauss

    code = "from droneulator.sensors.mag import wmm_field_ned_gauss as f; print(*f(47.4, 8.5, 500.0, 2025.5))"
    wmm = subprocess.run(
        [str(bundle), "_child", "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert wmm.returncode == 0, wmm.stderr
    assert [float(v) for v in wmm.stdout.split()] == wmm_field_ned_gauss(47.4, 8.5, 500.0, 2025.5).tolist()
