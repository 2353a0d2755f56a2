"""What the dynamics server publishes of its steps on ROS 2: odometry, TF and ``/clock``, the sensor topics.

They leave the dynamics server right after the physics step that produced the state (no process hop),
at ``runtime.state_hz`` and at every triggered camera instant (which ends a control period: these
states), so each triggered frame has odometry and TF of its stamp. The static TF goes out every
``STATIC_TF_PERIOD_S`` of wall time, and at once after a reset. Sensor topics (IMU, GPS fix, air
pressure, magnetic field): a vehicle a connected PX4 flies publishes what its PX4 link sent PX4 (the
link samples its sensors every step), any other vehicle what is sampled here of its sensors at each
state publish (the IMU every time, the others at ``px4.mag_hz``, ``baro_hz`` and ``gps_hz``).
"""

from __future__ import annotations

import time
from collections.abc import Collection

from droneulator.config import SimConfig
from droneulator.ros.publishers import StatePublisher
from droneulator.ros.topics import SENSOR_TOPICS
from droneulator.ros.zenoh_node import RosZenohNode
from droneulator.runtime.latency import LatencyLog
from droneulator.sensors import Truth
from droneulator.sensors.suite import Schedule
from droneulator.vehicles.vehicle import NS, VehicleState
from droneulator.world import World
from droneulator.world.world import StepResult

STATIC_TF_PERIOD_S = 1.0
#: how often the spray deposit grid goes out (sim time)
DEPOSIT_PERIOD_NS = NS


class StatePublishing:
    """Publishes ``world``'s states and sensor readings on ``node`` when due (:meth:`due`), and marks the
    odometry in the ``latency`` log."""

    def __init__(self, world: World, node: RosZenohNode, cfg: SimConfig, latency: LatencyLog | None) -> None:
        self.world = world
        self.ros = StatePublisher(node, cfg)
        self._latency = latency
        #: vehicles with a sensor topic, and when each of their sensors is next sampled here
        self._sensing = [
            name for name, v in world.vehicles.items() if any(k in v.rig.suite for k in SENSOR_TOPICS)
        ]
        self._sensor_schedules = {name: Schedule() for name in self._sensing}
        self.period_ns = round(NS / cfg.runtime.state_hz)
        self._next_state_ns = 0
        self._last_t_ns = 0
        self._last_static = -float("inf")
        self._next_deposit_ns = 0

    def due(self, states: dict[str, VehicleState], res: StepResult) -> bool:
        """(Under the lock, with the ``states`` just taken after step ``res``) whether they are published:
        the period is up or a triggered camera instant ends here. Sim time gone back (a reset through the
        API) restarts the period and sends the static TF again at once."""
        st = next(iter(states.values()))
        if st.t_ns < self._last_t_ns:
            self._last_static = -float("inf")
            self._next_state_ns = 0
        self._last_t_ns = st.t_ns
        due = st.stamp_ns >= self._next_state_ns or any(r is not None for r in res.camera_rigs)
        if due:
            self._next_state_ns = st.stamp_ns + self.period_ns
        return due

    def sensor_truths(self, fed: Collection[str]) -> dict[str, Truth]:
        """(Under the lock, with the states about to be published) the truth each sensing vehicle's sensors
        are sampled from, for the vehicles not in ``fed``: a connected PX4's link has sampled its
        vehicle's sensors this step already."""
        return {n: Truth.from_sim(self.world.vehicles[n]) for n in self._sensing if n not in fed}

    def publish_states(self, states: dict[str, VehicleState], stepped_wall_ns: int) -> None:
        """Odometry, TF and ``/clock`` of ``states``, produced by a step that ended at ``stepped_wall_ns``."""
        if self._latency is not None:
            self._latency.mark("odom", next(iter(states.values())).stamp_ns, stepped_wall_ns)
        self.ros.publish_states(states)
        spraying = self.world.spraying
        stamp = next(iter(states.values())).stamp_ns
        if spraying is not None and stamp >= self._next_deposit_ns:
            self._next_deposit_ns = stamp + DEPOSIT_PERIOD_NS
            c = spraying.cloud
            self.ros.publish_deposit(stamp, c.ground_deposit_ul_cm2(), c.ground_cell, c.ground_origin)

    def publish_sensors(self, states: dict[str, VehicleState], truths: dict[str, Truth]) -> None:
        """Sample the sensors of the vehicles in ``truths`` (the IMU now, the others when due), publish every
        sensing vehicle's newest readings (one sample per reading, whoever drew it), and the static TF
        when its period is up."""
        if self._sensing:
            vehicles = self.world.vehicles
            for name, truth in truths.items():
                vehicles[name].rig.suite.sample_due(truth, self._sensor_schedules[name])
            latest = {name: vehicles[name].rig.suite.latest for name in self._sensing}
            self.ros.publish_sensors(states, latest)
        now = time.monotonic()
        if now - self._last_static > STATIC_TF_PERIOD_S:
            self._last_static = now
            self.ros.publish_static(next(iter(states.values())).stamp_ns)
