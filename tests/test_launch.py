"""``launch_run``: a real ``droneulator run`` child on free ports, its failures and its shutdown."""

from __future__ import annotations

import os
import socket
import subprocess
import threading
import time

import pytest

from droneulator.config import load_config
from droneulator.ros.topics import TYPES, stamp_to_ns, vehicle_topics
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.launch import LaunchError, _ephemeral_range, free_port, launch_run

pytestmark = pytest.mark.slow


def ps(*select: str) -> list[str]:
    """Command lines of the live processes ``ps`` selects (zombies waiting for init are not alive)."""
    out = subprocess.run(["ps", "-o", "stat=,args=", *select], capture_output=True, text=True)
    return [line.split(None, 1)[1] for line in out.stdout.splitlines() if not line.lstrip().startswith("Z")]


def test_free_ports_are_distinct_bindable_and_outside_the_ephemeral_range():
    """A port handed out for a server started later must not be taken meanwhile by an outgoing connection
    (those take ephemeral source ports) or handed out again: either could explain the one UI test run
    that found its just-started run gone."""
    lo, hi = _ephemeral_range()
    ports = [free_port() for _ in range(300)]
    assert len(set(ports)) == len(ports)
    assert all(p >= 20000 and not lo <= p <= hi for p in ports)
    with socket.socket() as server, socket.socket() as client:
        server.bind(("127.0.0.1", ports[0]))
        server.listen()
        client.connect(("127.0.0.1", ports[0]))
        assert lo <= client.getsockname()[1] <= hi  # an outgoing connection's source port is ephemeral


def test_reserved_options_are_refused_before_anything_starts():
    for args in (["--api-port", "9000"], ["--set", "bridge.listen=[]"], ["--scene=orchard"]):
        with pytest.raises(ValueError, match="launch_run sets"):
            launch_run(load_config(), args)


def test_a_run_that_dies_or_does_not_answer_raises_with_its_log_and_is_gone():
    with pytest.raises(LaunchError) as err:
        launch_run(load_config(scene="no_such_scene"))
    assert "exited with code" in str(err.value) and "unknown scene 'no_such_scene'" in str(err.value)

    t0 = time.monotonic()
    with pytest.raises(LaunchError, match="did not answer on ws://127.0.0.1:[0-9]+ within 0.3 s"):
        launch_run(load_config(), start_timeout=0.3)
    assert time.monotonic() - t0 < 15
    assert not [c for c in ps("--ppid", str(os.getpid())) if "droneulator" in c]


def test_a_run_serves_its_api_and_topics_on_the_chosen_ports_and_stops_cleanly(tmp_path):
    cfg = load_config(None, ['render.cameras=[{"width": 160, "height": 120}]', "render.shadows=false"])
    with launch_run(cfg, ["--realtime"], log=tmp_path / "run.log") as run:
        assert cfg.runtime.api_port == 8765 and cfg.bridge.listen == ["tcp/127.0.0.1:7448"]  # untouched
        assert run.url == f"ws://127.0.0.1:{run.config.runtime.api_port}" and run.url != "ws://127.0.0.1:8765"
        assert run.config.bridge.listen == [run.zenoh_endpoint]
        with run.client() as client:
            assert client.scene_info()["name"] == "default"
            assert client.state()["mode"] == "idle"
        got: list[int] = []
        arrived = threading.Event()

        def on_clock(msg) -> None:
            got.append(stamp_to_ns(msg.clock))
            arrived.set()

        with RosZenohNode.from_config(cfg.bridge, listen=(), connect=(run.zenoh_endpoint,)) as node:
            node.subscribe(vehicle_topics("droneulator")["clock"], TYPES["clock"], on_clock)
            assert arrived.wait(30), "no /clock from the run's Zenoh endpoint"
        assert run.running() and got[0] >= 0
        deadline = time.monotonic() + 30  # the API answers first; the render server and bridge follow
        while "bridge ready" not in run.log.tail(200):
            assert time.monotonic() < deadline, "the bridge never started"
            time.sleep(0.1)
    assert run.proc.returncode == 0  # SIGTERM: an orderly shutdown
    # the whole group (dynamics, render, bridge) is gone; a child may still be tearing down its memory
    # for a moment (``ps`` shows it as ``[python]``) on a loaded machine
    deadline = time.monotonic() + 5
    while ps("-g", str(run.pid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert ps("-g", str(run.pid)) == []
    assert "bridge ready" in (tmp_path / "run.log").read_text()
    assert "bridge ready" in run.log.tail(200)


def test_lines_said_by_many_threads_at_once_reach_a_pipe_whole_and_in_order():
    """A run's stdout carries its children's relayed output (one thread each) beside its own lines (``UI:``,
    the demo's telemetry); ``print`` writes a line and its newline apart, and a run's ``UI:`` line was seen
    glued to a relayed one. :func:`~droneulator.logs.say` keeps every line whole, each thread's in order."""
    import io
    import re

    from droneulator.logs import say

    r, w = os.pipe()
    # stdout as ``python -u`` or PYTHONUNBUFFERED (CI's) makes it: every write a system call, which lets
    # another thread in between a line and its newline (with ``print`` here, about 100 of 8,000 lines broke)
    out = io.TextIOWrapper(os.fdopen(w, "wb", buffering=0), encoding="utf-8", write_through=True)
    received: list[str] = []

    def read() -> None:
        with os.fdopen(r, encoding="utf-8") as f:
            received.extend(f.read().splitlines())

    def talk(k: int) -> None:
        for i in range(2000):
            say(f"[thread {k}] line {i} " + "x" * (i % 97), out)

    reader = threading.Thread(target=read)
    reader.start()
    talkers = [threading.Thread(target=talk, args=(k,)) for k in range(4)]
    for t in talkers:
        t.start()
    for t in talkers:
        t.join()
    out.close()
    reader.join(10)
    assert len(received) == 8000
    for k in range(4):
        mine = [line for line in received if line.startswith(f"[thread {k}] ")]
        assert mine == [f"[thread {k}] line {i} " + "x" * (i % 97) for i in range(2000)]
    assert all(re.fullmatch(r"\[thread \d\] line \d+ x*", line) for line in received)
