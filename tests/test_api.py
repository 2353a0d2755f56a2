"""WebSocket command API: the protocol alone, then a real server on 127.0.0.1 (port 0) in front of a
real World that a background thread steps while holding the shared lock, like the runtime does."""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from droneulator.api import ApiError, ApiServer, DroneulatorClient, handle_request
from droneulator.commands import CommandPath
from droneulator.commands.ops import ERROR_CODES, OPS, ops_markdown
from droneulator.world import World

DOCS = Path(__file__).resolve().parents[1] / "docs" / "api.md"
STEPS_PER_TICK = 5  # control periods per 10 ms tick: the simulation runs at ~5x real time
MAX_MESSAGE = 4096


# --------------------------------------------------------------------------- protocol alone
@pytest.fixture()
def bare_sim() -> Iterator[World]:
    s = World(scene="default", render=False)
    yield s
    s.close()


def test_docs_carry_the_generated_op_reference():
    docs = DOCS.read_text()
    assert ops_markdown() in docs, "regenerate the section from droneulator.commands.ops.ops_markdown()"
    for name in OPS:
        assert f"### `{name}`" in docs
    for code in ERROR_CODES:
        assert f"`{code}`" in docs


def test_handle_request_runs_every_op(bare_sim):
    sim = bare_sim
    r = handle_request(sim, '{"id": "a", "op": "ping"}')
    assert r["id"] == "a" and r["ok"] and r["result"]["pong"] is True
    info = handle_request(sim, json.dumps({"id": 1, "op": "scene_info"}))["result"]
    assert info["name"] == "default" and info["bounds_min"] == [-30.0, -30.0, 0.0]
    assert isinstance(info["landmarks"]["trunks"], list) and "vineyard" in info["scenes"]
    json.dumps(info, allow_nan=False)
    assert handle_request(sim, '{"op": "state"}')["result"]["mode"] == "idle"
    r = handle_request(sim, '{"id": 2, "op": "takeoff", "altitude": 1.5}')
    assert r == {"id": 2, "ok": True, "result": {"duration": pytest.approx(3.28125), "t": 0.0, "stamp_ns": 0}}
    sim.run(1.0)
    r = handle_request(sim, '{"op": "goto", "position": [1, 2, 3], "yaw": 0.5, "speed": null}')
    assert r["ok"] and r["result"]["duration"] > 1.0
    assert handle_request(sim, '{"op": "velocity", "forward": 1.0, "yaw_rate": -0.2}')["ok"]
    assert handle_request(sim, '{"op": "hold"}')["ok"]
    assert handle_request(sim, b'{"op": "land"}')["ok"]  # bytes: as from a binary frame
    assert handle_request(sim, '{"op": "motors_off"}')["ok"]
    r = handle_request(sim, '{"op": "reset", "position": [1, 1, 2], "yaw": 0.3, "seed": 0}')
    st = r["result"]["state"]
    assert r["result"]["scene"] == "default" and st["mode"] == "hold" and st["t"] == 0.0
    assert st["position"] == [1.0, 1.0, 2.0] and st["yaw"] == pytest.approx(0.3)


BAD_REQUESTS = [
    ("{not json", "parse_error"),
    (b"\xff\xfe\x00garbage", "parse_error"),
    ("[" * 100_000, "parse_error"),
    ('{"op": "takeoff", "altitude": 1' + "0" * 5000 + "}", "parse_error"),
    ("[1, 2]", "invalid_request"),
    ('"takeoff"', "invalid_request"),
    ('{"id": 1}', "invalid_request"),
    ('{"op": 5}', "invalid_request"),
    ('{"id": [1], "op": "ping"}', "invalid_request"),
    ('{"id": true, "op": "ping"}', "invalid_request"),
    ('{"op": "fly"}', "unknown_op"),
    ('{"op": "goto"}', "invalid_argument"),
    ('{"op": "goto", "position": [1, 2]}', "invalid_argument"),
    ('{"op": "goto", "position": "here"}', "invalid_argument"),
    ('{"op": "goto", "position": [1, 2, true]}', "invalid_argument"),
    ('{"op": "takeoff", "altitude": true}', "invalid_argument"),
    ('{"op": "takeoff", "altitude": "2"}', "invalid_argument"),
    ('{"op": "takeoff", "altitude": NaN}', "invalid_argument"),
    ('{"op": "takeoff", "altitude": Infinity}', "invalid_argument"),
    ('{"op": "goto", "position": [0, -Infinity, 2]}', "invalid_argument"),
    ('{"op": "takeoff", "altitude": 1e999}', "invalid_argument"),
    ('{"op": "takeoff", "height": 2}', "invalid_argument"),
    ('{"op": "ping", "x": 1}', "invalid_argument"),
    ('{"op": "velocity", "forward": 1}', "invalid_argument"),
    ('{"op": "reset", "seed": 1.5}', "invalid_argument"),
    ('{"op": "reset", "scene": "mars"}', "invalid_argument"),
    ('{"op": "reset", "airborne": 1}', "invalid_argument"),
    ('{"op": "reset", "seed": -1}', "out_of_range"),
    ('{"op": "takeoff", "altitude": -1}', "below_ground"),
    ('{"op": "goto", "position": [100, 0, 2]}', "out_of_bounds"),
    ('{"op": "goto", "position": [1, 0, 2], "speed": 50}', "out_of_range"),
    ('{"op": "goto", "position": [1, 0, 2], "duration": 0.01}', "out_of_range"),
    ('{"op": "velocity", "forward": 1, "yaw_rate": 0}', "not_airborne"),
    ('{"op": "land"}', "not_airborne"),
    ('{"op": "subscribe", "streams": ["video"]}', "invalid_argument"),
    ('{"op": "subscribe", "streams": []}', "invalid_argument"),
    ('{"op": "subscribe", "rate_hz": 0}', "out_of_range"),
    ('{"op": "subscribe"}', "unsupported"),
]


