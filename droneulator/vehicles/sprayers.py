"""Spray-drone airframes as RotorPy parameter sets: a 10 L four-rotor class and a 40 L heavy-lift class
of about 90 kg take-off mass (docs/spray.md gives every number's source).

``sprayer10``: modelled on the DJI Agras T10 class (four foldable arms, 33 in propellers, 24.8 kg
maximum take-off mass with its 8 L tank), its tank taken to 10 L: 16 kg dry with the battery, 26 kg full.

``sprayer40``: modelled on the DJI Agras T40 (DJI's spec page: eight rotors as four coaxial pairs of
54 in propellers, 2184 mm diagonal wheelbase, 50 kg with its battery, 90 kg maximum take-off mass for
spraying, a 40 L tank, two rotary atomisers). The four-rotor model flies each coaxial pair as one rotor
of the pair's thrust (momentum theory: a coaxial pair is one disk of its area; the pair's lower
propeller's loss in the upper one's slipstream is in the thrust coefficient) and the pair's net yaw
moment; ``coaxial: True`` records it, and the spray wake uses one disk per pair.

Both are sized from their mass the same way: hover at full load at 60 % of the maximum rotor speed
(thrust-to-weight 2.8 at full speed), inertia from the motors at the arms' ends and the body and tank
as a box at the centre, the rotor aerodynamic coefficients of the hummingbird set scaled by the ratio of
hover thrusts per rotor (RotorPy's model keeps their meaning), a motor time constant of 50 ms for
motors of this size. The dry values are here; the tank's liquid is a payload added by the spray system
(:meth:`droneulator.world.world.World.set_payload`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from droneulator.vehicles.dynamics import GRAVITY

#: the hummingbird set's rotor coefficients per newton of its hover thrust per rotor (0.5 kg / 4)
_HB_HOVER_N = 0.5 * GRAVITY / 4.0
_HB = {"k_d": 1.19e-04, "k_z": 2.32e-04, "k_h": 3.39e-3}


def _sprayer(
    dry_kg: float,
    full_kg: float,
    arm_m: float,
    prop_in: float,
    motor_kg: float,
    body_m: tuple[float, float, float],
    frontal_m2: float,
    tank_l: float,
    coaxial: bool,
) -> dict[str, Any]:
    hover_n = full_kg * GRAVITY / 4.0
    w_max = 2.0 * math.pi * (3000.0 if prop_in < 40 else 2200.0) / 60.0
    k_eta = hover_n / (0.6 * w_max) ** 2
    radius = prop_in * 0.0254 / 2.0
    c = arm_m / math.sqrt(2.0)
    body_kg = dry_kg - 4.0 * motor_kg
    bx, by, bz = body_m
    ixx = 4.0 * motor_kg * c * c + body_kg * (by * by + bz * bz) / 12.0
    iyy = 4.0 * motor_kg * c * c + body_kg * (bx * bx + bz * bz) / 12.0
    izz = 4.0 * motor_kg * arm_m * arm_m + body_kg * (bx * bx + by * by) / 12.0
    scale = hover_n / _HB_HOVER_N
    w_hover = 0.6 * w_max
    drag = 0.5 * 1.225 * 1.0 * frontal_m2
    return {
        "mass": dry_kg,
        "Ixx": ixx,
        "Iyy": iyy,
        "Izz": izz,
        "Ixy": 0.0,
        "Iyz": 0.0,
        "Ixz": 0.0,
        "num_rotors": 4,
        "rotor_radius": radius,
        "rotor_pos": {
            "r1": c * np.array([1.0, 1.0, 0.0]),
            "r2": c * np.array([1.0, -1.0, 0.0]),
            "r3": c * np.array([-1.0, -1.0, 0.0]),
            "r4": c * np.array([-1.0, 1.0, 0.0]),
        },
        "rotor_directions": np.array([1, -1, 1, -1]),
        "rI": np.array([0.0, 0.0, 0.0]),
        "c_Dx": drag,
        "c_Dy": drag,
        "c_Dz": 2.0 * drag,
        "k_eta": k_eta,
        # yaw moment per unit thrust: 4 cm of lever for a propeller of this size (C_Q / C_T ~ 0.05 D)
        "k_m": k_eta * 0.05 * 2.0 * radius,
        # the hummingbird's coefficients are forces per rad/s of rotor speed: scale them so that each
        # gives the same force per newton of hover thrust at hover speed
        "k_d": _HB["k_d"] * scale * 470.0 / w_hover,
        "k_z": _HB["k_z"] * scale * 470.0 / w_hover,
        "k_h": _HB["k_h"] * scale,
        "k_flap": 0.0,
        "tau_m": 0.05,
        "rotor_speed_min": 0.0,
        "rotor_speed_max": w_max,
        "motor_noise_std": 0.0,
        "k_w": 1,
        "k_v": 10,
        "kp_att": 544,
        "kd_att": 46.64,
        "tank_l": tank_l,
        "full_mass": full_kg,
        "coaxial": coaxial,
    }


#: the spray airframes, by name (dry: the tank's liquid is a payload)
SPRAYERS: dict[str, dict[str, Any]] = {
    "sprayer10": _sprayer(16.0, 26.0, 0.74, 33.0, 1.2, (0.6, 0.6, 0.45), 0.35, 10.0, False),
    "sprayer40": _sprayer(50.0, 90.0, 1.09, 54.0, 3.5, (0.9, 0.9, 0.7), 0.8, 40.0, True),
}


def spray_system(name: str) -> dict[str, Any]:
    """The spray section of airframe ``name`` (``spray`` keys: tank and nozzles), as sold:

    * ``sprayer10``: four hydraulic flat fans, one under each rotor (the T10 class carries four TeeJet
      XR11001VS, 110 degrees, a Fine spray), 0.45 L/min each (1.8 L/min in all);
    * ``sprayer40``: two rotary atomisers under the rear rotors (the T40's two LX8060SZ centrifugal
      sprinklers; droplets 50-300 um by DJI's spec, here Dv0.1/0.5/0.9 = 90/150/240 um), 6 L/min each.
    """
    q = SPRAYERS[name]
    c = float(q["rotor_pos"]["r1"][0])
    if name == "sprayer10":
        nozzles = [
            {"name": f"n{i}", "position": [sx * c, sy * c, -0.35], "type": "flat_fan", "flow_l_min": 0.45,
             "spectrum": "F", "exit_speed_m_s": 15.0, "fan_angle_deg": 110.0}
            for i, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, -1), (-1, 1)))
        ]  # fmt: skip
    else:
        nozzles = [
            {"name": side, "position": [-c, sy * c, -0.4], "type": "rotary", "flow_l_min": 6.0,
             "dv10_um": 90.0, "dv50_um": 150.0, "dv90_um": 240.0, "exit_speed_m_s": 20.0}
            for side, sy in (("left", 1), ("right", -1))
        ]  # fmt: skip
    return {"tank_l": q["tank_l"], "load_l": q["tank_l"], "nozzles": nozzles}
