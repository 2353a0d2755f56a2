"""A mixed fleet: an internal vehicle, a PX4 one and an ArduPilot one in one world, stepped by one
lockstep loop (:mod:`droneulator.px4.fleet`) with the CI's scripted peers (:mod:`scripted_px4`,
:mod:`scripted_ardupilot`) on real sockets."""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import numpy as np
from scripted_ardupilot import ScriptedArduPilot
from scripted_px4 import ScriptedPX4

from droneulator.ardupilot import link as ardupilot_link
from droneulator.ardupilot.link import ArduPilotLink
from droneulator.config import ArduPilotConfig, PX4Config, VehicleSpec, load_config
from droneulator.px4.fleet import AutopilotFleet
from droneulator.px4.link import PX4Link
from droneulator.world import World

HZ = 1000  # a mixed world's rate: one ArduPilot frame a step, PX4's 250 Hz lockstep every 4th step
DT_US = 1_000_000 // HZ
PX4_DT_US = 4 * DT_US


class RecordingPX4(ScriptedPX4):
    """The scripted PX4, noting the time stamp of every HIL_SENSOR it is sent."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        self.stamps: list[int] = []
        super().__init__(*args, **kw)

    def _on_imu(self, msg: Any) -> None:
        self.stamps.append(msg.time_usec)
        super()._on_imu(msg)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred: Any, timeout: float = 60.0) -> None:
    """Wait for ``pred``: a failure detector, generous for a loaded machine compiling the kernels."""
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.002)


def test_internal_px4_and_ardupilot_vehicles_fly_one_world_in_lockstep_and_lose_peers_apart(monkeypatch):
    """The world steps once when both autopilots are ready; ArduPilot gets exactly one reply per step and
    PX4 one HIL_SENSOR per 4 ms (every 4th step), stamped with the same simulation times; each autopilot's
    outputs move its own vehicle only, while the internal one flies on the simulator's controller; a lost
    PX4 is held (``on_loss``) while ArduPilot goes on stepping the world, then a lost ArduPilot is landed."""
    monkeypatch.setattr(ardupilot_link, "LINK_SILENCE_S", 1.0)
    c = load_config(overrides=[f"vehicle.control_hz={HZ}"])
    c.vehicles = [
        VehicleSpec(name="own", params="px4_quadx"),
        VehicleSpec(name="px", params="px4_quadx", controlled_by="px4"),
        VehicleSpec(name="ap", params="px4_quadx", controlled_by="ardupilot"),
    ]
    c.px4 = PX4Config(base_port=0, speed_factor=0.0, on_loss="hold")
    c.ardupilot = ArduPilotConfig(base_port=0, on_loss="land")
    with World(c, scene="default", render=False) as w:
        w.step()  # compiles the three-vehicle step before a peer waits on it
        w.reset()
        fleet = AutopilotFleet.of(w)
        px_link, ap_link = fleet.links
        assert isinstance(px_link, PX4Link) and isinstance(ap_link, ArduPilotLink)
        assert (px_link.vehicle.name, ap_link.vehicle.name) == ("px", "ap")
        assert fleet.autopilots == "PX4 and ArduPilot"
        fleet.start()
        lock, stop = threading.Lock(), threading.Event()
        stepped: list[int] = []

        def serve() -> None:
            while not stop.is_set():
                if fleet.serve_once(0.01, lock) is not None:
                    stepped.append(w.t_ns)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        ap = ScriptedArduPilot(ap_link.port, rate_hz=HZ)
        px4: RecordingPX4 | None = None
        try:
            first = ap.step([1000] * 4)  # connects at t = 0: ArduPilot's clock is the world's
            assert first["timestamp"] * 1e6 == DT_US == w.t_ns // 1000
            with lock:
                w.vehicle("own").takeoff(1.0)
            px4 = RecordingPX4(px_link.port, free_port())
            wait_until(lambda: px_link.lockstep)
            ap_stamps: list[int] = []

            def ap_steps(n: int, pwm: list[int]) -> None:
                for _ in range(n):
                    ap_stamps.append(round(ap.step(pwm)["timestamp"] * 1e6))

            ap_steps(160, [1000] * 4)  # PX4 gets its GPS origin
            assert px4.origin is not None and px4.error is None
            px4.takeoff()
            ap_steps(1400, [1000] * 4)  # ArduPilot disarmed: only PX4's vehicle (and the internal one) climb
            with lock:
                px, apv, own = (w.vehicle(n) for n in ("px", "ap", "own"))
                assert px.state.position[2] > 0.3 and px.mode.value == "external"
                assert apv.state.position[2] < 0.01 and not np.any(apv.state.rotor_speeds)
                assert own.state.position[2] > 0.3 and own.mode.value != "external"
            climb = [1850] * 4
            ap_steps(320, climb)  # ArduPilot armed: its motor outputs are its vehicle's rotor speeds
            with lock:
                command = ap_link.motors.rotor_speeds(climb)  # the rotors lag it by < 1 % after 0.3 s
                np.testing.assert_allclose(apv.state.rotor_speeds, command, rtol=0.02)
                assert apv.state.position[2] > 0.1
                assert not np.allclose(px.state.rotor_speeds, apv.state.rotor_speeds)
            # a reply per step to ArduPilot, a HIL_SENSOR per 4 ms to PX4, on the same clock: from PX4's
            # first lockstep batch on, PX4's stamps are ArduPilot's on its 4 ms grid, each once
            on_grid = [t for t in ap_stamps if t % PX4_DT_US == 0]
            wait_until(lambda: px4.stamps[-1] == on_grid[-1])
            assert px4.stamps[1:] == on_grid[on_grid.index(px4.stamps[1]) :]
            assert np.all(np.diff(ap_stamps) == DT_US) and len(stepped) == len(set(stepped))

            px4.close()  # killed in the air: held, and ArduPilot steps the world on
            wait_until(lambda: not px_link.connected)
            ap_steps(40, climb)
            assert np.all(np.diff(ap_stamps[-41:]) == DT_US)
            events = fleet.take_events()
            lost = [e for e in events if e.type.endswith("_lost")]
            assert [(e.type, e.vehicle, e.data["action"]) for e in lost] == [("px4_lost", "px", "hold")]
            assert px.mode.value == "hold" and apv.mode.value == "external"

            ap.close()  # ArduPilot silent: lost after LINK_SILENCE_S, its vehicle landed
            wait_until(lambda: not ap_link.connected)
            taken: list[Any] = []

            def ardupilot_lost() -> list[Any]:
                taken.extend(fleet.take_events())
                return [e for e in taken if e.type == "ardupilot_lost"]

            wait_until(ardupilot_lost)
            lost = ardupilot_lost()
            assert lost[0].vehicle == "ap" and lost[0].data["action"] == "land"
            assert apv.mode.value == "land" and px.mode.value == "hold"
        finally:
            stop.set()
            thread.join(5.0)
            if px4 is not None:
                px4.close()
            ap.close()
            fleet.close()