@pytest.mark.parametrize(("raw", "code"), BAD_REQUESTS, ids=[f"{c}:{str(r)[:30]}" for r, c in BAD_REQUESTS])
def test_handle_request_rejects_bad_input_without_side_effects(bare_sim, raw, code):
    before = bare_sim.vehicle().state.position.copy()
    reply = handle_request(bare_sim, raw)
    assert reply["ok"] is False
    assert reply["error"]["code"] == code, reply["error"]["message"]
    assert set(reply) == {"id", "ok", "error"} and reply["error"]["message"]
    json.dumps(reply, allow_nan=False)
    assert bare_sim.vehicle().mode.value == "idle" and bare_sim.t == 0.0
    np.testing.assert_array_equal(bare_sim.vehicle().state.position, before)


def test_replies_echo_the_id_and_unknown_op_lists_the_ops(bare_sim):
    assert handle_request(bare_sim, '{"id": 9}')["id"] == 9
    r = handle_request(bare_sim, '{"id": "x", "op": "fly"}')
    assert r["id"] == "x" and "goto" in r["error"]["message"] and "subscribe" in r["error"]["message"]
    assert handle_request(bare_sim, "{oops")["id"] is None


def test_unexpected_exceptions_become_internal_error_and_are_logged(caplog):
    class Broken:  # a world whose vehicle's sensor fails
        @property
        def state(self) -> Any:
            raise RuntimeError("sensor exploded")

        def vehicle(self, name: str | None = None) -> Any:
            return self

    reply = handle_request(Broken(), '{"id": 3, "op": "state"}')  # type: ignore[arg-type]
    assert reply["error"] == {
        "code": "internal_error",
        "message": "state failed: RuntimeError: sensor exploded",
    }
    assert any(r.exc_info and r.levelno == logging.ERROR for r in caplog.records)


def test_flight_lock_and_extra_ops(bare_sim):
    locked = handle_request(bare_sim, '{"op": "takeoff"}', flight_locked="PX4 is in control")
    assert locked["error"] == {"code": "flight_locked", "message": "PX4 is in control"}
    assert handle_request(bare_sim, '{"op": "state"}', flight_locked="PX4 is in control")["ok"]
    extra = {"echo": lambda args: {"got": args}}
    assert handle_request(bare_sim, '{"id": 1, "op": "echo", "a": [1, 2]}', extra)["result"] == {
        "got": {"a": [1, 2]}
    }
    assert handle_request(bare_sim, '{"op": "echo", "a": NaN}', extra)["error"]["code"] == "invalid_argument"


