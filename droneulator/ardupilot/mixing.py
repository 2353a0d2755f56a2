"""ArduCopter quad-X (and octa-quad X, for coaxial airframes) servo PWM -> RotorPy rotor speeds.

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

Octa-quad X
    A coaxial airframe (``coaxial: True``: ``sprayer40``, four pairs flown as four rotors) is ArduCopter's
    OctaQuad X (``FRAME_CLASS 4``, ``FRAME_TYPE 1``; ``AP_MotorsMatrix::setup_octaquad_matrix``): motors 1-4
    are a quad X's upper ring (1 front-right CCW, 2 front-left CW, 3 rear-left CCW, 4 rear-right CW) and
    5-8 the lower one, each under the upper motor of its corner and spinning the other way (5 front-left
    CCW, 6 front-right CW, 7 rear-right CCW, 8 rear-left CW). The model has one rotor per pair, so
    :class:`ArduCopterOctaQuadMotors` gives each pair-rotor the speed whose thrust is its two motors'
    sum, then moves thrust between the CW and the CCW diagonal (which changes neither the total thrust
    nor roll and pitch) until the four rotors' reaction torque is the eight motors'. The octa-quad yaws
    only by splitting each pair's thrust between its upper and lower rotor: with the pair's thrust alone
    ArduCopter could not yaw the model at all.
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

#: (motor number, angle, yaw factor, testing order), AP_MotorsMatrix.cpp octa-quad X (FRAME_CLASS 4, TYPE 1)
ARDUCOPTER_OCTAQUAD_X_DEFS: tuple[tuple[int, float, int, int], ...] = (
    (1, 45.0, +1, 1),
    (2, -45.0, -1, 7),
    (3, -135.0, +1, 5),
    (4, 135.0, -1, 3),
    (5, -45.0, +1, 8),
    (6, 45.0, -1, 2),
    (7, 135.0, +1, 4),
    (8, -135.0, -1, 6),
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
#: ArduCopter's octa-quad X motors 1..8 (1-4 the upper ring, 5-8 the lower), from its table
ARDUCOPTER_OCTAQUAD_X: tuple[PX4Motor, ...] = tuple(_motor(*d[:3]) for d in ARDUCOPTER_OCTAQUAD_X_DEFS)


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


class ArduCopterOctaQuadMotors(ArduCopterMotors):
    """ArduCopter octa-quad X servo PWM (channels 1..8) -> the speeds of a coaxial airframe's four
    pair-rotors (RotorPy order), each pair one rotor (see the module's text).

    Each motor's thrust fraction ``t`` (of a single rotor's full thrust, half the pair-rotor's) comes from
    its PWM as for the quad X. Pair ``p`` gets the fraction ``f_p = (t_upper + t_lower) / 2`` of its
    rotor's full thrust, and its reaction torque would be ``kappa T_max (t_cw - t_ccw) / 2`` about +z up
    (``kappa = k_m / k_eta``, the same for a single rotor and the pair-rotor). The pair-rotors' torque is
    ``kappa T_max sum(d_i f_i)`` (``d_i`` = +1 CW, -1 CCW), so ``c = (sum_p (t_cw - t_ccw) / 2 -
    sum_i d_i f_i) / 4`` is added to the CW pair-rotors and taken from the CCW ones: total thrust, roll and
    pitch (each spin is a diagonal) stay the pairs', the yaw moment becomes the eight motors'."""

    def __init__(self, quad_params: dict[str, Any], cfg: ArduPilotConfig | None = None) -> None:
        self.cfg = cfg = cfg or ArduPilotConfig()
        #: the upper ring (motors 1..4) is a quad X: it fixes each corner's pair-rotor and its spin
        self.map = MotorMap(quad_params, cfg.thrust_expo, ARDUCOPTER_OCTAQUAD_X[:4], "ArduPilot")
        corner = {(m.forward, m.right): k for k, m in enumerate(ARDUCOPTER_OCTAQUAD_X[:4])}
        #: for motors 1..8: the RotorPy index of its pair-rotor and its spin (+1 CW, -1 CCW, RotorPy's sign)
        self.pair = np.array([self.map.order[corner[m.forward, m.right]] for m in ARDUCOPTER_OCTAQUAD_X])
        self.spin = np.array([1.0 if m.spin == "CW" else -1.0 for m in ARDUCOPTER_OCTAQUAD_X])
        dirs = np.asarray(quad_params["rotor_directions"], dtype=float)
        self.rotor_spin = np.sign(dirs)

    def armed(self, pwm: Any) -> bool:
        """Whether motor PWMs 1..8 say ArduCopter is armed (see :data:`ARMED_MARGIN`)."""
        return bool(np.any(self.actuator(np.asarray(pwm)[:8]) > ARMED_MARGIN))

    def pair_fractions(self, pwm: Any) -> tuple[np.ndarray, float]:
        """(each pair-rotor's thrust fraction ``f``, RotorPy order; the eight motors' yaw torque in units
        of ``kappa`` times a pair-rotor's full thrust) for a servo packet's PWMs."""
        r = self.throttle_ratio(np.asarray(pwm, dtype=float)[:8])
        k = self.map.k
        t = (1.0 - k) * r + k * r * r
        f = np.zeros(4)
        np.add.at(f, self.pair, 0.5 * t)
        return f, float(np.sum(0.5 * self.spin * t))

    def rotor_speeds(self, pwm: Any) -> np.ndarray:
        """Pair-rotor speeds (rad/s, RotorPy order) for a servo packet's PWMs (motors 1..8 come first)."""
        f, yaw = self.pair_fractions(pwm)
        c = (yaw - float(self.rotor_spin @ f)) / 4.0
        f = np.clip(f + c * self.rotor_spin, 0.0, 1.0)
        return self.map.w_min + (self.map.w_max - self.map.w_min) * np.sqrt(f)

    def pwm_for_speed(self, w: Any) -> np.ndarray:
        """The eight PWMs (motors 1..8) that give pair-rotor speeds ``w`` (RotorPy order) with each pair's
        two motors equal, for tests and tools."""
        return super().pwm_for_speed(np.asarray(w, dtype=float)[self.pair])

    def table(self) -> list[tuple[int, str, str, str]]:
        """(motor, position, spin, RotorPy pair-rotor) rows, for logs and docs."""
        return [
            (m.number, f"{m.name} {'upper' if m.number <= 4 else 'lower'}", m.spin, self.map.rotor_names[i])
            for m, i in zip(ARDUCOPTER_OCTAQUAD_X, self.pair, strict=True)
        ]


def arducopter_motors(quad_params: dict[str, Any], cfg: ArduPilotConfig | None = None) -> ArduCopterMotors:
    """The ArduCopter frame that flies airframe ``quad_params``: octa-quad X (FRAME_CLASS 4) for a coaxial
    airframe (``coaxial: True``, four pairs), quad X (FRAME_CLASS 1) for the others."""
    if quad_params.get("coaxial", False):
        return ArduCopterOctaQuadMotors(quad_params, cfg)
    return ArduCopterMotors(quad_params, cfg)
