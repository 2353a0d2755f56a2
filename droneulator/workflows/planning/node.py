"""``droneulator plan``: the local planner as a process that is a ROS 2 node in all but name.

It talks only ROS 2 messages over Zenoh, like EGO-Planner does through a bridge: depth image, its
camera_info, odometry and the camera pose (``/<ns>/<cam>/pose``, synchronised with the depth) in;
goals as ``geometry_msgs/PoseStamped`` on ``/<ns>/planner/goal``; ``quadrotor_msgs/PositionCommand``
on ``/<ns>/position_cmd`` out, at 100 Hz of sim time. The map comes from depth images alone.

One node plans for one vehicle (``PlanNodeConfig.vehicle``, :mod:`~droneulator.workflows.planning.fleet`):
in a world of several, ``<ns>`` is that vehicle's namespace (``droneulator/uav1``) and its frames are the
vehicle's (``uav1/odom``); one node per vehicle, each mapping the others from its depth images.

One thread besides Zenoh's callbacks: the planning thread integrates the newest depth frame and
(re)plans. The trajectory server is the ``/clock`` callback: it samples the current B-spline each time
the clock has advanced 10 ms, so every 10 ms tick the simulator sends gets its command however busy the
machine is (in lockstep the simulator waits only for its cameras, so sim time, not the wall clock,
paces the commands). With no depth for 1 s of sim time it stops publishing, so the simulator's
``track_timeout`` holds the vehicle.

With an ``autopilot`` (``droneulator plan --px4``: PX4 in OFFBOARD through
:class:`~droneulator.workflows.planning.offboard.OffboardLink`) the samples go to it instead of the
topic, and the node works in the frame the autopilot flies, as a companion computer does: it plans
from, checks arrival on and judges tracking by the autopilot's own estimate (PX4's local position),
not the simulator's true odometry, and plans nothing until the autopilot has taken control and
holds (a goal asks it to). The map is still built from the depth images' poses.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from threadpoolctl import threadpool_limits

from droneulator import frames
from droneulator.ros import messages
from droneulator.ros.topics import (
    TYPES,
    VehicleNames,
    decode_depth,
    header_ns,
    ns_to_seconds,
    stamp_to_ns,
)
from droneulator.ros.zenoh_node import RosZenohNode, ZenohNodeConfig
from droneulator.workflows.planning.bspline import BSpline
from droneulator.workflows.planning.config import PlannerConfig
from droneulator.workflows.planning.fleet import PlannedVehicle, single_vehicle
from droneulator.workflows.planning.planner import Planner
from droneulator.workflows.planning.tracking import TrackingMargin

if TYPE_CHECKING:
    from droneulator.workflows.planning.offboard import Estimate

log = logging.getLogger("droneulator.plan")

GOAL_TYPE = "geometry_msgs/msg/PoseStamped"
#: trajectory server period, sim time
COMMAND_PERIOD_NS = 10_000_000
#: after a failed plan, the next attempt waits this long (sim time)
RETRY_PERIOD_NS = 100_000_000
#: the tracking error is sampled at most this often (sim time; PX4 streams its estimate at 30 Hz)
TRACK_PERIOD_NS = 50_000_000


class Autopilot(Protocol):
    """What flies the planner's setpoints instead of the simulator's track mode (PX4 offboard:
    :class:`~droneulator.workflows.planning.offboard.OffboardLink`)."""

    def engage(self) -> None:
        """Take control of the vehicle (a goal is active)."""

    def estimate(self) -> Estimate | None:
        """The autopilot's estimate of the vehicle (ENU world) once it holds under our control; else None."""

    def setpoint(
        self, t: float, p: np.ndarray, v: np.ndarray, a: np.ndarray, yaw: float, yaw_rate: float
    ) -> None:
        """A trajectory-server sample: sim time (s), world position, velocity, acceleration, yaw, yaw rate."""