# --------------------------------------------------------------------------- a real server
class Rig:
    """A world + lock + ApiServer + a thread stepping the simulation and publishing to the server."""

    def __init__(self) -> None:
        self.sim = World(scene="default", render=False)
        self.lock = threading.Lock()
        self.commands = CommandPath(self.sim, self.lock)
        self.server = ApiServer(self.commands, port=0, max_message_bytes=MAX_MESSAGE, state_rate_hz=30.0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._step, name="test-stepper", daemon=True)

    def _step(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                events = [e.to_dict() for _ in range(STEPS_PER_TICK) for e in self.sim.step().events]
                state = self.sim.vehicle().state  # what the runtime publishes too
            for e in events:
                self.server.publish_event(e)
            self.server.publish_state(state)
            time.sleep(0.01)

    def __enter__(self) -> Rig:
        self.server.start()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.server.stop()
        self.sim.close()


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    with Rig() as r:
        yield r


@pytest.fixture()
def client(rig: Rig, caplog: pytest.LogCaptureFixture) -> Iterator[DroneulatorClient]:
    """A connected client; afterwards the server must have logged no error and dropped every connection."""
    with DroneulatorClient(rig.server.url, timeout=5.0) as c:
        yield c
    deadline = time.monotonic() + 3.0
    while rig.server.client_count and time.monotonic() < deadline:
        time.sleep(0.02)
    assert rig.server.client_count == 0
    errors = [r for r in caplog.get_records("call") if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]


def exchange(ws: ClientConnection, data: str | bytes) -> dict[str, Any]:
    """Send one raw message on a raw connection and return the reply."""
    ws.send(data)
    return json.loads(ws.recv(timeout=5.0))


def test_takeoff_then_goto_arrives_at_the_target(client):
    client.reset()
    client.subscribe(["events"])
    client.takeoff(1.5)
    event = client.wait_for_event("arrived", timeout=10)
    assert event["command"] == "takeoff" and event["target"] == [0.0, 0.0, 1.5]
    target = [3.0, -2.0, 2.5]
    r = client.goto(target, yaw=1.0, speed=2.0)
    assert r["duration"] > 1.0
    event = client.wait_for_event("arrived", timeout=10)
    assert event["command"] == "goto" and event["t"] >= r["t"] + r["duration"]
    st = client.state()
    assert st["mode"] == "hold"
    assert np.linalg.norm(np.subtract(st["position"], target)) < 0.06
    assert abs(math.remainder(st["yaw"] - 1.0, 2 * math.pi)) < 0.03


def test_velocity_mode_moves_the_vehicle(client):
    st = client.reset(position=[0.0, 0.0, 2.0], yaw=0.0)["state"]
    assert st["mode"] == "hold"
    client.velocity(2.0, 0.0)
    st = client.wait_until(lambda s: s["position"][0] > 2.0, timeout=10)
    assert st["mode"] == "velocity" and st["velocity"][0] > 1.0
    assert abs(st["position"][1]) < 0.1 and abs(st["position"][2] - 2.0) < 0.1
    client.hold()


def test_every_bad_input_gets_its_code_and_the_simulation_keeps_going(rig, client):
    client.reset()  # on the ground: velocity must be refused
    cases = [
        ("{not json", "parse_error"),
        ("[1, 2, 3]", "invalid_request"),
        ('{"id": 4}', "invalid_request"),
        ('{"op": "teleport"}', "unknown_op"),
        ('{"op": "goto"}', "invalid_argument"),
        ('{"op": "goto", "position": "up"}', "invalid_argument"),
        ('{"op": "takeoff", "altitude": false}', "invalid_argument"),
        ('{"op": "takeoff", "altitude": NaN}', "invalid_argument"),
        ('{"op": "takeoff", "altitude": Infinity}', "invalid_argument"),
        ('{"op": "takeoff", "altitude": -Infinity}', "invalid_argument"),
        ('{"op": "goto", "position": [0, 0, -2]}', "below_ground"),
        ('{"op": "goto", "position": [0, 500, 2]}', "out_of_bounds"),
        ('{"op": "velocity", "forward": 1.0, "yaw_rate": 0.0}', "not_airborne"),
        ('{"op": "ping", "pad": "' + "x" * MAX_MESSAGE + '"}', "message_too_large"),
        (b"\x00\xff\x13garbage\xc3", "parse_error"),
    ]
    t0 = client.state()["t"]
    with connect(rig.server.url) as ws:
        for i, (raw, code) in enumerate(cases):
            reply = exchange(ws, raw)
            assert reply["ok"] is False and reply["error"]["code"] == code, (i, reply)
            assert reply["error"]["message"]
        reply = exchange(ws, b'{"id": 1, "op": "ping"}')  # a binary frame holding JSON is fine
        assert reply["ok"] and reply["id"] == 1
        reply = exchange(ws, json.dumps({"id": "ok", "op": "takeoff", "altitude": 1.0}))
        assert reply["ok"] and reply["id"] == "ok"  # the same connection still works
    deadline = time.monotonic() + 5.0  # the exchanges can take less than one state period
    while client.state()["t"] <= t0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert client.state()["t"] > t0  # the simulation kept stepping
    assert client.state()["mode"] == "takeoff"
    with pytest.raises(ApiError) as e:
        client.goto([float("nan"), 0.0, 2.0])
    assert e.value.code == "invalid_argument"
    with pytest.raises(ApiError) as e:
        client.request("ping", pad="y" * MAX_MESSAGE)
    assert e.value.code == "message_too_large"
    assert client.ping()["pong"] is True


def test_a_message_past_the_transport_limit_closes_only_its_connection(rig, client):
    with connect(rig.server.url, max_size=None) as ws:
        ws.send("[" + " " * rig.server.transport_limit + "]")
        with pytest.raises(ConnectionClosed) as e:
            ws.recv(timeout=5.0)
    assert e.value.rcvd is not None and e.value.rcvd.code == 1009  # message too big
    assert client.ping()["pong"] is True
    with DroneulatorClient(rig.server.url) as other:
        assert other.state()["t"] > 0


def test_clients_vanishing_mid_command_or_mid_stream_are_harmless(rig, client):
    client.reset(position=[0.0, 0.0, 2.0])
    client.subscribe(["state"], rate_hz=50)
    with rig.lock, connect(rig.server.url) as ws:  # the stepper waits: the goto runs after ws is gone
        ws.send(json.dumps({"id": 1, "op": "goto", "position": [1.0, 0.0, 2.0]}))
        time.sleep(0.1)
    with connect(rig.server.url) as streamer:
        assert exchange(streamer, '{"id": 1, "op": "subscribe", "rate_hz": 200}')["ok"]
        streamer.recv(timeout=5.0)
        streamer.socket.shutdown(socket.SHUT_RDWR)  # vanish without a closing handshake
    deadline = time.monotonic() + 3.0
    while rig.server.client_count > 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert rig.server.client_count == 1
    states = [client.next_message(2.0) for _ in range(10)]
    assert all(m is not None and m["type"] == "state" for m in states)
    assert client.state()["mode"] == "goto"  # the vanished client's command was still carried out


def test_subscriptions_deliver_state_at_the_rate_and_events_in_order(rig, client):
    client.reset()
    client.subscribe(["state"], rate_hz=20)
    client.next_message(2.0)
    start = time.monotonic()
    stamps = []
    while time.monotonic() - start < 1.5:
        m = client.next_message(0.5)
        if m is not None:
            assert m["type"] == "state"
            stamps.append(m["state"]["t"])
    assert 22 <= len(stamps) <= 32  # 20 Hz for 1.5 s
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))

    with DroneulatorClient(rig.server.url) as listener:
        assert listener.subscribe(["events"]) == {"streams": ["events"], "rate_hz": None}
        for i in range(500):
            rig.server.publish_event({"type": "probe", "seq": i})
        client.unsubscribe()
        client.takeoff(1.0)
        client.wait_until(lambda s: s["mode"] == "hold", timeout=10)
        client.land()
        got: list[dict[str, Any]] = []
        deadline = time.monotonic() + 15.0
        while not got or got[-1]["type"] != "landed":
            m = listener.next_message(max(0.1, deadline - time.monotonic()))
            assert m is not None, got[-3:]
            if m["type"] == "event":
                got.append(m["event"])
    assert [e["seq"] for e in got[:500]] == list(range(500))
    assert [e["type"] for e in got[500:]] == ["arrived", "landed"]
    assert got[500]["t"] < got[501]["t"]


