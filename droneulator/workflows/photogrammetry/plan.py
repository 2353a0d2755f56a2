"""Stage 1 of a capture: the viewpoints around the tree and the paths between them (pure geometry).

Views sit on rings of radius ``capture.radius`` around the tree's vertical axis, one ring per
altitude, each facing the axis. Arcs between views are split into legs of at most
``capture.max_leg_deg`` so that a straight min-snap leg stays close to the circle, and
:func:`segment_errors` measures how far the flown path strays from a commanded leg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.frames import wrap_angle


@dataclass(frozen=True)
class Viewpoint:
    """One capture pose: ``index`` names the image (``NNNN.jpg``); ``yaw`` faces the tree."""

    index: int
    ring: int
    azimuth: float
    position: tuple[float, float, float]
    yaw: float

    @property
    def name(self) -> str:
        return image_name(self.index)


def image_name(index: int) -> str:
    return f"{index:04d}.jpg"


def ring_sizes(views: int, rings: int) -> list[int]:
    """Views per ring, shared out as evenly as possible (the first rings take the remainder)."""
    base, extra = divmod(views, rings)
    return [base + (r < extra) for r in range(rings)]


def ring_point(center: Sequence[float], radius: float, azimuth: float, altitude: float) -> np.ndarray:
    return np.array(
        [center[0] + radius * math.cos(azimuth), center[1] + radius * math.sin(azimuth), altitude]
    )


def facing_yaw(center: Sequence[float], p: Sequence[float]) -> float:
    """Heading from ``p`` towards the vertical axis through ``center``."""
    return math.atan2(center[1] - p[1], center[0] - p[0])


def plan_viewpoints(
    center: Sequence[float],
    radius: float,
    altitudes: Sequence[float],
    views: int,
    arc_deg: float = 360.0,
    start_azimuth: float = 0.0,
) -> list[Viewpoint]:
    """Rings of evenly spaced viewpoints around ``center`` (x, y), counter-clockwise, ring after ring.

    A full circle (``arc_deg`` 360) spaces a ring's views by 360/n and staggers successive rings by half
    a spacing so that their views interleave; a partial arc puts views at both of its ends.
    """
    plan: list[Viewpoint] = []
    full = arc_deg >= 360.0
    for ring, (alt, n) in enumerate(zip(altitudes, ring_sizes(views, len(altitudes)), strict=True)):
        step = math.radians(arc_deg) / (n if full else max(n - 1, 1))
        offset = 0.5 * (ring % 2) if full else 0.0
        for j in range(n):
            az = wrap_angle(start_azimuth + (j + offset) * step)
            p = ring_point(center, radius, az, alt)
            plan.append(Viewpoint(len(plan), ring, az, tuple(float(v) for v in p), facing_yaw(center, p)))
    return plan


def aim_pitch_deg(
    radius: float, altitudes: Sequence[float], look_at_z: float, mount: Sequence[float]
) -> float:
    """Mount pitch (degrees, positive down) that points the optical axis at height ``look_at_z`` on the
    tree's axis from the mean ring altitude, for a camera mounted at ``mount`` (body FLU) facing the tree."""
    drop = float(np.mean(altitudes)) + mount[2] - look_at_z
    return math.degrees(math.atan2(drop, radius - mount[0]))


def arc_waypoints(
    center: Sequence[float], radius: float, altitude: float, az_from: float, az_to: float, max_step_deg: float
) -> list[np.ndarray]:
    """Points along the shorter arc from ``az_from`` to ``az_to`` (end included), ``max_step_deg`` apart
    at most."""
    delta = wrap_angle(az_to - az_from)
    if abs(delta) < 1e-9:
        return []
    n = max(1, math.ceil(abs(math.degrees(delta)) / max_step_deg - 1e-9))
    return [ring_point(center, radius, az_from + delta * (k + 1) / n, altitude) for k in range(n)]