@dataclass
class PlanNodeConfig:
    """Wiring and timing of the planner process."""

    zenoh: str = "tcp/127.0.0.1:7448"
    #: the single vehicle's namespace, used when ``vehicle`` is not given
    namespace: str = "droneulator"
    camera: str = "front"
    #: the vehicle planned for, with its topic and frame names (``fleet.from_scene_info`` or
    #: ``fleet.from_config``); None: the single vehicle of a one-vehicle run under ``namespace``
    vehicle: PlannedVehicle | None = None
    #: replan at least this often while a goal is active (sim time), besides when the map demands it
    replan_period_s: float = 1.0
    #: no depth image for this long (sim time) -> stop publishing, the simulator holds
    depth_timeout_s: float = 1.0
    #: the goal counts as reached within this distance of the odometry position
    goal_tolerance: float = 0.1
    #: when a replan fails, the current trajectory is kept while its first collision with the
    #: (newly seen) map is further ahead than this (sim seconds); otherwise the vehicle stops
    stop_margin_s: float = 1.0
    #: largest yaw rate the trajectory server commands (rad/s), like EGO's traj_server
    max_yaw_rate: float = math.pi / 2
    #: the camera faces the point of the trajectory this far ahead (sim seconds; EGO's traj_server
    #: ``time_forward``), so on a bend it looks at what the vehicle is about to pass
    yaw_lookahead_s: float = 1.0
    #: a plan that took longer than this (sim time; the planner runs on the wall clock beside the
    #: simulation) is dropped and made again: its start state lies that far in the past
    max_plan_lag_s: float = 0.3
    #: the trajectory is served only while the planning thread has looked at it within this much sim
    #: time (between map updates, collision checks and plans); past it (one plan or map update stuck on a
    #: loaded machine while the simulation runs on) the vehicle holds where its reference is, and the next
    #: plan starts from the odometry there: as with ``depth_timeout_s``, nothing flies on unchecked for
    #: longer. Must exceed ``max_plan_lag_s``, so a plan that is kept never stops the vehicle
    max_check_age_s: float = 1.0
    #: the odometry further than this from the reference (a collision, a gust, a rejected command):
    #: the trajectory no longer describes the vehicle, so the next plan starts from the odometry
    #: (``math.inf``: never, e.g. when something other than these setpoints flies the vehicle)
    max_tracking_error: float = 1.0
    #: with an autopilot: the mapped obstacles grow by up to this much (metres; 0: never) beyond the
    #: planner's inflation, by the 95th percentile of the measured tracking error (:class:`TrackingMargin`)
    tracking_margin_max: float = 0.5
    #: optional box ((xmin, ymin, zmin), (xmax, ymax, zmax)) goals must lie in; without it a goal must
    #: lie inside the local map when it arrives (goals further than the horizon are then approached in steps)
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

    def __post_init__(self) -> None:
        if self.vehicle is None:
            self.vehicle = single_vehicle(self.namespace)
        self.vehicle.check_camera(self.camera)
        if self.bounds is not None:
            lo, hi = (np.asarray(b, dtype=float).reshape(3) for b in self.bounds)
            if not np.all(lo < hi):
                raise ValueError(f"bounds need min < max on every axis, got {self.bounds}")
        if self.replan_period_s <= 0 or self.depth_timeout_s <= 0 or self.goal_tolerance <= 0:
            raise ValueError("replan_period_s, depth_timeout_s and goal_tolerance must be positive")
        if self.max_yaw_rate <= 0:
            raise ValueError("max_yaw_rate must be positive")
        if not self.yaw_lookahead_s >= 0:
            raise ValueError(f"yaw_lookahead_s must be >= 0 (0: along the velocity), got "
                             f"{self.yaw_lookahead_s}")  # fmt: skip
        if self.max_plan_lag_s <= 0 or self.max_tracking_error <= 0:
            raise ValueError("max_plan_lag_s and max_tracking_error must be positive")
        if not self.max_check_age_s > self.max_plan_lag_s:
            raise ValueError(f"max_check_age_s ({self.max_check_age_s}) must exceed max_plan_lag_s "
                             f"({self.max_plan_lag_s})")  # fmt: skip
        if self.tracking_margin_max < 0:
            raise ValueError("tracking_margin_max must be >= 0")