def test_a_slow_state_subscriber_is_woken_only_when_a_state_is_due(bare_sim):
    """States published at 1 kHz to a 5 Hz subscriber: the server's loop is woken for the subscriber
    only when it waits for a newer state, not at the publishing rate; and after a pause in publishing
    the next state still goes out at once."""
    server = ApiServer(CommandPath(bare_sim), port=0).start()
    wakes = 0
    wake = server._wake_state_subscribers

    def counted() -> None:
        nonlocal wakes
        wakes += 1
        wake()

    server._wake_state_subscribers = counted  # the loop calls the instance attribute
    stop = threading.Event()

    def publish() -> None:
        while not stop.is_set():
            server.publish_state(bare_sim.vehicle().state)
            time.sleep(0.001)

    with DroneulatorClient(server.url, timeout=5.0) as c:
        c.subscribe(["state"], rate_hz=5)
        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        start = time.monotonic()
        got = 0
        while time.monotonic() - start < 2.0:
            got += c.next_message(0.5) is not None
        stop.set()
        publisher.join()
        assert 8 <= got <= 13, got  # 5 Hz for 2 s
        assert wakes <= 2 * got + 2, f"{wakes} wake-ups for {got} states"
        while c.next_message(0.3) is not None:  # drain; the subscriber now waits for a newer state
            pass
        time.sleep(0.5)
        sent = time.monotonic()
        server.publish_state(bare_sim.vehicle().state)
        assert c.next_message(2.0) is not None
        assert time.monotonic() - sent < 0.2
    server.stop()


