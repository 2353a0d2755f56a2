"""Rotor downwash: the wind a vehicle feels in the wake of the vehicles above it.

The model, from momentum theory and the round turbulent jet (each step, for every pair of vehicles):

* The upper vehicle's rotors, of total disk area ``A`` (equivalent radius ``R0 = sqrt(A / pi)``), make
  a thrust ``T = k_eta * sum(omega^2)``. Momentum theory gives the induced velocity at the disk,
  ``v_h = sqrt(T / (2 rho A))`` (``rho`` = 1.225 kg/m^3), and a wake that contracts to half the area
  (radius ``R_w = R0 / sqrt(2)``) while it accelerates to ``2 v_h``.
* Along the thrust axis, a distance ``z`` below the rotors, the ideal actuator disk's slipstream speeds
  up as ``v_h (1 + z / sqrt(z^2 + R0^2))`` (from ``v_h`` at the disk towards ``2 v_h``).
* Further down the wake mixes with still air like a round turbulent jet: a Gaussian profile whose
  width grows linearly, ``b(z) = R_w + k z`` (``k`` = 0.11, the spreading rate of a round jet), and whose
  momentum flux ``rho u_c^2 pi b^2 / 2`` stays that of the contracted wake, ``rho (2 v_h)^2 pi R_w^2``,
  so its centre speed decays as ``u_c = 2 sqrt(2) v_h R_w / b(z)``.
* The speed at a point ``z`` below and ``r`` off the axis is ``u = min(near, far) * exp(-(r / b)^2)``
  with ``near`` and ``far`` the two centre speeds above. It blows along the upper vehicle's thrust axis,
  away from it (down, for a level vehicle), and adds to the lower vehicle's wind: the aerodynamic model
  sees it as airspeed (less thrust from each rotor, drag), as RotorPy's wind.

Points above the rotor plane, more than ``Z_MAX`` below it or more than ``3 b`` off the axis feel
nothing; contributions of several vehicles above add up. The pairs are found through a cell list of
``CELL`` m (:mod:`droneulator.world.contact`), so thousands of vehicles stay cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from droneulator.frames_numba import quat_to_matrix_into
from droneulator.state import STATE
from droneulator.world.contact import cell_key, cell_list

RHO = 1.225
#: spreading rate of a round turbulent jet: its half-width grows by this much per metre downstream
SPREAD = 0.11
#: the wake is followed this far below the rotors (m)
Z_MAX = 15.0
#: cell size of the pair search (m): the widest wake considered, 3 b(Z_MAX), stays within one cell
CELL = 6.0
#: where the attitude and the rotor speeds start in the packed state (the kernel indexes it directly)
_Q, _W = STATE.q.start, STATE.rotor_speeds.start


@numba.njit(cache=True)
def wake_speed(thrust: float, disk_area: float, z: float, r: float) -> float:
    """Wake speed (m/s) ``z`` m below a rotor plane of total ``disk_area`` m^2 making ``thrust`` N, ``r`` m
    off its axis (the module docstring's model)."""
    if thrust <= 0.0:
        return 0.0
    return disk_wake_speed(math.sqrt(thrust / (2.0 * RHO * disk_area)), math.sqrt(disk_area / math.pi), z, r)


@numba.njit(cache=True)
def disk_wake_speed(vh: float, r0: float, z: float, r: float) -> float:
    """:func:`wake_speed` of a disk of radius ``r0`` whose induced velocity at hover is ``vh`` (m/s)."""
    if z <= 0.0 or z > Z_MAX:
        return 0.0
    rw = r0 / math.sqrt(2.0)
    b = rw + SPREAD * z
    if r > 3.0 * b:
        return 0.0
    near = vh * (1.0 + z / math.sqrt(z * z + r0 * r0))
    far = 2.0 * math.sqrt(2.0) * vh * rw / b
    return min(near, far) * math.exp(-((r / b) ** 2))


@dataclass
class WakeModel:
    """What the wake needs of each vehicle: its thrust coefficient and its rotor disk area."""

    k_eta: np.ndarray
    disk_area: np.ndarray

    @property
    def active(self) -> bool:
        """Wakes matter once there are two vehicles."""
        return self.k_eta.shape[0] > 1

    @classmethod
    def of(cls, vehicles: list[Any]) -> WakeModel:
        return cls(
            np.array([float(v.quad_params["k_eta"]) for v in vehicles]),
            np.array([v.disk_area for v in vehicles]),
        )


@numba.njit(cache=True)
def _downwash(rows: np.ndarray, k_eta: np.ndarray, area: np.ndarray, out: np.ndarray) -> None:
    n = rows.shape[0]
    zmin, zmax = rows[:, 2].min(), rows[:, 2].max()
    if zmax - zmin < 1e-6:
        return  # everyone at one height: nobody is below anybody
    order, keys, cells = cell_list(rows[:, 0:2], CELL)
    # each occupied cell once: its key, its first row in ``order``, and the lowest vehicle in it
    starts = [0]
    for k in range(1, n):
        if keys[k] != keys[k - 1]:
            starts.append(k)
    m = len(starts)
    ukeys = np.empty(m, dtype=np.int64)
    first = np.empty(m + 1, dtype=np.int64)
    lowest = np.empty(m)
    for c in range(m):
        first[c] = starts[c]
        ukeys[c] = keys[starts[c]]
    first[m] = n
    for c in range(m):
        lo = math.inf
        for k in range(first[c], first[c + 1]):
            lo = min(lo, rows[order[k], 2])
        lowest[c] = lo
    R = np.empty((3, 3))
    for u in range(n):  # the upper vehicle: its wake onto everyone below
        w = rows[u, _W : _W + 4]
        thrust = k_eta[u] * (w[0] * w[0] + w[1] * w[1] + w[2] * w[2] + w[3] * w[3])
        if thrust <= 0.0 or rows[u, 2] <= zmin:
            continue
        quat_to_matrix_into(rows[u, _Q : _Q + 4], R)
        ax, ay, az = R[0, 2], R[1, 2], R[2, 2]  # thrust axis (body z) in the world
        for dx_ in range(-1, 2):
            for dy_ in range(-1, 2):
                key = cell_key(cells[u, 0] + dx_, cells[u, 1] + dy_)
                c = np.searchsorted(ukeys, key)
                if c >= m or ukeys[c] != key or lowest[c] >= rows[u, 2]:
                    continue  # an empty cell, or nobody in it lower than the upper vehicle
                for k in range(first[c], first[c + 1]):
                    lo = order[k]
                    if lo == u:
                        continue
                    dx = rows[lo, 0] - rows[u, 0]
                    dy = rows[lo, 1] - rows[u, 1]
                    dz = rows[lo, 2] - rows[u, 2]
                    z = -(dx * ax + dy * ay + dz * az)  # distance below the rotor plane, along the axis
                    if z <= 0.0:
                        continue
                    px, py, pz = dx + z * ax, dy + z * ay, dz + z * az
                    speed = wake_speed(thrust, area[u], z, math.sqrt(px * px + py * py + pz * pz))
                    out[lo, 0] -= speed * ax
                    out[lo, 1] -= speed * ay
                    out[lo, 2] -= speed * az


def wakes(rows: np.ndarray, model: WakeModel) -> np.ndarray:
    """The wind every vehicle's wake adds to the vehicles below it ``(rows, 3)``, for state ``rows``."""
    wake = np.zeros((rows.shape[0], 3))
    _downwash(rows, model.k_eta, model.disk_area, wake)
    return wake