class PlanNode:
    """The planner node: subscriptions, a planning thread and a 100 Hz (sim time) trajectory server."""

    def __init__(
        self,
        config: PlanNodeConfig | None = None,
        planner: PlannerConfig | None = None,
        autopilot: Autopilot | None = None,
    ) -> None:
        """``autopilot``: flies the trajectory-server samples instead of the PositionCommand topic, and its
        estimate replaces the odometry for planning (see the module docstring)."""
        self.cfg = config or PlanNodeConfig()
        # the optimiser's vectors are small: BLAS threads only contend with the simulator for the cores
        self._blas_limit = threadpool_limits(limits=1, user_api="blas")
        self._autopilot = autopilot
        self._setpoint: tuple[np.ndarray, np.ndarray, np.ndarray, float, float] | None = None
        self.planner = Planner(planner)
        #: the tracking error measured with an autopilot, and the extra obstacle margin it asks for
        self.tracking = TrackingMargin(self.cfg.tracking_margin_max if autopilot is not None else 0.0,
                                       self.planner.cfg.resolution)  # fmt: skip
        self._last_track_ns: int | None = None
        log.info("planner kernels ready in %.1f s", self.planner.warm_up())
        cam = self.cfg.camera
        #: the vehicle's topic names and TF frames
        self.names: VehicleNames = self.cfg.vehicle.names
        ns = self.names.namespace
        self.topics = {**self.names.topics(), **self.names.camera_topics(cam), "goal": f"/{ns}/planner/goal"}
        #: frame of the commands sent and of the goals taken besides map/world: the vehicle's odom
        self.frame = self.names.odom_frame
        self.node = RosZenohNode(
            ZenohNodeConfig(mode="peer", listen=(), connect=(self.cfg.zenoh,), node_name="droneulator_plan",
                            node_namespace=f"/{ns}")  # fmt: skip
        )
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._stop = False
        #: held while a command goes out, so close() can wait for the one in flight before the publisher
        #: goes (a put racing the undeclare fails in zenoh-python with "Already borrowed")
        self._send_lock = threading.Lock()
        # inputs (guarded by _lock)
        self._now_ns: int | None = None
        self._odom: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None  # stamp, p, q, v_world
        self._K: np.ndarray | None = None
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()  # stamp -> T_world_optical
        self._depth: tuple[int, np.ndarray] | None = None
        self._last_depth_ns: int | None = None
        self._goal: np.ndarray | None = None
        self._new_goal = False
        # output state (guarded by _lock)
        self._traj: BSpline | None = None
        self._traj_t0_ns = 0
        self._traj_id = 0
        self._traj_goal: np.ndarray | None = None  # the goal itself when the trajectory ends there
        self._failing = False  # the last plan attempt failed
        self._hold: np.ndarray | None = None  # stop point after a failed replan
        self._yaw: float | None = None
        self._last_cmd_ns: int | None = None
        self._holding_for_depth = False
        self._checked_ns: int | None = None  # sim time of the planning thread's latest look at the plan
        self._stalled_at: np.ndarray | None = None  # where the server holds while that look is overdue
        #: what ended the planning thread (an exception), None while it runs: nothing is commanded then
        self.error: BaseException | None = None
        #: counters for tests and logs
        self.plans = 0
        self.failures = 0
        self.stale_plans = 0
        self.off_track = 0
        #: times the server held because the planning thread had not looked at the plan for too long
        self.stalls = 0
        self.commands = 0
        self.reached = threading.Event()
        self.last_failure = ""
        self.cycle_s: list[float] = []
        self.map_s: list[float] = []
        #: sim seconds from each integrated depth image's stamp to the newest /clock heard once it was
        #: integrated: how far the map runs behind the simulation, which does not wait for this node (a
        #: little below 0 when the image came before the /clock of its own stamp)
        self.map_lag_s: list[float] = []
        #: the latest plans served, (sim time in ns, B-spline), newest last
        self.history: deque[tuple[int, BSpline]] = deque(maxlen=50)
        self._pub = self.node.publisher(self.topics["position_cmd"], TYPES["position_cmd"])
        t = self.topics
        self.node.subscribe(t["clock"], TYPES["clock"], self._on_clock)
        self.node.subscribe(t["odom"], TYPES["odom"], self._on_odom)
        self.node.subscribe(t["info_depth"], TYPES["info_depth"], self._on_info)
        self.node.subscribe(t["pose"], TYPES["pose"], self._on_pose)
        self.node.subscribe(t["depth"], TYPES["depth"], self._on_depth)
        self.node.subscribe(t["goal"], GOAL_TYPE, self._on_goal)
        self._thread = threading.Thread(target=self._plan_thread, name="plan", daemon=True)
        self._thread.start()
        log.info("planner for %s listening on %s (camera %s, goals on %s)", self.names.vehicle,
                 self.cfg.zenoh, cam, t["goal"])  # fmt: skip

    # ------------------------------------------------------------------ callbacks (Zenoh threads)
    def _on_clock(self, msg: Any) -> None:
        now = stamp_to_ns(msg.clock)
        with self._wake:
            self._now_ns = now
            self._wake.notify_all()
        self._serve(now)

    def _on_odom(self, msg: Any) -> None:
        p, o, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear
        q = np.array([o.x, o.y, o.z, o.w])
        v_world = frames.body_to_world(q, np.array([v.x, v.y, v.z]))
        with self._lock:
            self._odom = (header_ns(msg), np.array([p.x, p.y, p.z]), q, v_world)

    def _on_info(self, msg: Any) -> None:
        K = np.asarray(msg.k, dtype=float).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"depth camera_info has no intrinsics: K = {K.ravel().tolist()}")
        with self._lock:
            self._K = K

    def _on_pose(self, msg: Any) -> None:
        p, o = msg.pose.position, msg.pose.orientation
        T = frames.transform_from_pose(np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]))
        with self._lock:
            self._poses[header_ns(msg)] = T
            while len(self._poses) > 50:
                self._poses.popitem(last=False)

    def _on_depth(self, msg: Any) -> None:
        depth = decode_depth(msg)
        with self._wake:
            stamp = header_ns(msg)
            self._depth = (stamp, depth)
            self._last_depth_ns = stamp
            self._wake.notify_all()

    def _on_goal(self, msg: Any) -> None:
        p = msg.pose.position
        goal = np.array([p.x, p.y, p.z], dtype=float)
        if not np.all(np.isfinite(goal)):
            log.error("goal %s rejected: not finite", goal)
            return
        if msg.header.frame_id not in ("", self.frame, "map", "world"):
            log.error("goal rejected: frame %r is not %s/map/world", msg.header.frame_id, self.frame)
            return
        log.info("new goal %s", goal.round(3))
        with self._wake:
            self._goal = goal
            self._new_goal = True
            self.reached.clear()
            self._wake.notify_all()
        if self._autopilot is not None:
            self._autopilot.engage()

    # ------------------------------------------------------------------ public
    def set_goal(self, goal: np.ndarray) -> None:
        """Same as a goal message: plan to ``goal`` (the vehicle's odom frame, i.e. the world)."""
        msg = messages.pose_stamped(0, self.frame, np.asarray(goal, dtype=float), (0.0, 0.0, 0.0, 1.0))
        self._on_goal(msg)

    def stats(self) -> dict[str, Any]:
        """Counters and the wall time of every plan and map update (seconds), for benchmarks."""
        return {
            "plans": self.plans,
            "failures": self.failures,
            "stale_plans": self.stale_plans,
            "off_track": self.off_track,
            "stalls": self.stalls,
            "commands": self.commands,
            "last_failure": self.last_failure,
            "error": None if self.error is None else repr(self.error),
            "tracking": self.tracking.stats(),
            "plan_s": list(self.cycle_s),
            "map_update_s": list(self.map_s),
            "map_lag_s": list(self.map_lag_s),
        }

    def inputs(self) -> dict[str, Any]:
        """What has arrived so far: the clock and odometry stamps, whether the depth intrinsics came,
        how many camera poses are held and the newest depth image's stamp (sim s; None: not yet); for
        telling a missing topic from a slow one."""
        sec = lambda ns: None if ns is None else ns_to_seconds(ns)  # noqa: E731
        with self._lock:
            return {"clock": sec(self._now_ns), "odom": sec(None if self._odom is None else self._odom[0]),
                    "camera_info": self._K is not None, "poses": len(self._poses),
                    "newest_pose": sec(next(reversed(self._poses), None)), "depth": sec(self._last_depth_ns),
                    "depth_integrated": len(self.map_s)}  # fmt: skip

    def close(self) -> None:
        """Stop the planning thread and the trajectory server, and close the Zenoh session."""
        with self._wake:
            self._stop = True
            self._wake.notify_all()
        self._thread.join(timeout=5)
        with self._send_lock:  # the command in flight is out; none starts after this
            pass
        self.node.close()
        self._blas_limit.restore_original_limits()

    def __enter__(self) -> PlanNode:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ planning thread
    def _take_depth(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, int]:
        """The newest depth frame with its camera pose (same stamp) and K, or None; and its stamp."""
        if self._depth is None or self._K is None:
            return None, 0
        stamp, depth = self._depth
        T = self._poses.get(stamp)
        if T is None:
            return None, stamp
        self._depth = None
        return (depth, T, self._K), stamp

    def _plan_thread(self) -> None:
        """The planning loop; if it fails, the commands stop (the simulator's ``track_timeout`` then holds
        the vehicle) instead of the last plan being flown with nothing checking it against the map."""
        try:
            self._plan_loop()
        except BaseException as exc:
            log.exception("the planning thread failed: no more commands, the vehicle holds")
            with self._lock:
                self.error = exc

    def _plan_loop(self) -> None:
        last_plan_ns: int | None = None
        started, warned = time.monotonic(), False
        while True:
            with self._wake:
                self._wake.wait(timeout=0.05)
                if self._stop:
                    return
                frame, frame_stamp = self._take_depth()
                goal, new_goal = self._goal, self._new_goal
                self._new_goal = False
                odom, now = self._odom, self._now_ns
            if now is None and not warned and time.monotonic() - started > 5.0:
                log.warning("no /clock from %s after 5 s: is `droneulator run` up there?", self.cfg.zenoh)
                warned = True
            if frame is not None:
                t_map, integrated = time.perf_counter(), False
                try:
                    updates = self.planner.update_map(*frame)
                except ValueError as exc:
                    log.error("depth frame skipped: %s", exc)
                else:
                    self.map_s.append(time.perf_counter() - t_map)
                    integrated = True
                    if len(self.map_s) == 1:
                        log.info("first depth image integrated (%d voxel updates)", updates)
                with self._lock:  # the state the plan starts from is the one after the map update
                    odom, now = self._odom, self._now_ns
                if integrated and now is not None:
                    self.map_lag_s.append(ns_to_seconds(now - frame_stamp))
            with self._lock:
                traj, t0, hold = self._look(now)
            odom = self._flown_state(odom)
            if goal is None or odom is None or now is None or self.reached.is_set():
                continue
            if new_goal and not self._goal_allowed(goal):
                continue
            t_rel = ns_to_seconds(now - t0)
            if traj is not None and not new_goal:
                off = float(np.linalg.norm(odom[1] - traj.position(min(t_rel, traj.duration))))
                if off > self.cfg.max_tracking_error:
                    log.warning("the vehicle is %.2f m from its reference (a collision?): planning again "
                                "from its odometry", off)  # fmt: skip
                    self.off_track += 1
                    self._replan(goal, odom, now, traj, t_rel, new_goal, from_odom=True)
                    last_plan_ns = now
                    continue
                self._track(off, now)
            due = new_goal or last_plan_ns is None or now - last_plan_ns >= self.cfg.replan_period_s * 1e9
            ended = traj is not None and t_rel >= traj.duration and not new_goal
            if ended and self._traj_goal is goal:
                # the final leg is flown: wait at its end point for the odometry to converge
                self._arrive(goal, odom[1])
                continue
            if traj is None and hold is not None and not new_goal and self._arrive(goal, odom[1]):
                continue  # stopped by a failed replan, but at the goal: that is arriving too
            if due and traj is not None and not new_goal and self._traj_goal is goal:
                due = False  # the final leg is replanned only when it meets an obstacle, as EGO near the goal
            # a leg towards an intermediate (horizon) goal that has ended is continued at once
            if not (due or ended or self.planner.needs_replan(traj, t_rel)):
                continue
            if not new_goal and self._failing and now - last_plan_ns < RETRY_PERIOD_NS:
                continue  # after a failed plan, retry at most every RETRY_PERIOD_NS, not in a busy loop
            self._replan(goal, odom, now, traj, t_rel, new_goal)
            last_plan_ns = now

    def _look(self, now: int | None) -> tuple[BSpline | None, int, np.ndarray | None]:
        """The planning thread takes the plan it serves at sim time ``now`` (lock held): it marks the plan
        as looked at, and if the server held meanwhile it turns that hold into a stop, so the next plan
        starts from the odometry there. Returns (trajectory, its start in ns, stop point)."""
        if now is not None:
            self._checked_ns = now
        if self._stalled_at is not None:
            log.info("the planning thread is back: planning from where the vehicle held")
            self._traj, self._hold, self._stalled_at = None, self._stalled_at, None
        return self._traj, self._traj_t0_ns, self._hold

    def _arrive(self, goal: np.ndarray, position: np.ndarray) -> bool:
        """Count the goal as reached if ``position`` (the odometry, or the autopilot's estimate) is within
        ``goal_tolerance`` of it."""
        if np.linalg.norm(position - goal) > self.cfg.goal_tolerance:
            return False
        source = "odometry" if self._autopilot is None else "the autopilot's estimate"
        log.info("goal %s reached (%s %s)", goal.round(3), source, position.round(3))
        self.reached.set()
        return True

    def _track(self, off: float, now: int) -> None:
        """Take the tracking error ``off`` (at most one sample per TRACK_PERIOD_NS of sim time) and widen
        the mapped obstacles when its high percentile asks for more margin (planning thread: owns the map)."""
        if self._last_track_ns is not None and now - self._last_track_ns < TRACK_PERIOD_NS:
            return
        self._last_track_ns = now
        if self.tracking.add(off):
            m = self.tracking.margin
            log.info("the autopilot tracks its setpoints within %.2f m (p%g of %d samples): obstacles grown "
                     "by %.2f m more (%.2f m in all)", self.tracking.high, self.tracking.quantile,
                     self.tracking.count, m, self.planner.cfg.inflation + m)  # fmt: skip
            self.planner.map.set_tracking_margin(m)

    def _flown_state(self, odom: tuple | None) -> tuple | None:
        """(stamp, position, attitude, world velocity) of the vehicle in the frame its setpoints are
        flown in: the odometry, or with an autopilot its estimate (None until it holds under our control)."""
        if self._autopilot is None:
            return odom
        est = self._autopilot.estimate()
        if est is None:
            return None
        q = frames.quat_from_yaw(est.yaw) if est.yaw is not None else (None if odom is None else odom[2])
        if q is None:
            return None
        return (0 if odom is None else odom[0], est.position, q, est.velocity)

    def _replan(self, goal: np.ndarray, odom: tuple, now: int, traj: BSpline | None, t_rel: float,
                new_goal: bool, from_odom: bool = False) -> None:  # fmt: skip
        """Plan from the odometry state (first plan, or the vehicle off its reference) or the current
        reference (replans, continuity). A plan that took more than ``max_plan_lag_s`` of sim time is
        dropped: it starts where the vehicle was, and serving it would jump the reference ahead."""
        if traj is None or new_goal or from_odom:
            p0, v0, a0 = odom[1], odom[3], np.zeros(3)
        else:
            p0, v0, a0 = traj.position(t_rel), traj.velocity(t_rel), traj.acceleration(t_rel)
        t_wall = time.perf_counter()  # one planning cycle: the local goal's A* and the plan
        target = self.planner.local_goal(p0, goal)
        plan = self.planner.plan(p0, v0, a0, target)
        self.cycle_s.append(time.perf_counter() - t_wall)
        reason = self.planner.reason
        with self._lock:
            lag = ns_to_seconds(self._now_ns - now)
            if plan is not None and lag > self.cfg.max_plan_lag_s:
                log.warning("a plan took %.2f s of sim time (%.0f ms): dropped, planning again from the "
                            "newer state", lag, 1e3 * self.cycle_s[-1])  # fmt: skip
                self.stale_plans += 1
                if from_odom:
                    self._traj, self._hold = None, odom[1]
                return
            if plan is None:
                self.failures += 1
                self.last_failure = reason
                if new_goal or (traj is None and self._hold is None):
                    log.error("no motion: %s", reason)
                    self._traj, self._hold, self._goal = None, None, None
                elif from_odom:
                    log.warning("replan from the odometry failed (%s): stopping", reason)
                    self._traj, self._hold = None, odom[1]
                elif traj is None:
                    if not self._failing:
                        log.warning("still stopped at %s: %s; retrying", self._hold.round(2), reason)
                elif self.planner.time_to_collision(traj, t_rel) > self.cfg.stop_margin_s:
                    if not self._failing:
                        log.warning("replan failed (%s): keeping the trajectory while it is clear", reason)
                else:
                    log.warning("replan failed (%s) with an obstacle close ahead: stopping", reason)
                    self._traj, self._hold = None, p0
                self._failing = True
                return
            if self._failing:
                log.info("planning again after %d failed attempts", self.failures)
            self._failing = False
            self.plans += 1
            self._traj, self._traj_t0_ns, self._hold = plan, now, None
            self.history.append((now, plan))
            self._traj_goal = goal if np.array_equal(target, goal) else None
            self._traj_id += 1
        log.debug("plan %d: %.2f s to %s in %.0f ms", self.plans, plan.duration, target.round(2),
                  1e3 * self.cycle_s[-1])  # fmt: skip

    def _goal_allowed(self, goal: np.ndarray) -> bool:
        """Check a new goal against ``bounds`` (or the local map) and the map's occupancy; log why and
        drop it if it fails."""
        if self.cfg.bounds is not None:
            lo, hi = (np.asarray(b, dtype=float) for b in self.cfg.bounds)
            where = f"the bounds [{lo}, {hi}]"
        else:
            lo, hi = self.planner.map.bounds
            where = f"the local map [{lo.round(2)}, {hi.round(2)}]"
        m = self.planner.map
        if not (np.all(goal >= lo) and np.all(goal <= hi)):
            reason = f"goal {goal.round(2)} is outside {where}"
        elif m.inside(goal) and m.is_occupied(goal):
            near = self.planner.cfg.obstacle_inflation
            reason = f"goal {goal.round(2)} is occupied (within {near:g} m of an obstacle)"
        else:
            return True
        log.error("no motion: %s", reason)
        with self._lock:
            self.failures += 1
            self.last_failure = reason
            if self._goal is goal:
                self._goal = None
        return False

    # ------------------------------------------------------------------ trajectory server
    def _serve(self, now: int) -> None:
        """The trajectory server, on the ``/clock`` callback: the command for sim time ``now`` once the
        clock has advanced COMMAND_PERIOD_NS since the last one."""
        with self._lock:
            last = self._last_cmd_ns
            if self._stop or (last is not None and now - last < COMMAND_PERIOD_NS):
                return
            cmd = self._command(now)
            if cmd is None:
                return
            self._last_cmd_ns = now
            setpoint = self._setpoint
        with self._send_lock:
            if self._stop:
                return
            if self._autopilot is not None:
                self._autopilot.setpoint(ns_to_seconds(now), *setpoint)
            else:
                self._pub.publish(messages.serialize(cmd), now)
            self.commands += 1

    def _command(self, now: int) -> Any:
        """The PositionCommand for sim time ``now``, or None when nothing should be sent (lock held)."""
        if self.error is not None:
            return None
        stale = self._last_depth_ns is None or now - self._last_depth_ns > self.cfg.depth_timeout_s * 1e9
        if stale and (self._traj is not None or self._hold is not None):
            if not self._holding_for_depth:
                log.warning("no depth image for %.1f s of sim time: not commanding, the vehicle holds",
                            self.cfg.depth_timeout_s)  # fmt: skip
                self._holding_for_depth = True
            return None
        if self._holding_for_depth and not stale:
            log.info("depth images are back: commanding again")
            self._holding_for_depth = False
        overdue = self._checked_ns is not None and now - self._checked_ns > self.cfg.max_check_age_s * 1e9
        if self._traj is not None and overdue and self._stalled_at is None:
            t = min(ns_to_seconds(now - self._traj_t0_ns), self._traj.duration)
            self._stalled_at = self._traj.position(t)
            self.stalls += 1
            log.warning("the planning thread has not looked at the plan for %.2f s of sim time: holding at "
                        "%s until it does", ns_to_seconds(now - self._checked_ns),
                        self._stalled_at.round(2))  # fmt: skip
        if self._stalled_at is not None:
            p, v, a = self._stalled_at, np.zeros(3), np.zeros(3)
        elif self._traj is not None:
            t = min(ns_to_seconds(now - self._traj_t0_ns), self._traj.duration)
            p, v, a = self._traj.position(t), self._traj.velocity(t), self._traj.acceleration(t)
        elif self._hold is not None:
            p, v, a = self._hold, np.zeros(3), np.zeros(3)
        else:
            return None
        yaw_prev = self._yaw
        if yaw_prev is None:
            flown = self._flown_state(self._odom)
            yaw_prev = frames.yaw_of(flown[2]) if flown else 0.0
        flying = self._traj is not None and self._stalled_at is None
        want = self._traj.yaw(t, yaw_prev, self.cfg.yaw_lookahead_s) if flying else yaw_prev
        dt = COMMAND_PERIOD_NS / 1e9
        step = float(np.clip(frames.wrap_angle(want - yaw_prev), -self.cfg.max_yaw_rate * dt,
                             self.cfg.max_yaw_rate * dt))  # fmt: skip
        self._yaw = frames.wrap_angle(yaw_prev + step)
        self._setpoint = (p, v, a, self._yaw, step / dt)
        return messages.position_command(
            now, self.frame, p, v, a, self._yaw, step / dt, trajectory_id=self._traj_id
        )
