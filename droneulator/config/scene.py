"""The scene's build parameters beside its name and seed: its vegetation density."""

from __future__ import annotations

from typing import Any

#: the vegetation densities a scene can be built with (``SimConfig.vegetation``; 1: as designed): its
#: leaves x this (cards per cluster, per metre of hedge), a sparse or a dense canopy; not its collision
VEGETATION_RANGE = (0.1, 3.0)


def check_vegetation(value: Any, name: str = "vegetation") -> float:
    """``value`` as a density in :data:`VEGETATION_RANGE`, else a ValueError naming ``name``."""
    lo, hi = VEGETATION_RANGE
    ok = isinstance(value, int | float) and not isinstance(value, bool) and lo <= value <= hi
    if not ok:
        raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}] (1: as designed), got {value!r}")
    return float(value)
