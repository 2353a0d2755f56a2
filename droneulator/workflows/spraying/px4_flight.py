"""Fly a coverage plan spraying with PX4 SITL: the plan uploaded as a mission, PX4 flying it in lockstep.

The world steps only on PX4's lockstep actuator messages (:class:`~droneulator.px4.link.PX4Link`, which
also switches the spray with PX4's spray output). Beside it, a ground-station link on PX4's onboard
MAVLink (:class:`~droneulator.workflows.planning.offboard.OffboardLink`, identity "gcs", never taking
offboard control) runs the mission in a thread:

1. wait for PX4's HEARTBEAT, set ``PWM_MAIN_FUNC5 = 301`` (the fifth simulator output follows
   DO_SET_ACTUATOR's actuator 1, the spray) with PARAM_SET and check PX4's PARAM_VALUE;
2. upload the plan's mission (:mod:`.px4_mission`; a refusal ends the flight with its MAV_MISSION_RESULT);
3. MAV_CMD_MISSION_START (PX4's commander switches to AUTO.MISSION and arms in one), repeated while PX4
   answers TEMPORARILY_REJECTED (its preflight checks pass only once EKF2 has a position and a home);
4. wait until PX4 has flown the mission and its closing RTL and disarmed on the ground
   (COM_DISARM_LAND), noting each new MISSION_ITEM_REACHED at sim time (PX4 reports the last item
   done, a waypoint's DO items included, and repeats it once a second).

Then the cloud settles and the report is the internal controller's (:func:`.mission.report`), with a
``px4`` section: the spray's switches at sim time with where the vehicle was, and the items reached.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator.config import SimConfig
from droneulator.spray.spraying import Spraying
from droneulator.workflows.spraying.coverage import CoveragePlan
from droneulator.workflows.spraying.mission import report
from droneulator.workflows.spraying.px4_mission import mission_items, upload_mission

log = logging.getLogger(__name__)

#: the PX4 parameter that makes the fifth simulator output the spray's: "Peripheral via Actuator Set 1"
SPRAY_PARAM, SPRAY_FUNCTION = "PWM_MAIN_FUNC5", 301
#: sim time PX4 may take beyond the plan's flying time (take-off, turns, RTL, landing) before giving up
SIM_SLACK_S = 180.0
#: wall seconds OffboardLink waits for PX4's HEARTBEAT before it logs its own error (this module reports it)
LONG_WAIT_S = 3600.0
#: sim time by which PX4 must have started the mission (its boot, EKF2's first fix, the home)
START_LIMIT_S = 120.0
#: how often MAV_CMD_MISSION_START is repeated while PX4 is not ready to arm (wall s)
START_RETRY_S = 1.0


class PX4FlightError(RuntimeError):
    """PX4 did not come, refused the mission or the start, or did not finish the mission."""


@dataclass
class PX4Options:
    """Where PX4 is and how long to wait for it."""

    #: PX4 SITL instance N: simulator TCP port px4.base_port + N, onboard MAVLink UDP 14540 + N
    instance: int = 0
    #: the UDP port PX4's onboard MAVLink sends to; None: 14540 + N (``px4-rc.mavlink``)
    mavlink_port: int | None = None
    #: wall seconds to wait for PX4 to connect (simulator link) and to send its HEARTBEAT
    timeout_s: float = 120.0


@dataclass
class _Mission:
    """The mission thread's progress, read by the stepping loop."""

    done: threading.Event = field(default_factory=threading.Event)
    #: set by the stepping loop when it ends: the mission thread gives up
    stop: threading.Event = field(default_factory=threading.Event)
    #: set once PX4 steps the world (past its first sim second): PX4 boots in sim time, so its HEARTBEAT
    #: is waited for from then on, however long the first steps took (the spray kernels compile)
    booting: threading.Event = field(default_factory=threading.Event)
    error: str | None = None
    armed_seen: bool = False
    reached: list[tuple[float, int]] = field(default_factory=list)
    stage: str = "waiting for PX4's HEARTBEAT"


