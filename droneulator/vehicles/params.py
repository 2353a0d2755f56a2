"""Named RotorPy parameter sets the simulator can fly."""

from __future__ import annotations

from typing import Any

from rotorpy.vehicles.crazyflie_params import quad_params as crazyflie
from rotorpy.vehicles.crazyfliebrushless_params import quad_params as crazyflie_brushless
from rotorpy.vehicles.hummingbird_params import quad_params as hummingbird
from rotorpy.vehicles.px4_sihsim_quadx_params import quad_params as px4_quadx

from droneulator.vehicles.sprayers import SPRAYERS

PARAMETER_SETS: dict[str, dict[str, Any]] = {
    "hummingbird": hummingbird,
    "crazyflie": crazyflie,
    "crazyflie_brushless": crazyflie_brushless,
    "px4_quadx": px4_quadx,
    **SPRAYERS,
}


def get_params(name: str) -> dict[str, Any]:
    """A copy of RotorPy's parameter dict ``name`` (ValueError listing the known sets otherwise)."""
    try:
        return dict(PARAMETER_SETS[name])
    except KeyError:
        raise ValueError(
            f"unknown vehicle parameter set {name!r}; known: {', '.join(PARAMETER_SETS)}"
        ) from None
