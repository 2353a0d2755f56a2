"""How fast a PX4 SITL flight runs: ``droneulator run --px4`` with the full 640x480 camera rig, driven in
lockstep by a peer playing PX4 (pymavlink over TCP, answering every HIL_SENSOR with HIL_ACTUATOR_CONTROLS
at once, armed, holding 2 m with a vertical PD loop on HIL_STATE_QUATERNION), for each
``px4.speed_factor``.

Real PX4 answers in well under a millisecond per 4 ms step, so the peer's reply time stands in for it
(no PX4 here). Per speed factor it prints: simulated seconds per wall second, the PX4 step (must stay
exactly 4000 us of HIL_SENSOR time per actuator message), camera frames received on Zenoh against the
frames the simulated time calls for (lockstep: none may be lost), the altitude held, and the wall-clock
gaps between HIL_SENSOR messages (PX4 logs a poll timeout after 1 s without one).
"""

from __future__ import annotations

import argparse
import json
import socket
import threading
import time
from typing import Any

import numpy as np
import zenoh
from _common import write
from pymavlink.dialects.v20 import common as mavlink

from droneulator.config import load_config
from droneulator.px4.mixing import MotorMap
from droneulator.ros.topics import TYPES, header_ns, topic_names
from droneulator.runtime.launch import free_port, launch_run
from droneulator.vehicles.params import get_params

ALTITUDE = 2.0


class Px4Peer:
    """The PX4 side of the simulator link, minimal: heartbeat, then actuators for every HIL_SENSOR."""

    def __init__(self, port: int, home_alt_m: float) -> None:
        self.home_alt_m = home_alt_m
        end = time.monotonic() + 60.0
        while True:  # as PX4: retry until the simulator listens (once its cameras are warm)
            try:
                self.sock = socket.create_connection(("127.0.0.1", port), timeout=10.0)
                break
            except ConnectionRefusedError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.01)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.tx, self.rx = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None)
        qp = get_params("px4_quadx")
        self.motors = MotorMap(qp, 0.0)
        self.hover = float(np.sqrt(qp["mass"] * 9.81 / (4 * qp["k_eta"])))
        self.z = self.vz = 0.0
        self.t_us: list[int] = []
        self.arrivals: list[float] = []  # wall time of each HIL_SENSOR
        hb = self.tx.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
        self.sock.sendall(hb.pack(self.tx))

    def _outputs(self) -> list[float]:
        thrust = 1.0 + 0.8 * (ALTITUDE - self.z) - 0.6 * self.vz  # relative to hover thrust
        w = self.hover * np.sqrt(np.clip(thrust, 0.3, 1.8))
        return [float(self.motors.speed_to_output(w))] * 4 + [0.0] * 12

    def run(self, seconds: float) -> None:
        """Answer every HIL_SENSOR for ``seconds`` of wall time."""
        end = time.monotonic() + seconds
        self.sock.sendall(self.tx.hil_actuator_controls_encode(0, self._outputs(), 129, 1).pack(self.tx))
        while time.monotonic() < end:
            for m in self.rx.parse_buffer(self.sock.recv(65536)) or []:
                kind = m.get_type()
                if kind == "HIL_STATE_QUATERNION":
                    self.z, self.vz = m.alt / 1000.0 - self.home_alt_m, -m.vz / 100.0  # alt MSL mm, vz down
                elif kind == "HIL_SENSOR":
                    self.t_us.append(m.time_usec)
                    self.arrivals.append(time.monotonic())
                    msg = self.tx.hil_actuator_controls_encode(m.time_usec, self._outputs(), 129, 1)
                    self.sock.sendall(msg.pack(self.tx))

    def close(self) -> None:
        self.sock.close()


def measure(speed_factor: float, seconds: float, scene: str) -> dict[str, Any]:
    cfg = load_config(scene=scene)
    port = free_port()
    args = ["--px4", "--set", f"px4.base_port={port}", "--set", f"px4.speed_factor={speed_factor}"]
    stamps: list[int] = []
    lock = threading.Lock()
    with launch_run(cfg, args) as run:
        conf = zenoh.Config()
        conf.insert_json5("connect/endpoints", json.dumps([run.zenoh_endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        with zenoh.open(conf) as session:
            key = topic_names(cfg.bridge.namespace, cfg.render.cameras[0].name)["depth"].lstrip("/")

            def on_depth(sample: zenoh.Sample) -> None:
                from droneulator.ros.messages import decode

                with lock:
                    stamps.append(header_ns(decode(TYPES["depth"], sample.payload.to_bytes())))

            sub = session.declare_subscriber(key, on_depth)
            with run.client() as client:
                deadline = time.monotonic() + 60  # the clock moves once the renderer and the bridge are up
                while client.state()["t"] < 0.1:
                    if time.monotonic() > deadline:
                        raise TimeoutError("the simulation clock never started")
                    time.sleep(0.1)
                peer = Px4Peer(port, cfg.site.altitude_m)
                wall0 = time.monotonic()
                peer.run(seconds)
                wall = time.monotonic() - wall0
                state = client.state()
            peer.close()
            time.sleep(1.0)
            sub.undeclare()
    t_us = np.array(peer.t_us, dtype=np.int64)
    steps = np.diff(t_us)
    gaps = np.diff(peer.arrivals)
    sim_s = (t_us[-1] - t_us[0]) / 1e6
    with lock:
        got = np.unique(stamps)
    period = round(1e9 / cfg.render.camera_hz)
    inside = got[(got >= t_us[0] * 1000 + period) & (got <= t_us[-1] * 1000 - period)]
    expected = int((inside[-1] - inside[0]) // period + 1) if inside.size else 0
    return {
        "speed_factor": speed_factor,
        "wall_seconds": wall,
        "sim_seconds": sim_s,
        "real_time_factor": sim_s / wall,
        "px4_steps": int(steps.size),
        "step_us_all_4000": bool(np.all(steps == 4000)),
        "frames_received": int(inside.size),
        "frames_expected": expected,
        "altitude_m": float(state["position"][2]),
        # PX4's simulator_mavlink logs "poll timeout" after 1 s without sensor data
        "sensor_gap_median_s": float(np.median(gaps)),
        "sensor_gap_max_s": float(gaps.max()),
        "sensor_gaps_over_1s": int((gaps > 1.0).sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="default", help="scene name (default default)")
    ap.add_argument("--seconds", type=float, default=15.0, help="wall seconds per speed factor (default 15)")
    ap.add_argument("--speeds", default="1,0", help="speed factors, comma separated (default 1,0)")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/px4_speed.json)")
    args = ap.parse_args()
    rows = [measure(float(s), args.seconds, args.scene) for s in args.speeds.split(",")]
    print(f"PX4 lockstep with the 640x480 rig at 30 Hz on {args.scene}, peer answering at once:")
    for r in rows:
        print(
            f"  speed_factor {r['speed_factor']:g}: {r['sim_seconds']:.1f} s simulated "
            f"in {r['wall_seconds']:.1f} s "
            f"(real-time factor {r['real_time_factor']:.2f}); {r['px4_steps']} PX4 steps, all 4000 us: "
            f"{r['step_us_all_4000']}; depth frames {r['frames_received']}/{r['frames_expected']}; "
            f"altitude {r['altitude_m']:.2f} m; sensor gaps median {r['sensor_gap_median_s'] * 1e3:.1f} ms, "
            f"max {r['sensor_gap_max_s']:.2f} s, {r['sensor_gaps_over_1s']} over PX4's 1 s poll timeout"
        )
    write("px4_speed", {"scene": args.scene, "runs": rows}, args.json)


if __name__ == "__main__":
    main()