def segment_errors(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point (n, 3) from the segment a-b, and its height error against the segment's
    height at the closest point: the tracking errors against a straight commanded path."""
    points = np.atleast_2d(points)
    ab = b - a
    denom = float(ab @ ab)
    s = np.zeros(len(points)) if denom < 1e-12 else np.clip((points - a) @ ab / denom, 0.0, 1.0)
    closest = a + s[:, None] * ab
    return np.linalg.norm(points - closest, axis=1), np.abs(points[:, 2] - closest[:, 2])


def axis_clearance(center: Sequence[float], a: Sequence[float], b: Sequence[float]) -> float:
    """Least horizontal distance from the vertical axis through ``center`` (x, y) to the segment a-b."""
    c = np.asarray(center[:2], dtype=float)
    p, q = np.asarray(a[:2], dtype=float) - c, np.asarray(b[:2], dtype=float) - c
    d = q - p
    denom = float(d @ d)
    s = 0.0 if denom < 1e-12 else float(np.clip(-(p @ d) / denom, 0.0, 1.0))
    return float(np.linalg.norm(p + s * d))


def pending_views(plan: Sequence[Viewpoint], done: set[int] | dict[int, Any]) -> list[Viewpoint]:
    """The viewpoints still to capture, in flight order."""
    return [v for v in plan if v.index not in done]


def ring_neighbours(plan: Sequence[Viewpoint], a: Viewpoint, b: Viewpoint) -> bool:
    """Whether ``a`` and ``b`` are next to each other on their ring: no other view of the ring lies on
    the shorter arc between them (the arc a capture leg flies)."""
    if a.ring != b.ring or a.index == b.index:
        return False
    span = wrap_angle(b.azimuth - a.azimuth)
    for v in plan:
        if v.ring == a.ring and v.index not in (a.index, b.index):
            f = wrap_angle(v.azimuth - a.azimuth) / span
            if 0.0 < f < 1.0:
                return False
    return True


def mirrored_halves(vehicles: int, arc_deg: float) -> bool:
    """Whether ``vehicles`` vehicles fly mirrored halves of every ring (:func:`fleet_routes`): two, on full
    circles."""
    return vehicles == 2 and arc_deg >= 360.0


def _nearest(views: Sequence[Viewpoint], azimuth: float) -> int:
    """Index in ``views`` of the view nearest ``azimuth`` (ties: the earlier one)."""
    return min(range(len(views)), key=lambda j: (round(abs(wrap_angle(views[j].azimuth - azimuth)), 9), j))


def _turned(views: Sequence[Viewpoint], azimuth: float, ccw: bool) -> list[Viewpoint]:
    """A ring's ``views`` (counter-clockwise) in the order met turning from ``azimuth`` counter-clockwise
    (``ccw``) or clockwise, the first at or past it."""

    def ahead(j: int) -> float:  # the turn to view j, in [0, 2 pi); a view a hair behind counts as at it
        d = wrap_angle(views[j].azimuth - azimuth)
        turn = (d if ccw else -d) % (2.0 * math.pi)
        return 0.0 if turn > 2.0 * math.pi - 1e-9 else round(turn, 9)

    j = min(range(len(views)), key=lambda j: (ahead(j), j))
    return list(views[j:]) + list(views[:j]) if ccw else [views[j], *views[:j][::-1], *views[j + 1 :][::-1]]


def fleet_routes(
    plan: Sequence[Viewpoint], center: Sequence[float], positions: Sequence[Sequence[float]], arc_deg: float
) -> list[list[Viewpoint]]:
    """The views each of one or several vehicles (at ``positions``, x, y, ...) flies, in flight order.

    Full circles (``arc_deg`` 360):

    * One vehicle flies ring after ring: the first counter-clockwise from the first view past where it
      stands, each later one from its view nearest where the one before ended, the other way round. It
      never flies round the tree to a start, and each ring change is a short climb.
    * Two vehicles (:func:`mirrored_halves`) split every ring at their mean azimuth: the one standing
      clockwise of the other takes the clockwise half, the other the counter-clockwise half (the first
      the larger one when a ring's views are odd). Each flies its half of the first ring outwards from the
      split, of the next ring back, and so on, so they part at once, fly opposite halves of the orbit at
      one altitude (neither in the other's downwash), never enter each other's half and come no closer
      than neighbouring views, at the split and across the tree.
    * More vehicles: every ring is split into ``n`` contiguous arcs of (nearly) equal size, and vehicle k
      (in counter-clockwise order of the vehicles around the tree) takes arc k of every ring, the arcs
      turned so that they start half an arc to either side of the vehicles' mean azimuth. Every vehicle
      flies its arcs the same way round (counter-clockwise on even rings, back on odd ones), so vehicles
      that keep pace stay an arc apart and never meet.

    A partial arc: its views shared out in order, in arcs as above (one vehicle: the plan's order).
    """
    n = len(positions)
    if n < 1:
        raise ValueError("need at least one vehicle")
    full = arc_deg >= 360.0
    azimuths = [math.atan2(p[1] - center[1], p[0] - center[0]) for p in positions]
    mean = math.atan2(sum(math.sin(a) for a in azimuths), sum(math.cos(a) for a in azimuths))
    order = sorted(range(n), key=lambda k: (wrap_angle(azimuths[k] - mean), k))
    rings = [
        sorted((v for v in plan if v.ring == r), key=lambda v: v.index)
        for r in sorted({v.ring for v in plan})
    ]
    if full and n == 1:
        route: list[Viewpoint] = []
        at, ccw = azimuths[0], True
        for views in rings:
            views = _turned(views, views[_nearest(views, at)].azimuth if route else at, ccw)
            route += views
            at, ccw = views[-1].azimuth, not ccw
        return [route]
    if n == 1:
        return [list(plan)]
    routes: list[list[Viewpoint]] = [[] for _ in range(n)]
    if mirrored_halves(n, arc_deg):
        for r, views in enumerate(rings):
            cw = _turned(views, mean, ccw=False)
            size = ring_sizes(len(views), 2)[0]
            halves = (cw[:size], cw[size:][::-1])
            for k, half in zip(order, halves, strict=True):
                routes[k] += half if r % 2 == 0 else half[::-1]
        return routes
    for r, views in enumerate(rings):
        if full:
            first = mean - math.pi + math.pi / n
            turn = min(range(len(views)), key=lambda j: abs(wrap_angle(views[j].azimuth - first)))
            views = views[turn:] + views[:turn]
        start = 0
        for k, size in enumerate(ring_sizes(len(views), n)):
            arc = views[start : start + size]
            routes[order[k]] += arc if r % 2 == 0 else arc[::-1]
            start += size
    return routes
