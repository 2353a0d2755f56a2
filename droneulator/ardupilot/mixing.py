"""ArduCopter quad-X servo PWM -> RotorPy rotor speeds.

Motor order
    ArduCopter's quad X (``FRAME_CLASS 1``, ``FRAME_TYPE 1``; ``AP_MotorsMatrix::setup_quad_matrix``)
    defines motor i by its angle from the nose, clockwise seen from above, and its yaw factor
    (``AP_MOTORS_MATRIX_YAW_FACTOR_CCW = 1``, ``_CW = -1``): motor 1 at 45 deg CCW, motor 2 at -135 deg
    CCW, motor 3 at -45 deg CW, motor 4 at 135 deg CW, i.e. 1 front-right CCW, 2 rear-left CCW,
    3 front-left CW, 4 rear-right CW: the same layout as PX4's quad-X. With the default
    ``SERVOn_FUNCTION`` (33 + i - 1 on SERVOi) motor i is PWM channel i - 1 of the servo packet. The
    RotorPy rotor of each motor is derived from the parameter set's geometry and spins
    (:func:`~droneulator.px4.mixing.quad_x_rotor_order`), and a set that does not match is refused.

PWM -> speed
    ArduCopter computes a thrust fraction ``t`` per motor, then (``Thrust_Linearization::
    thrust_to_actuator`` and ``AP_MotorsMulticopter::output_to_pwm``) the throttle ratio ``r`` that solves
    ``t = (1 - e) r + e r^2`` (``e`` = ``MOT_THST_EXPO``, default 0.65), the actuator
    ``a = spin_min + (spin_max - spin_min) r`` and ``pwm = pwm_min + (pwm_max - pwm_min) a``. The map
    inverts that chain: PWM -> ``a`` -> ``r`` (clipped to [0, 1]: below ``MOT_SPIN_MIN`` a rotor makes no
    thrust) -> thrust fraction ``t`` -> the rotor speed whose thrust ``k_eta w^2`` is that fraction,
    ``w = w_min + (w_max - w_min) sqrt(t)``. So the plant has exactly the thrust curve ArduCopter's
    linearisation assumes: with the right ``ardupilot`` settings its thrust commands are linear in the
    thrust the rotors give, and its hover throttle learning (``MOT_THST_HOVER``) settles where the plant
    hovers. A speed-linear map (``e = 1``) is what ``ardupilot.thrust_expo = 1`` gives. ArduCopter's
    battery voltage compensation (``MOT_BAT_VOLT_MAX``) scales ``t`` by a few percent, which its
    controllers absorb; the plant has no battery.

Armed
    The servo packet carries no arming flag. Disarmed, ArduCopter outputs ``MOT_PWM_MIN`` on every motor
    (0 before its outputs start); armed, at least ``MOT_SPIN_ARM`` (10 % above it by default). A motor
    PWM more than :data:`ARMED_MARGIN` of the range above ``pwm_min`` reads as armed.

The eight-rotor (octo-quad) mapping of the sprayer airframe is not here yet.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from droneulator.config import ArduPilotConfig
from droneulator.px4.mixing import MotorMap, PX4Motor

#: (motor number, angle from the nose clockwise in degrees, yaw factor), AP_MotorsMatrix.cpp quad X
ARDUCOPTER_QUAD_X_DEFS: tuple[tuple[int, float, int], ...] = (
    (1, 45.0, +1),
    (2, -135.0, +1),
    (3, -45.0, -1),
    (4, 135.0, -1),
)

#: a motor PWM this fraction of the PWM range above ``pwm_min`` reads as armed (MOT_SPIN_ARM is 0.10)
ARMED_MARGIN = 0.02


def _motor(number: int, angle_deg: float, yaw_factor: int) -> PX4Motor:
    forward = int(math.copysign(1, round(math.cos(math.radians(angle_deg)), 9)))
    right = int(math.copysign(1, round(math.sin(math.radians(angle_deg)), 9)))
    name = f"{'front' if forward > 0 else 'rear'}-{'right' if right > 0 else 'left'}"
    return PX4Motor(number, name, forward, right, "CCW" if yaw_factor > 0 else "CW")


#: ArduCopter's quad X motors 1..4: position signs (FRD) and spin, from :data:`ARDUCOPTER_QUAD_X_DEFS`
ARDUCOPTER_QUAD_X: tuple[PX4Motor, ...] = tuple(_motor(*d) for d in ARDUCOPTER_QUAD_X_DEFS)


class ArduCopterMotors:
    """ArduCopter quad-X servo PWM (channels 1..4) -> rotor speeds in RotorPy order, for ``cfg``'s
    ``MOT_*`` settings (see the module's text)."""

    def __init__(self, quad_params: dict[str, Any], cfg: ArduPilotConfig | None = None) -> None:
        self.cfg = cfg = cfg or ArduPilotConfig()
        self.map = MotorMap(quad_params, cfg.thrust_expo, ARDUCOPTER_QUAD_X, "ArduPilot")

    @property
    def order(self) -> tuple[int, ...]:
        """RotorPy rotor index of motors 1..4."""
        return self.map.order

    def actuator(self, pwm: Any) -> np.ndarray:
        """Actuator fractions ``a`` in [0, 1] of motor PWMs (0 and other values out of range clipped)."""
        c = self.cfg
        p = np.asarray(pwm, dtype=float)
        return np.clip((p - c.pwm_min) / (c.pwm_max - c.pwm_min), 0.0, 1.0)

    def throttle_ratio(self, pwm: Any) -> np.ndarray:
        """Throttle ratios ``r`` in [0, 1] between MOT_SPIN_MIN and MOT_SPIN_MAX of motor PWMs."""
        c = self.cfg
        return np.clip((self.actuator(pwm) - c.spin_min) / (c.spin_max - c.spin_min), 0.0, 1.0)

    def armed(self, pwm: Any) -> bool:
        """Whether motor PWMs 1..4 say ArduCopter is armed (see :data:`ARMED_MARGIN`)."""
        return bool(np.any(self.actuator(np.asarray(pwm)[:4]) > ARMED_MARGIN))

    def rotor_speeds(self, pwm: Any) -> np.ndarray:
        """Rotor speeds (rad/s, RotorPy order) for a servo packet's PWMs (motors 1..4 come first)."""
        return self.map.rotor_speeds(self.throttle_ratio(np.asarray(pwm)[:4]))

    def pwm_for_speed(self, w: Any) -> np.ndarray:
        """The PWM ArduCopter must output for rotor speed ``w`` (rad/s): the map's inverse, for tests and
        tools (a scripted mixer)."""
        c = self.cfg
        r = self.map.speed_to_output(np.clip(w, self.map.w_min, self.map.w_max))
        a = c.spin_min + (c.spin_max - c.spin_min) * r
        return c.pwm_min + (c.pwm_max - c.pwm_min) * a

    def table(self) -> list[tuple[int, str, str, str]]:
        """(motor, position, spin, RotorPy rotor) rows, for logs and docs."""
        return self.map.table()
