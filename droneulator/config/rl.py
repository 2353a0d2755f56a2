"""Settings of ``droneulator train``/``evaluate`` (the ``rl`` section of a config file and of ``--set``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from droneulator.config.camera_presets import DEPTH_PRESETS

#: the control levels a policy may act at (``rl.action``; :mod:`droneulator.workflows.rl.levels`)
ACTIONS = ("velocity", "ctbr", "attitude", "rotors")
#: RK4 sub-steps per 10 ms control period of the learning envs at the velocity level (``rl.substeps``)
VELOCITY_SUBSTEPS = 4


@dataclass
class RLConfig:
    """Workflow 3 (``droneulator train``/``evaluate``): vineyard navigation environment and its reward.

    The agent sees a depth strip from a small depth-only camera, the heading error to the goal (through
    a look-ahead point on the A* path, or straight at it) and its own speeds; it commands forward speed
    and yaw rate in velocity mode at a held altitude, or acts at a lower level (``action``). Reward:
    ``progress_scale * (d_prev - d) - step_penalty``, plus ``goal_reward`` within ``goal_radius`` of the
    goal or minus ``collision_penalty`` on a collision, with ``d`` the shortest-path distance to the goal.
    """

    #: the control level the policy acts at: "velocity" (forward speed and yaw rate, the altitude held),
    #: "ctbr" (collective thrust and body rates), "attitude" (collective thrust, tilt and yaw rate) or
    #: "rotors" (each rotor's thrust); all but "velocity" add body rates, attitude, vertical and lateral
    #: speed and the altitude error to the observation (docs/rl.md, "Control levels")
    action: str = "velocity"
    altitude: float = 1.5
    #: depth camera (depth only, no shadows): its centre row is min-pooled into the 32-sample strip
    camera_width: int = 128
    camera_height: int = 9
    hfov_deg: float = 90.0
    #: depth is clipped here and normalised by it; the camera's far plane sits here too (faithful: a miss
    #: and a return beyond it both read 1.0)
    depth_clip: float = 10.0
    #: the depth camera's error model (``render.cameras[].depth_model``'s presets): "ideal" (exact), "d435"
    #: or "tof"; its noise is seeded by the config seed
    depth_model: str = "ideal"
    forward_min: float = -2.0
    forward_max: float = 3.0
    max_yaw_rate: float = 1.5
    progress_scale: float = 1.0
    step_penalty: float = 0.01
    goal_reward: float = 100.0
    collision_penalty: float = 30.0
    goal_radius: float = 1.5
    #: occupancy grid: cell size and the safety margin added to the vehicle's collision radius
    grid_resolution: float = 0.1
    safety_margin: float = 0.3
    #: heading error toward "path" (a point ``lookahead`` m along the shortest path) or "goal" (straight)
    heading: str = "path"
    lookahead: float = 2.0
    #: start/goal sampling: shortest-path distance range and the share of goals in another alley
    min_separation: float = 8.0
    max_path_length: float = 45.0
    other_row_prob: float = 0.7
    #: start heading: toward the first leg of the shortest path, plus normal noise of this std (deg)
    start_yaw_std_deg: float = 30.0
    #: episode time limit (truncation): base seconds plus the initial path length over this speed
    time_limit_base_s: float = 10.0
    min_average_speed: float = 0.75
    #: with several agents per world (``--agents``): each agent observes the nearest other agent of its
    #: world within this range (m), its position and velocity relative to its own in its heading frame, as
    #: a swarm's position broadcast gives them (the depth strip sees crossing traffic too late); 0: depth
    #: alone
    neighbour_range: float = 4.0
    #: with several agents per world, in **training** envs only: the share of drawn tasks that send an
    #: agent against another of its world (its start beside that one's goal, its goal beside that one's
    #: position: one route flown both ways), since drawn tasks seldom meet (in 20,000 steps of 8 worlds of
    #: two agents the path teacher never had to give way); held-out checks and evaluations draw with 0
    encounters: float = 0.0
    #: the scale of the actions below velocity: the collective thrust (``ctbr``, ``attitude``) or a
    #: rotor's thrust times four (``rotors``) at +1 as a multiple of the weight, capped at every rotor at
    #: full speed; and the body rates at +-1 (``ctbr``; deg/s: roll, pitch, yaw), capped at the airframe's
    #: ``flight.max_body_rate_deg_s``, which the levels' observation also reads as +-1. null: the
    #: airframe's whole range (a Hummingbird lifts ten times its weight and turns at 720 deg/s)
    max_thrust_to_weight: float | None = None
    max_body_rate_deg_s: tuple[float, float, float] | None = None
    #: RK4 sub-steps per control period in the learning envs (replacing ``vehicle.substeps`` there). null:
    #: :data:`VELOCITY_SUBSTEPS` at the velocity level, whose controller keeps the flight smooth (positions
    #: within 1 um of 1,000 sub-steps after 5 s of random commands, docs/rl.md), and ``vehicle.substeps``
    #: at the levels below, whose commands reach the rotors' 5 ms lag directly
    substeps: int | None = None

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"rl.action must be one of {', '.join(ACTIONS)}, got {self.action!r}")
        if self.heading not in ("path", "goal"):
            raise ValueError(f"rl.heading must be 'path' or 'goal', got {self.heading!r}")
        if not self.forward_min < 0 < self.forward_max or not self.max_yaw_rate > 0:
            raise ValueError("rl.forward_min < 0 < rl.forward_max and rl.max_yaw_rate > 0 are required")
        if self.camera_width < 32 or self.camera_height < 1:
            raise ValueError("rl.camera_width must be at least 32 (one pixel per strip sample)")
        if not 0 < self.min_separation < self.max_path_length:
            raise ValueError("rl.min_separation must be positive and below rl.max_path_length")
        if self.max_thrust_to_weight is not None and not (
            math.isfinite(self.max_thrust_to_weight) and self.max_thrust_to_weight > 1.0
        ):
            ratio = self.max_thrust_to_weight
            raise ValueError(f"rl.max_thrust_to_weight must be a number above 1 or null, got {ratio}")
        if self.max_body_rate_deg_s is not None and (
            len(self.max_body_rate_deg_s) != 3
            or not all(math.isfinite(r) and r > 0 for r in self.max_body_rate_deg_s)
        ):
            rates = self.max_body_rate_deg_s
            raise ValueError(f"rl.max_body_rate_deg_s must be three positive numbers or null, got {rates}")
        if not (math.isfinite(self.neighbour_range) and self.neighbour_range >= 0.0):
            raise ValueError(f"rl.neighbour_range must be a distance >= 0 (m), got {self.neighbour_range!r}")
        if not 0.0 <= self.encounters <= 1.0:
            raise ValueError(f"rl.encounters must be a share in [0, 1], got {self.encounters!r}")
        if self.substeps is not None and (
            isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or self.substeps < 1
        ):
            raise ValueError(f"rl.substeps must be a whole number >= 1 or null, got {self.substeps!r}")
        if self.depth_model not in DEPTH_PRESETS:
            choices = ", ".join(DEPTH_PRESETS)
            raise ValueError(f"rl.depth_model must be one of {choices}, got {self.depth_model!r}")

    def substeps_for(self, vehicle_substeps: int) -> int:
        """The RK4 sub-steps per control period the learning envs fly (see :attr:`substeps`)."""
        if self.substeps is not None:
            return self.substeps
        return VELOCITY_SUBSTEPS if self.action == "velocity" else vehicle_substeps
