"""Stage 2 of a capture: flying the plan over the WebSocket API.

Each leg is one min-snap ``goto``; the vehicle counts as settled when the published odometry has
stayed within position, speed, heading and turn-rate thresholds of the leg's end for
``capture.settle_time_s`` of sim time. The path flown is compared with the commanded straight leg
(:func:`~.plan.segment_errors`), and a collision event from the API ends the capture. In a fleet each
vehicle has its own :class:`Flyer` (its own client, topics and thread); a shared stop event ends the
others' legs when one fails.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.api.client import DroneulatorClient
from droneulator.config import CaptureConfig
from droneulator.frames import wrap_angle, yaw_of
from droneulator.ros.topics import ns_to_seconds, seconds_to_ns
from droneulator.workflows.photogrammetry.plan import (
    Viewpoint,
    arc_waypoints,
    axis_clearance,
    facing_yaw,
    ring_point,
    segment_errors,
)
from droneulator.workflows.photogrammetry.record import OdomSample, TopicRecorder


@dataclass
class LegStats:
    kind: str
    max_path_error_m: float = 0.0
    max_altitude_error_m: float = 0.0
    flight_sim_s: float = 0.0
    settle_sim_s: float = 0.0
    gotos: int = 0
    #: gotos that ended within the acceptance radius without settling (wind)
    unsettled: int = 0

    def merge(self, other: LegStats) -> None:
        self.max_path_error_m = max(self.max_path_error_m, other.max_path_error_m)
        self.max_altitude_error_m = max(self.max_altitude_error_m, other.max_altitude_error_m)
        self.flight_sim_s += other.flight_sim_s
        self.settle_sim_s += other.settle_sim_s
        self.gotos += other.gotos
        self.unsettled += other.unsettled

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "max_path_error_m": round(self.max_path_error_m, 5),
            "max_altitude_error_m": round(self.max_altitude_error_m, 5),
            "flight_sim_s": round(self.flight_sim_s, 3),
            "settle_sim_s": round(self.settle_sim_s, 3),
            "gotos": self.gotos,
            "unsettled": self.unsettled,
        }


class CollisionError(RuntimeError):
    """The simulator reported a collision during a leg."""


class StoppedError(RuntimeError):
    """Another vehicle's flight failed, so this one stopped."""