def fly_plan_px4(
    config: SimConfig,
    plan: CoveragePlan,
    opts: PX4Options | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[dict[str, Any], Spraying]:
    """Fly ``plan`` with PX4 SITL (module docstring); returns the report and the :class:`Spraying`.
    ``config`` hands its first vehicle, a sprayer, to PX4 (``px4.enabled``) at PX4's 250 Hz."""
    from droneulator.px4.link import PX4Link
    from droneulator.workflows.planning.offboard import OffboardConfig, OffboardLink
    from droneulator.world.world import World

    opts = opts or PX4Options()
    config.spray.enabled = True  # the world's own spraying, which the PX4 link switches
    world = World(config, render=False)
    spraying = world.spraying
    assert spraying is not None
    v = world.vehicle()
    system = spraying.system(v.name)
    items = mission_items(plan, config.site)
    flying_s = sum(float(np.linalg.norm(leg.end - leg.start)) / leg.speed for leg in plan.legs)
    sim_limit = flying_s + SIM_SLACK_S
    site = config.site
    gcs_cfg = OffboardConfig(
        instance=opts.instance,
        identity="gcs",
        connect_timeout_s=LONG_WAIT_S,  # its HEARTBEAT is waited for here, from when PX4 is connected
        home_lat_deg=site.latitude_deg,
        home_lon_deg=site.longitude_deg,
        home_alt_m=site.altitude_m,
    )
    if opts.mavlink_port is not None:
        gcs_cfg.base_port = opts.mavlink_port - min(opts.instance, 9)
    switches: list[dict[str, Any]] = []
    state = _Mission()
    with PX4Link(world, instance=opts.instance) as link, OffboardLink(gcs_cfg) as gcs:
        print(f"waiting for PX4 SITL instance {opts.instance}: simulator link on tcp://{link.cfg.host}:"
              f"{link.port}, MAVLink on udp {gcs.address[0]}:{gcs.address[1]} (start PX4 as docs/px4.md "
              f"says; giving up after {opts.timeout_s:.0f} s)", flush=True)  # fmt: skip
        args = (gcs, items, state, world, opts.timeout_s)
        worker = threading.Thread(target=_run_mission, args=args, daemon=True)
        worker.start()
        wall0 = time.monotonic()
        on = False
        try:
            while not state.done.is_set():
                if not link.connected and world.t == 0.0 and time.monotonic() - wall0 > opts.timeout_s:
                    raise PX4FlightError(
                        f"no PX4 connected to the simulator port tcp://{link.cfg.host}:{link.port} within "
                        f"{opts.timeout_s:.0f} s: start PX4 SITL instance {opts.instance} (docs/px4.md)"
                    )
                if world.t > sim_limit:
                    raise PX4FlightError(f"PX4 has not finished the mission after {sim_limit:.0f} s of sim "
                                         f"time ({state.stage})")  # fmt: skip
                if link.serve_once(0.05) is None:
                    continue
                if world.t >= 1.0:
                    state.booting.set()
                if (system.rate > 0.0) != on:
                    on = not on
                    p = v.state.position
                    switches.append({"t": world.t, "on": on, "position": [round(float(x), 3) for x in p],
                                     "tank_l": system.level_l})  # fmt: skip
                if progress and world.t_ns % 250_000_000 == 0:
                    progress(min(world.t / (flying_s + 60.0), 0.99), f"t={world.t:.0f}s {state.stage} "
                             f"tank={system.level_l:.2f}L")  # fmt: skip
        finally:
            state.stop.set()  # the mission thread ends too, whatever ended the flight
            worker.join(timeout=5.0)
        if state.error:
            raise PX4FlightError(state.error)
    system.set(0.0)
    spraying.cloud.settle([], limit_s=60.0)
    if progress:
        progress(1.0, "settled")
    out = report(spraying, plan)
    out["px4"] = {
        "mission_items": len(items),
        "items_reached": [{"t": t, "seq": s} for t, s in state.reached],
        "spray_switches": switches,
        "flown_s": world.t,
    }
    return out, spraying


def _run_mission(gcs: Any, items: list[Any], state: _Mission, world: Any, timeout_s: float) -> None:
    """The mission thread: steps 1-4 of the module docstring; an error ends it with ``state.error``."""
    try:
        _mission_steps(gcs, items, state, world, timeout_s)
    except Exception as exc:  # the stepping loop reports it
        state.error = str(exc)
    finally:
        state.done.set()


def _mission_steps(gcs: Any, items: list[Any], state: _Mission, world: Any, timeout_s: float) -> None:
    from droneulator.workflows.planning.offboard import MavlinkPort

    while not state.booting.wait(0.1):
        if state.stop.is_set():
            return
    end = time.monotonic() + timeout_s
    while not gcs.connected and not state.stop.is_set():
        if time.monotonic() > end:
            where = f"udp {gcs.address[0]}:{gcs.address[1]}"
            raise PX4FlightError(f"PX4 steps the simulator but sent no HEARTBEAT on {where} within "
                                 f"{timeout_s:.0f} s: is its onboard MAVLink (mavlink start -u 14580+N -o "
                                 "14540+N) on, or another --px4-port?")  # fmt: skip
        time.sleep(0.05)
    if state.stop.is_set():
        return
    port = MavlinkPort(gcs, ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK", "PARAM_VALUE",
                             "MISSION_ITEM_REACHED"])  # fmt: skip
    state.stage = f"setting {SPRAY_PARAM}"
    _set_int_param(port, gcs, SPRAY_PARAM, SPRAY_FUNCTION)
    state.stage = "uploading the mission"
    upload_mission(port, items, gcs.sysid, gcs.compid)
    log.info("PX4 accepted the mission (%d items)", len(items))
    state.stage = "starting the mission"
    while not state.stop.is_set():
        result = gcs.command(mavlink.MAV_CMD_MISSION_START, "mission start", 0.0, float(len(items) - 1))
        if result == mavlink.MAV_RESULT_ACCEPTED:
            break
        # DENIED until the navigator has checked the new mission, TEMPORARILY_REJECTED until the
        # preflight checks pass (EKF2's position, the home): both pass within seconds of sim time
        if result not in (None, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, mavlink.MAV_RESULT_DENIED):
            name = mavlink.enums["MAV_RESULT"][result].name
            raise PX4FlightError(f"PX4 refused MAV_CMD_MISSION_START: {name} (see PX4's console)")
        if world.t > START_LIMIT_S:
            why = "no COMMAND_ACK" if result is None else mavlink.enums["MAV_RESULT"][result].name
            raise PX4FlightError(f"PX4 did not start the mission within {START_LIMIT_S:.0f} s of sim time "
                                 f"({why}; its preflight checks failing? see PX4's console)")  # fmt: skip
        time.sleep(START_RETRY_S)
    log.info("PX4 started the mission at t=%.2f s", world.t)
    state.stage = "flying the mission"
    while not state.stop.is_set():
        msg = port.recv_match(type="MISSION_ITEM_REACHED", blocking=True, timeout=0.1)
        if msg is not None and (not state.reached or state.reached[-1][1] != msg.seq):  # repeated at 1 Hz
            state.reached.append((world.t, int(msg.seq)))
            log.info("PX4 reached mission item %d at t=%.2f s", msg.seq, world.t)
        if gcs.armed:
            state.armed_seen = True
        elif state.armed_seen and gcs.connected:
            state.stage = "landed and disarmed"
            log.info("PX4 landed and disarmed at t=%.2f s", world.t)
            return


def _set_int_param(port: Any, gcs: Any, name: str, value: int) -> None:
    """PARAM_SET an INT32 parameter (PX4 encodes an integer's bytes in the float field) until PX4's
    PARAM_VALUE shows it."""
    as_float = struct.unpack("<f", struct.pack("<i", value))[0]
    for _ in range(gcs.cfg.retries):
        port.mav.send(port.mav.param_set_encode(gcs.sysid, gcs.compid, name.encode(), as_float,
                                                mavlink.MAV_PARAM_TYPE_INT32))  # fmt: skip
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            msg = port.recv_match(type="PARAM_VALUE", blocking=True, timeout=end - time.monotonic())
            if msg is None or msg.param_id != name:
                continue
            got = struct.unpack("<i", struct.pack("<f", msg.param_value))[0]
            if got == value:
                log.info("PX4 %s = %d", name, value)
                return
            raise PX4FlightError(f"PX4 kept {name} = {got} after PARAM_SET {value}")
    raise PX4FlightError(f"PX4 did not confirm {name} = {value} (no PARAM_VALUE): is its simulator output "
                         "module pwm_out_sim running?")  # fmt: skip