def test_two_clients_at_once_and_a_subscriber_that_never_reads(rig, client):
    client.reset(position=[0.0, 0.0, 2.0])
    errors: list[BaseException] = []

    def hammer(c: DroneulatorClient) -> None:
        try:
            for i in range(40):
                assert c.request("ping")["pong"]
                assert c.state()["mode"] == "hold"
                if i % 10 == 0:
                    c.hold()
        except BaseException as e:
            errors.append(e)

    with connect(rig.server.url, close_timeout=1.0) as sluggard, DroneulatorClient(rig.server.url) as second:
        assert exchange(sluggard, '{"id": 1, "op": "subscribe", "rate_hz": 1000}')["ok"]
        threads = [threading.Thread(target=hammer, args=(c,)) for c in (client, second)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        # both clients got every reply (each within the client's timeout) while the subscriber never read:
        # its unread states did not hold the server up; how fast is the machine's (benchmarks/)
        assert not errors, errors
        assert not any(t.is_alive() for t in threads)
        assert second.ping()["pong"]


def test_flight_lock_and_extra_ops_over_the_server(rig, client):
    rig.server.add_op("echo", lambda args: {"echo": args})
    assert client.request("echo", word="hi") == {"echo": {"word": "hi"}}
    rig.commands.refuse_flight("PX4 is in control")
    try:
        with pytest.raises(ApiError) as e:
            client.takeoff(1.0)
        assert (e.value.code, e.value.message) == ("flight_locked", "PX4 is in control")
        assert client.state()["t"] >= 0
    finally:
        rig.commands.allow_flight()
    client.reset()
    assert client.takeoff(1.0)["duration"] > 0
    with pytest.raises(ValueError):
        rig.server.add_op("goto", lambda args: {})


def test_stop_is_prompt_even_with_a_command_waiting_for_the_lock(rig, bare_sim):
    with pytest.raises(OSError):
        ApiServer(CommandPath(bare_sim), port=rig.server.port).start()
    lock = threading.Lock()
    server = ApiServer(CommandPath(bare_sim, lock), port=0).start()
    c = DroneulatorClient(server.url, timeout=5.0)
    assert c.ping()["pong"]
    with lock:  # like a stepping loop that stops the server while holding the lock
        c.send_raw('{"id": 1, "op": "takeoff"}')
        time.sleep(0.1)
        start = time.monotonic()
        server.stop()
        assert time.monotonic() - start < 3.0
    time.sleep(0.1)
    assert bare_sim.vehicle().mode.value == "idle"  # the command never ran
    server.publish_state(bare_sim.vehicle().state)
    server.publish_event({"type": "late"})
    with pytest.raises(ApiError) as e:
        c.ping()
    assert e.value.code == "connection_closed"
    c.close()


def test_random_requests_always_get_a_well_formed_reply(bare_sim):
    rng = np.random.default_rng(1)
    pool: list[Any] = [0, 1, -1, 2.5, 1e308, 10**30, True, None, "", "default", [], {}, [1, 2, 3], [0, 0, 2]]
    pool += [[1.0, "a", 2], [[1], 2, 3], {"x": 1}, "NaN"]
    names = [*OPS, "bogus"]
    fields = sorted({a.name for op in OPS.values() for a in op.args} | {"id", "extra"})
    for _ in range(400):
        req: dict[str, Any] = {"op": names[rng.integers(len(names))]}
        for f in rng.choice(fields, size=rng.integers(0, 4), replace=False):
            req[str(f)] = pool[rng.integers(len(pool))]
        reply = handle_request(bare_sim, json.dumps(req))
        assert set(reply) in ({"id", "ok", "result"}, {"id", "ok", "error"}), reply
        if not reply["ok"]:
            assert reply["error"]["code"] in ERROR_CODES and reply["error"]["code"] != "internal_error", (
                req,
                reply,
            )
        json.dumps(reply, allow_nan=False)
    assert handle_request(bare_sim, None)["error"]["code"] == "parse_error"  # type: ignore[arg-type]