class Flyer:
    """Sends gotos over the WebSocket API and judges arrival from the published odometry."""

    def __init__(
        self,
        client: DroneulatorClient,
        topics: TopicRecorder,
        cap: CaptureConfig,
        center: Sequence[float],
        vehicle: str | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        self.client = client
        self.topics = topics
        self.cap = cap
        self.center = np.asarray(center, dtype=float)
        self.vehicle = vehicle
        self.stop = stop
        self.commanded: np.ndarray | None = None

    def _check_events(self) -> None:
        if self.stop is not None and self.stop.is_set():
            raise StoppedError(f"{self.vehicle}: stopped, another vehicle's flight failed")
        while (msg := self.client.next_message(timeout=0.0)) is not None:
            if msg.get("type") == "event" and msg["event"].get("type") == "collision":
                event = msg["event"]
                who = event.get("vehicles") or event.get("vehicle") or "the vehicle"
                raise CollisionError(f"{who} collided at {event.get('position')}")

    def current(self) -> OdomSample:
        """The vehicle's odometry now: the first sample stamped at or after the simulator's clock as the
        API reads it. The odometry comes over Zenoh and the API's replies and events over the WebSocket;
        on a loaded machine the topic can lag the event that a takeoff ended, and the latest sample heard
        is then still one from the ground."""
        now = int(self.client.state(vehicle=self.vehicle)["stamp_ns"])
        return self.topics.odom_after(now - 1, timeout=self.cap.leg_timeout_s)[0]

    def _in_tolerance(self, s: OdomSample, goal: np.ndarray, yaw: float) -> bool:
        c = self.cap
        return (
            float(np.linalg.norm(s.position - goal)) <= c.settle_position_m
            and float(np.linalg.norm(s.linear)) <= c.settle_speed_mps
            and abs(wrap_angle(yaw_of(s.quaternion) - yaw)) <= math.radians(c.settle_yaw_deg)
            and float(np.linalg.norm(s.angular)) <= math.radians(c.settle_rate_dps)
        )

    def _accepted(self, s: OdomSample, goal: np.ndarray, yaw: float) -> bool:
        c = self.cap
        return float(np.linalg.norm(s.position - goal)) <= c.acceptance_m and abs(
            wrap_angle(yaw_of(s.quaternion) - yaw)
        ) <= math.radians(c.acceptance_deg)

    def goto(self, goal: np.ndarray, yaw: float, kind: str) -> tuple[LegStats, int]:
        """Fly one min-snap leg to ``goal``; returns its tracking statistics and the settle stamp (ns): when
        the odometry has stayed within the settle tolerances for ``settle_time_s``, or, ``accept_after_s``
        after the leg's reference ended without that (wind), when it is within the acceptance radius."""
        start = self.commanded if self.commanded is not None else self.current().position
        reply = self.client.goto(goal.tolist(), yaw=yaw, speed=self.cap.speed, vehicle=self.vehicle)
        t0 = int(reply["stamp_ns"])  # the ROS clock, which the odometry stamps use
        accept_from = t0 + seconds_to_ns(float(reply["duration"]) + self.cap.accept_after_s)
        stats = LegStats(kind, gotos=1)
        self.commanded = goal.copy()
        deadline = time.monotonic() + self.cap.leg_timeout_s
        run_start: int | None = None
        last = t0
        while True:
            self._check_events()
            samples = self.topics.odom_after(last, timeout=max(0.1, deadline - time.monotonic()))
            pts = np.array([s.position for s in samples])
            path_err, alt_err = segment_errors(pts, start, goal)
            stats.max_path_error_m = max(stats.max_path_error_m, float(path_err.max()))
            stats.max_altitude_error_m = max(stats.max_altitude_error_m, float(alt_err.max()))
            for s in samples:
                if s.stamp >= accept_from and self._accepted(s, goal, yaw):
                    stats.flight_sim_s = ns_to_seconds(s.stamp - t0)
                    stats.unsettled = 1
                    return stats, s.stamp
                if not self._in_tolerance(s, goal, yaw):
                    run_start = None
                    continue
                if run_start is None:
                    run_start = s.stamp
                if s.stamp - run_start >= seconds_to_ns(self.cap.settle_time_s):
                    stats.flight_sim_s = ns_to_seconds(run_start - t0)
                    stats.settle_sim_s = ns_to_seconds(s.stamp - run_start)
                    return stats, s.stamp
            last = samples[-1].stamp
            if time.monotonic() > deadline:
                s = samples[-1]
                raise TimeoutError(
                    f"not settled at {goal.round(3).tolist()} within {self.cap.leg_timeout_s} s: odometry "
                    f"{s.position.round(3).tolist()}, speed {np.linalg.norm(s.linear):.3f} m/s"
                )

    def fly(self, waypoints: list[np.ndarray], kind: str) -> tuple[LegStats, int | None]:
        """Fly through ``waypoints`` (each a goto facing the tree); merged statistics, last settle stamp."""
        total = LegStats(kind)
        stamp = None
        for p in waypoints:
            stats, stamp = self.goto(p, facing_yaw(self.center, p), kind)
            total.merge(stats)
        return total, stamp

    def transit(self, view: Viewpoint, radius: float, arc_first: bool = False) -> tuple[LegStats, int | None]:
        """Reach ``view`` from anywhere outside the crown: straight there when the straight line keeps as far
        from the tree's axis as a capture leg's chord does (:func:`~.plan.axis_clearance`, at least
        ``radius cos(max_leg_deg / 2)``), else out (or in) to the ring at the current azimuth and altitude,
        up or down to the ring, then along the circle, so the path never crosses the tree.

        ``arc_first`` (a fleet): along the circle at the current radius (the ring's if inside it) and
        altitude first, then in to the ring and up or down, so that vehicles standing side by side move
        apart before any of them closes in on the ring; the circle is flown in the longest chords that stay
        outside the ring (``capture.max_leg_deg`` at least)."""
        cur = self.current().position
        az = math.atan2(cur[1] - self.center[1], cur[0] - self.center[0])
        tol = self.cap.settle_position_m
        pts: list[np.ndarray] = []
        if arc_first:
            r = max(radius, math.hypot(*(cur[:2] - self.center[:2])))
            if r - math.hypot(*(cur[:2] - self.center[:2])) > tol:
                pts.append(ring_point(self.center, r, az, cur[2]))
            step = max(self.cap.max_leg_deg, math.degrees(2 * math.acos(radius / r)))
            pts += arc_waypoints(self.center, r, cur[2], az, view.azimuth, step)
            if r - radius > tol:
                pts.append(ring_point(self.center, radius, view.azimuth, cur[2]))
        elif axis_clearance(self.center, cur, view.position) >= radius * math.cos(
            math.radians(self.cap.max_leg_deg) / 2
        ):
            pts.append(np.array(view.position))
        else:
            if abs(math.hypot(*(cur[:2] - self.center[:2])) - radius) > tol:
                pts.append(ring_point(self.center, radius, az, cur[2]))
            if abs(cur[2] - view.position[2]) > tol:
                pts.append(ring_point(self.center, radius, az, view.position[2]))
            pts += arc_waypoints(
                self.center, radius, view.position[2], az, view.azimuth, self.cap.max_leg_deg
            )
        if not pts or np.linalg.norm(pts[-1] - np.array(view.position)) > 1e-6:
            pts.append(np.array(view.position))
        return self.fly(pts, "transit")
