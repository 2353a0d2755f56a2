"""The sensor registry: every sensor model registers its class under a kind name.

Adding a sensor is one module in :mod:`droneulator.sensors` that decorates its model with
:func:`register` (plus the publisher that sends its readings); code that builds sensors looks
them up with :func:`get_sensor` instead of importing each model.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T", bound=type)

#: kind name -> sensor model class, in registration order
SENSORS: dict[str, type] = {}


def register(kind: str) -> Callable[[T], T]:
    """Class decorator: make the model available as ``get_sensor(kind)``; sets ``cls.kind``."""

    def add(cls: T) -> T:
        if kind in SENSORS and SENSORS[kind] is not cls:
            raise ValueError(f"sensor kind {kind!r} is already registered by {SENSORS[kind].__qualname__}")
        cls.kind = kind  # type: ignore[attr-defined]
        SENSORS[kind] = cls
        return cls

    return add


def get_sensor(kind: str) -> type:
    """The model class registered as ``kind``; an unknown kind names the registered ones."""
    try:
        return SENSORS[kind]
    except KeyError:
        raise ValueError(f"unknown sensor kind {kind!r}; registered: {', '.join(sorted(SENSORS))}") from None
