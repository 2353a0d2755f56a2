"""Many independent one-vehicle worlds of one scene, stepped together (:class:`BatchedWorlds`).

Learning needs many copies of one task, not many vehicles in one world: each copy has its own clock and
its own vehicle, the copies never see each other, and all of them step in one compiled call (ManiSkill's
batched sub-scenes; RotorPy's ``BatchedMultirotor`` N-axis state). Every copy steps exactly as a
:class:`~droneulator.world.World` with one vehicle does (same control period, camera instants, SE(3)
controller, RK4 sub-steps and scene collisions, using the same compiled functions), so a copy's flight
equals the single world's to float rounding; only the flight modes learning uses are batched: hold and
velocity mode (the paper's unicycle command path: :func:`~droneulator.controllers.velocity.velocity_flat`,
the compiled reference every :class:`~droneulator.controllers.velocity.VelocityReference` runs).

The copies share the scene, so its layout is the config's scene and seed. Each copy flies in its own
realisation of the wind field (:mod:`droneulator.wind.field`, ``config.wind``; settable per copy with
:meth:`BatchedWorlds.set_wind`, for domain randomisation), sampled once a camera frame and held over it
(a single world samples it every control period: the two agree exactly in calm air only). RotorPy's wind
profiles (``vehicle.wind``) are not batched.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from droneulator.config import SimConfig
from droneulator.controllers.se3 import se3_into
from droneulator.controllers.velocity import VCMD, VREF_SIZE, start_reference, velocity_flat, velocity_limits
from droneulator.frames import quat_from_yaw, yaw_of
from droneulator.frames_numba import set_quat_from_yaw
from droneulator.frames_numba import yaw_of as yaw_of_nb
from droneulator.scenes import get_scene
from droneulator.state import FLAT_SIZE, STATE, STATE_SIZE
from droneulator.vehicles.dynamics import OUTPUT_SIZE, ParamTable, integrate, work_arrays
from droneulator.vehicles.vehicle import Vehicle
from droneulator.wind.field import WindField
from droneulator.world.world import NS

#: where the attitude quaternion starts in the packed state (a plain int for the compiled kernels)
_Q = STATE.q.start
#: flight modes of a copy (a collided copy stays where it stopped until placed again)
HOLD, VELOCITY, COLLIDED = 0, 1, 2


@numba.njit(cache=True)
def _step_copy(
    b, states, vref, mode, hold, t_ns, next_frame, run, period_ns, camera_ns, substep, lim, P, G, D, gains,
    sdf, origin, res, radius, flat, cmd, out, work, R, cam, hit,
):  # fmt: skip
    """Step copy ``b`` one control period at a time up to the end of the period holding its next camera
    instant, as :meth:`World.step` does: the reference for the period, the SE(3) command, then RK4 split at
    the camera instant, where the state is copied to ``cam[b]``. A copy that touches the scene stops there,
    level (``hit[b]``, mode collided) and is not integrated further; its clock goes on."""
    s = states[b]
    dt = period_ns / NS
    alive = mode[b] != COLLIDED
    hit[b] = False
    while True:
        if mode[b] == VELOCITY:
            velocity_flat(vref[b], dt, s, lim, flat[b])
        else:
            for j in range(FLAT_SIZE):
                flat[b, j] = hold[b, j]
        se3_into(s, flat[b], gains, cmd[b], R[b])
        t_end = t_ns[b] + period_ns
        framed = False
        while t_ns[b] < t_end:
            t_next = min(t_end, next_frame[b])
            h = (t_next - t_ns[b]) / NS
            n_sub = max(1, math.ceil(h / substep - 1e-9))
            if alive:
                for j in range(OUTPUT_SIZE):
                    out[b, j] = 0.0
                if integrate(s, cmd[b], h, n_sub, P, G, D, sdf, origin, res, radius, out[b], work[b], R[b]):
                    hit[b] = True
                    alive = False
                    mode[b] = COLLIDED
                    # Vehicle.on_collision: it stops where it is, level
                    for j in range(3, 6):
                        s[j] = 0.0
                    for j in range(10, 13):
                        s[j] = 0.0
                    set_quat_from_yaw(s[_Q : _Q + 4], yaw_of_nb(s[_Q : _Q + 4]))
            t_ns[b] = t_next
            if t_ns[b] == next_frame[b]:
                for j in range(STATE_SIZE):
                    cam[b, j] = s[j]
                next_frame[b] += camera_ns
                framed = True
        if framed:
            return


@numba.njit(cache=True, parallel=True)
def _step_copies(
    states, vref, mode, hold, t_ns, next_frame, run, period_ns, camera_ns, substep, lim, P, G, D, gains, sdf,
    origin, res, radius, flat, cmd, out, work, R, cam, hit,
):  # fmt: skip
    for b in numba.prange(states.shape[0]):
        if run[b]:
            _step_copy(b, states, vref, mode, hold, t_ns, next_frame, run, period_ns, camera_ns,
                       substep, lim, P, G, D, gains, sdf, origin, res, radius, flat, cmd, out, work, R, cam,
                       hit)  # fmt: skip


class BatchedWorlds:
    """``num_worlds`` independent one-vehicle worlds of ``config``'s scene, stepped one camera frame at a
    time in one compiled, multi-threaded call.

    ``states`` is ``(num_worlds, STATE_SIZE)`` (RotorPy's layout, :data:`~droneulator.state.STATE`);
    each copy has its own clock ``t_ns``. :meth:`place` puts copies hovering at a pose (as
    ``World.reset(position=..., yaw=..., airborne=True)``), :meth:`velocity` gives them velocity-mode
    commands (as ``Vehicle.velocity``) and :meth:`step_frame` advances chosen copies to their next camera
    instant, returning the state there and whether they touched the scene on the way.
    """

    def __init__(self, config: SimConfig, num_worlds: int) -> None:
        if int(num_worlds) < 1:
            raise ValueError(f"num_worlds must be at least 1, got {num_worlds!r}")
        if config.vehicle.wind != "none":
            raise ValueError(
                "batched worlds take the wind field (the wind section), not RotorPy's profiles: "
                "set vehicle.wind = 'none'"
            )
        specs = config.vehicle_specs()
        if len(specs) != 1:
            raise ValueError("each batched world holds one vehicle: give at most one vehicle in the config")
        self.config = config
        self.num_worlds = n = int(num_worlds)
        self.scene = get_scene(config.scene, config.seed, config.vegetation)
        spec = specs[0]
        # one template vehicle of the spec gives the packed airframe, gains and limits every copy uses
        template_row, template_motion = np.zeros(STATE_SIZE), np.zeros(6)
        vehicle = Vehicle(self, config, spec, template_row, template_motion, 0)
        table = ParamTable()
        table.add((spec.params,), vehicle.packed)
        self._P, self._G, self._D = table.params[0], table.geometry[0], table.directions[0]
        self._gains = vehicle.flight.se3.gains()
        self.hover_speed = vehicle.hover_speed
        self.radius = vehicle.collision_radius
        fc = vehicle.flight_config
        self.max_speed = fc.max_speed
        self._lim = velocity_limits(fc)
        self.period_ns = round(NS / config.vehicle.control_hz)
        self.camera_ns = round(NS / config.render.camera_hz)
        self._substep = 1.0 / (config.vehicle.control_hz * config.vehicle.substeps)
        self.states = np.zeros((n, STATE_SIZE))
        self.t_ns = np.zeros(n, dtype=np.int64)
        self._next_frame = np.full(n, self.camera_ns, dtype=np.int64)
        self.mode = np.full(n, HOLD, dtype=np.int64)
        self._vref = np.zeros((n, VREF_SIZE))
        self._hold = np.zeros((n, FLAT_SIZE))
        self._flat = np.zeros((n, FLAT_SIZE))
        self._cmd = np.zeros((n, 4))
        self._out = np.zeros((n, OUTPUT_SIZE))
        self._work, self._R = work_arrays(n)
        self.camera_states = np.zeros((n, STATE_SIZE))
        self.hit = np.zeros(n, dtype=bool)
        #: every copy's wind, sampled once a camera frame
        self.wind = WindField(config.wind, n, self.camera_ns / NS, config.seed, self.scene.collision)

    def set_wind(self, configs: Any, idx: np.ndarray | None = None) -> None:
        """The wind settings (one :class:`~droneulator.config.WindConfig`, or one per copy) of copies ``idx``
        (None: all), from their next step on."""
        self.wind.configure(configs, list(self._rows(idx)))

    def _rows(self, idx: np.ndarray | None) -> np.ndarray:
        return np.arange(self.num_worlds) if idx is None else np.asarray(idx, dtype=np.int64).reshape(-1)

    def place(self, idx: np.ndarray, positions: np.ndarray, yaws: np.ndarray) -> None:
        """Restart copies ``idx`` at t = 0, at rest, hovering at ``positions`` (k, 3) facing ``yaws`` (k,)."""
        rows = self._rows(idx)
        pos = np.asarray(positions, dtype=float).reshape(len(rows), 3)
        yaw = np.asarray(yaws, dtype=float).reshape(len(rows))
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(yaw))):
            raise ValueError("positions and yaws must be finite")
        for k, b in enumerate(rows):
            s = self.states[b]
            s[:] = 0.0
            s[STATE.x] = pos[k]
            s[STATE.q] = quat_from_yaw(float(yaw[k]))
            s[STATE.rotor_speeds] = self.hover_speed
            self._hold[b] = 0.0
            self._hold[b, 0:3] = pos[k]
            self._hold[b, 9] = yaw_of(s[STATE.q])
        self.mode[rows] = HOLD
        self.t_ns[rows] = 0
        self._next_frame[rows] = self.camera_ns
        self.wind.reset_rows(rows)

    def velocity(self, idx: np.ndarray | None, forward: np.ndarray, yaw_rate: np.ndarray) -> None:
        """Velocity-mode commands (forward speed m/s, yaw rate rad/s) for copies ``idx`` (None: all); a
        copy entering the mode starts its reference where its hold reference is, at its current speed."""
        rows = self._rows(idx)
        f = np.asarray(forward, dtype=float).reshape(len(rows))
        r = np.asarray(yaw_rate, dtype=float).reshape(len(rows))
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(r))):
            raise ValueError("forward and yaw_rate must be finite numbers")
        if np.any(np.abs(f) > self.max_speed) or np.any(np.abs(r) > math.pi):
            raise ValueError(f"need |forward| <= {self.max_speed} m/s and |yaw_rate| <= pi rad/s")
        if np.any(self.mode[rows] == COLLIDED):
            raise ValueError("a collided copy takes no command until it is placed again")
        entering = rows[self.mode[rows] != VELOCITY]
        for b in entering:
            hold = self._hold[b]
            yaw = float(hold[9])
            speed0 = float(self.states[b, 3:5] @ (math.cos(yaw), math.sin(yaw)))
            start_reference(self._vref[b], hold[0:3], yaw, speed0, 0.0)
        self.mode[entering] = VELOCITY
        self._vref[rows, VCMD] = f
        self._vref[rows, VCMD + 1] = r

    def frame_t_ns(self) -> np.ndarray:
        """Each copy's latest camera instant (ns since its :meth:`place`)."""
        return self._next_frame - self.camera_ns

    def step_frame(self, run: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Advance the copies where ``run`` (bool, num_worlds; None: all) to the end of the control period
        holding their next camera instant. Returns (states at those instants, touched the scene), both
        arrays this object reuses (rows of copies not run keep old values)."""
        mask = np.ones(self.num_worlds, dtype=bool) if run is None else np.asarray(run, dtype=bool)
        col = self.scene.collision
        if not self.wind.calm:
            self.states[:, STATE.wind] = self.wind.update(self.states[:, STATE.x], self.states[:, STATE.v])
        else:
            self.states[:, STATE.wind] = 0.0
        _step_copies(
            self.states, self._vref, self.mode, self._hold, self.t_ns, self._next_frame, mask, self.period_ns,
            self.camera_ns, self._substep, self._lim, self._P, self._G, self._D, self._gains, col.sdf,
            col.origin, col.resolution, self.radius, self._flat, self._cmd, self._out, self._work, self._R,
            self.camera_states, self.hit,
        )  # fmt: skip
        return self.camera_states, self.hit
