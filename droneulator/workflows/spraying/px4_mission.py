"""A coverage plan as a PX4 mission: its legs as MAVLink MISSION_ITEM_INTs and their upload over the
mission protocol, for a sprayer that PX4 flies (``--px4``) rather than the internal controller.

The items: a NAV_TAKEOFF to the plan's altitude over the first leg's start, a NAV_WAYPOINT at the start
and one at each leg's end (global frame, WGS84 and altitude above mean sea level, from the world's ENU
coordinates through the site's origin with :func:`droneulator.frames.enu_to_geodetic`, PX4's own
projection), a DO_CHANGE_SPEED wherever the legs' speed changes, and around each spraying leg a
MAV_CMD_DO_SET_ACTUATOR that switches the spray on (+1) before it and off (-1) after it, then
NAV_RETURN_TO_LAUNCH.

Why DO_SET_ACTUATOR and not DO_SET_SERVO: since v1.13 PX4 maps DO_SET_ACTUATOR's actuator 1-6 to the
outputs assigned the functions "Peripheral via Actuator Set 1-6" (``PWM_MAIN_FUNCn`` and the like), in
missions and as commands; its DO_SET_SERVO mission item is reported ignored (PX4-Autopilot issue 20554,
open). The spray follows that output: with PX4's fifth simulator output set to "Peripheral via Actuator
Set 1" (``PWM_MAIN_FUNC5 = 301``), the PX4 link reads it from the HIL_ACTUATOR_CONTROLS PX4 already sends
and switches the vehicle's spray system on above +0.5 and off below -0.5
(:func:`droneulator.px4.link.spray_switch`).

The upload is the MAVLink mission protocol's, as PX4's ``MavlinkMissionManager`` runs it: the ground
station sends MISSION_COUNT, the vehicle asks for each item in turn with MISSION_REQUEST_INT (older
peers: MISSION_REQUEST) and the station answers with that MISSION_ITEM_INT; after the last item the
vehicle sends MISSION_ACK (MAV_MISSION_ACCEPTED, or the error that stopped it). A request the station
misses is repeated by the vehicle; a count with no answer is sent again here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from droneulator.config.site import SiteConfig
from droneulator.frames import enu_to_geodetic
from droneulator.workflows.spraying.coverage import CoveragePlan

#: the DO_SET_ACTUATOR actuator (1-6) the spray follows: PX4's "Peripheral via Actuator Set 1"
SPRAY_ACTUATOR = 1
#: a waypoint's acceptance radius (m): PX4's default for a multicopter (NAV_ACC_RAD) is 10 m, which would
#: turn onto the next row 10 m before a row's end; a multicopter takes an item's own radius instead
ACCEPTANCE_RADIUS_M = 1.0
#: how long to wait for the vehicle's next request or ack (s), and how often to send the count again
TIMEOUT_S, RETRIES = 1.5, 3


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT's content: its command, frame, params 1-4, and x, y (degrees for a global
    frame, else raw) and z (m above mean sea level for a global frame, else param 7)."""

    command: int
    frame: int
    params: tuple[float, float, float, float]
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0

    def encode(self, mav: mavlink.MAVLink, seq: int, target_system: int, target_component: int) -> Any:
        """The MISSION_ITEM_INT message for position ``seq`` of the mission."""
        glob = self.frame == mavlink.MAV_FRAME_GLOBAL
        x, y = (round(self.x * 1e7), round(self.y * 1e7)) if glob else (round(self.x), round(self.y))
        return mav.mission_item_int_encode(
            target_system, target_component, seq, self.frame, self.command, 0, 1, *self.params, x, y,
            float(self.z), mavlink.MAV_MISSION_TYPE_MISSION,
        )  # fmt: skip


def _spray(on: bool) -> MissionItem:
    values = [math.nan] * 4
    values[SPRAY_ACTUATOR - 1] = 1.0 if on else -1.0
    # actuators 5 and 6 are MISSION_ITEM_INT's integer x and y: 0 there (PX4 cannot be sent NaN in them)
    return MissionItem(mavlink.MAV_CMD_DO_SET_ACTUATOR, mavlink.MAV_FRAME_MISSION, tuple(values), 0, 0, 0.0)


def mission_items(plan: CoveragePlan, site: SiteConfig) -> list[MissionItem]:
    """The mission of ``plan`` (see the module docstring), its positions on ``site``'s origin."""
    if not plan.legs:
        raise ValueError("mission: the coverage plan has no legs")

    def at(p: Any, command: int = mavlink.MAV_CMD_NAV_WAYPOINT) -> MissionItem:
        lat, lon, alt = enu_to_geodetic(p, site.latitude_deg, site.longitude_deg, site.altitude_m)
        params = (0.0, ACCEPTANCE_RADIUS_M, 0.0, math.nan)  # no hold, a row's end, no pass-by, keep the yaw
        return MissionItem(command, mavlink.MAV_FRAME_GLOBAL, params, lat, lon, alt)

    items = [at(plan.legs[0].start, mavlink.MAV_CMD_NAV_TAKEOFF), at(plan.legs[0].start)]
    speed = None
    for leg in plan.legs:
        if leg.speed != speed:
            speed = leg.speed
            items.append(MissionItem(mavlink.MAV_CMD_DO_CHANGE_SPEED, mavlink.MAV_FRAME_MISSION,
                                     (1.0, float(speed), -1.0, 0.0)))  # fmt: skip
        if leg.spray:
            items.append(_spray(True))
        items.append(at(leg.end))
        if leg.spray:
            items.append(_spray(False))
    items.append(MissionItem(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_FRAME_MISSION, (0.0,) * 4))
    return items


class MissionUploadError(RuntimeError):
    """The vehicle refused the mission or stopped answering."""


def upload_mission(
    conn: Any,
    items: list[MissionItem],
    target_system: int = 1,
    target_component: int = 1,
    timeout_s: float = TIMEOUT_S,
) -> None:
    """Upload ``items`` over ``conn`` (a pymavlink connection) by the mission protocol (module docstring);
    returns on MAV_MISSION_ACCEPTED, raises :class:`MissionUploadError` otherwise."""
    mav = conn.mav
    count = mav.mission_count_encode(
        target_system, target_component, len(items), mavlink.MAV_MISSION_TYPE_MISSION
    )
    kinds = ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"]
    for _ in range(RETRIES):
        conn.mav.send(count)
        deadline = time.monotonic() + timeout_s
        sent_any = False
        while time.monotonic() < deadline:
            msg = conn.recv_match(type=kinds, blocking=True, timeout=max(deadline - time.monotonic(), 0.01))
            if msg is None:
                break
            if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
                continue
            if msg.get_type() == "MISSION_ACK":
                if msg.type == mavlink.MAV_MISSION_ACCEPTED and sent_any:
                    return
                name = mavlink.enums["MAV_MISSION_RESULT"][msg.type].name
                raise MissionUploadError(f"mission upload refused: {name}")
            if not 0 <= msg.seq < len(items):
                raise MissionUploadError(
                    f"mission upload: the vehicle asked for item {msg.seq} of {len(items)}"
                )
            conn.mav.send(items[msg.seq].encode(mav, msg.seq, target_system, target_component))
            sent_any = True
            deadline = time.monotonic() + timeout_s
        if sent_any:
            raise MissionUploadError("mission upload: the vehicle stopped asking for items")
    raise MissionUploadError(f"mission upload: no answer to MISSION_COUNT after {RETRIES} tries")
