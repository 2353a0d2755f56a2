"""PX4 quad-X motor outputs -> RotorPy rotor speeds.

Motor order
    PX4's quad-X (airframe 4001, SITL ``10016_none_iris``; ``CA_ROTOR0..3``) numbers its motors
    1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW (spin seen from above).
    RotorPy parameter sets list rotors in any order, so the order is *derived*: each PX4 motor is
    matched to the RotorPy rotor in its quadrant (from ``rotor_pos``, body FLU) whose spin agrees
    (``rotor_directions``: RotorPy adds ``dir * k_m * w^2`` to the body yaw moment about +z up, so
    ``+1`` is a clockwise propeller, ``-1`` a counter-clockwise one). A set that is not a quad-X
    with that spin pattern is refused, since PX4 would then fly it with the wrong mixer.

Output -> speed
    PX4's ``pwm_out_sim`` scales non-reversible motor outputs ``u`` to [0, 1] and sends zeros while
    disarmed. PX4's mixer assumes the thrust model of its ``THR_MDL_FAC`` parameter, thrust
    fraction ``f(u) = (1 - k) u + k u^2``, default ``k = 0``: thrust linear in ``u``, which is what
    PX4's own SIH (``T = SIH_T_MAX * u``, the source of RotorPy's ``px4_quadx`` set) and jMAVSim
    simulate. With rotor thrust ``k_eta w^2``, the rotor speed that gives that thrust is
    ``w = w_min + (w_max - w_min) sqrt(f(u))`` between the set's ``rotor_speed_min`` and
    ``rotor_speed_max``. ``PX4Config.thrust_model_factor`` is ``k``: keep it equal to PX4's
    ``THR_MDL_FAC``. ``k = 1`` makes speed linear in ``u``, the map of PX4's Gazebo-classic Iris
    (``w = 1000 u + 100`` rad/s) and of RotorPy's ``PX4Multirotor``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.logs import LogThrottle

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PX4Motor:
    """One motor of a quad-X motor table (PX4's, or ArduPilot's in :mod:`droneulator.ardupilot.mixing`):
    number, position signs in the FRD body frame, spin seen from above."""

    number: int
    name: str
    forward: int
    right: int
    spin: str


PX4_QUAD_X: tuple[PX4Motor, ...] = (
    PX4Motor(1, "front-right", +1, +1, "CCW"),
    PX4Motor(2, "rear-left", -1, -1, "CCW"),
    PX4Motor(3, "front-left", +1, -1, "CW"),
    PX4Motor(4, "rear-right", -1, +1, "CW"),
)


def _spin(direction: float) -> str:
    return "CW" if direction > 0 else "CCW"


def px4_rotor_order(quad_params: dict[str, Any]) -> tuple[int, ...]:
    """Index of the RotorPy rotor driven by each PX4 quad-X motor (motor 1 first).

    Raises ValueError when the parameter set is not a quad-X whose quadrants and spins match PX4's.
    """
    return quad_x_rotor_order(quad_params, PX4_QUAD_X, "PX4")


def quad_x_rotor_order(
    quad_params: dict[str, Any], motors: Sequence[PX4Motor], autopilot: str
) -> tuple[int, ...]:
    """Index of the RotorPy rotor driven by each motor of ``autopilot``'s quad-X table ``motors`` (in
    the table's order): the rotor in the motor's quadrant whose spin agrees.

    Raises ValueError when the parameter set is not a quad-X whose quadrants and spins match the table.
    """
    names = list(quad_params["rotor_pos"])
    pos = np.array([quad_params["rotor_pos"][k] for k in names], dtype=float)
    dirs = np.asarray(quad_params["rotor_directions"], dtype=float)
    if len(names) != 4 or dirs.shape != (4,):
        raise ValueError(f"{autopilot} quad-X needs 4 rotors, this parameter set has {len(names)}")
    arm = float(np.max(np.linalg.norm(pos[:, :2], axis=1)))
    order: list[int] = []
    for m in motors:
        # FRD forward = FLU x, FRD right = -FLU y
        hits = [
            i
            for i in range(4)
            if np.sign(pos[i, 0]) == m.forward
            and np.sign(-pos[i, 1]) == m.right
            and min(abs(pos[i, 0]), abs(pos[i, 1])) > 0.1 * arm
        ]
        if len(hits) != 1:
            layout = {k: np.round(p, 3).tolist() for k, p in zip(names, pos, strict=True)}
            raise ValueError(
                f"{autopilot} quad-X motor {m.number} sits {m.name}, but this parameter set has {len(hits)} "
                f"rotors there (rotor_pos, body FLU: {layout}); it is not an X frame"
            )
        i = hits[0]
        if dirs[i] == 0 or _spin(dirs[i]) != m.spin:
            raise ValueError(
                f"rotor {names[i]!r} ({m.name}) spins {_spin(dirs[i]) if dirs[i] else 'nowhere'} but "
                f"{autopilot} quad-X motor {m.number} ({m.name}) spins {m.spin}: {autopilot} would yaw this "
                "vehicle the wrong way; use a parameter set with front-right/rear-left CCW, "
                "front-left/rear-right CW"
            )
        order.append(i)
    return tuple(order)


class MotorMap:
    """Quad-X motor outputs in [0, 1] (motor 1..4 of ``motors``, PX4's table by default) -> rotor speeds
    in RotorPy order (rad/s). ``thrust_model_factor`` is the ``k`` of the thrust fraction
    ``(1 - k) u + k u^2`` (PX4's THR_MDL_FAC in [0, 1]; ArduPilot's MOT_THST_EXPO, in [-1, 1])."""

    def __init__(
        self,
        quad_params: dict[str, Any],
        thrust_model_factor: float = 0.0,
        motors: Sequence[PX4Motor] = PX4_QUAD_X,
        autopilot: str = "PX4",
    ) -> None:
        if not -1.0 <= thrust_model_factor <= 1.0:
            raise ValueError(
                "thrust_model_factor (PX4's THR_MDL_FAC, ArduPilot's MOT_THST_EXPO) must lie in [-1, 1]"
            )
        self.k = float(thrust_model_factor)
        self.motors = tuple(motors)
        self.autopilot = autopilot
        self.order = quad_x_rotor_order(quad_params, self.motors, autopilot)
        self.rotor_names = list(quad_params["rotor_pos"])
        self.w_min = float(quad_params["rotor_speed_min"])
        self.w_max = float(quad_params["rotor_speed_max"])
        if not self.w_max > self.w_min >= 0.0:
            raise ValueError(
                f"need 0 <= rotor_speed_min < rotor_speed_max to map {autopilot} outputs to rotor speeds"
            )
        self._last_valid = np.zeros(4)
        self._errors = LogThrottle(log, period=1.0)

    def output_to_speed(self, u: Any) -> np.ndarray:
        """Rotor speed (rad/s) whose thrust is the fraction ``(1 - k) u + k u^2`` of full thrust."""
        u = np.asarray(u, dtype=float)
        return self.w_min + (self.w_max - self.w_min) * np.sqrt((1.0 - self.k) * u + self.k * u * u)

    def speed_to_output(self, w: Any) -> np.ndarray:
        """Inverse of :meth:`output_to_speed`: the output the autopilot must command for rotor speed ``w``."""
        f = ((np.asarray(w, dtype=float) - self.w_min) / (self.w_max - self.w_min)) ** 2
        if self.k == 0.0:
            return f
        return (-(1.0 - self.k) + np.sqrt((1.0 - self.k) ** 2 + 4.0 * self.k * f)) / (2.0 * self.k)

    def sanitize(self, outputs: Any) -> np.ndarray:
        """The four motor outputs, each in [0, 1]: out-of-range values are clipped and non-finite
        ones replaced by that motor's last valid output, with a (rate-limited) logged error."""
        u = np.asarray(outputs, dtype=float).reshape(-1)[:4]
        if u.shape != (4,):
            self._errors.error(
                "short", "%s sent %d motor outputs, need 4: holding the last outputs", self.autopilot, u.size
            )
            return self._last_valid.copy()
        bad = ~np.isfinite(u)
        if bad.any():
            self._errors.error(
                "nonfinite",
                "%s motor outputs %s are not finite: motors %s keep their last valid output",
                self.autopilot,
                u.tolist(),
                [self.motors[i].number for i in np.flatnonzero(bad)],
            )
            u = np.where(bad, self._last_valid, u)
        if np.any(u < 0.0) or np.any(u > 1.0):
            self._errors.error(
                "range", "%s motor outputs %s outside [0, 1]: clipped", self.autopilot, u.tolist()
            )
            u = np.clip(u, 0.0, 1.0)
        self._last_valid = u.copy()
        return u

    def rotor_speeds(self, outputs: Any) -> np.ndarray:
        """Rotor speeds (rad/s) in RotorPy order for motor outputs (validated by :meth:`sanitize`)."""
        w = np.zeros(4)
        w[list(self.order)] = self.output_to_speed(self.sanitize(outputs))
        return w

    def table(self) -> list[tuple[int, str, str, str]]:
        """(motor, position, spin, RotorPy rotor) rows, for logs and docs."""
        return [
            (m.number, m.name, m.spin, self.rotor_names[i])
            for m, i in zip(self.motors, self.order, strict=True)
        ]
