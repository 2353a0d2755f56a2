"""The PX4 offboard sender over real UDP, against a pymavlink peer that plays PX4's onboard MAVLink."""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from droneulator import frames
from droneulator.config import SiteConfig
from droneulator.workflows.planning.offboard import (
    TYPE_MASK_HOLD,
    TYPE_MASK_TRAJECTORY,
    OffboardConfig,
    OffboardLink,
)

HOME = SiteConfig().geodetic
#: PX4's custom_mode of OFFBOARD (main mode 6 in bits 16-23) and of POSCTL (3)
OFFBOARD = 6 << 16
POSCTL = 3 << 16


def wait_until(pred: Any, timeout: float = 5.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.01)


class FakePX4:
    """PX4's onboard MAVLink instance as a pymavlink peer: sends to the link's port like PX4 sends to
    14540+N, HEARTBEATs as MAV_AUTOPILOT_PX4 with its custom mode, LOCAL_POSITION_NED (30 Hz) and
    ATTITUDE (its estimate, ``local_ned`` and ``yaw_ned``), acks commands (results per command, accepted by
    default; OFFBOARD only while setpoints stream, as PX4 does), answers REQUEST_MESSAGE for
    GPS_GLOBAL_ORIGIN and records what it gets. ``silent`` stops everything it sends (a lost link);
    ``local_ned`` None: no position estimate yet (no LOCAL_POSITION_NED until it is set)."""

    def __init__(self, port: int, origin_geodetic: tuple[float, float, float] | None = HOME, sysid: int = 1,
                 hb_hz: float = 10.0, local_ned: Any = (0.0, 0.0, 0.0),
                 yaw_ned: float = 0.0) -> None:  # fmt: skip
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=sysid, source_component=1
        )
        self.origin = origin_geodetic
        self.hb_hz = hb_hz
        self.local_ned = None if local_ned is None else np.asarray(local_ned, dtype=float)
        self.yaw_ned = yaw_ned
        self.results: dict[int, int] = {}
        self.custom_mode = POSCTL
        self.armed = False
        self.silent = threading.Event()
        self.lock = threading.Lock()
        #: (kind, message, custom_mode when it arrived, monotonic time)
        self.log: list[tuple[str, Any, int, float]] = []
        self._last_setpoint = -math.inf
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        next_hb = next_pos = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb and not self.silent.is_set():
                base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
                    mavlink.MAV_MODE_FLAG_SAFETY_ARMED * self.armed
                )
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base,
                                             self.custom_mode, mavlink.MAV_STATE_STANDBY)  # fmt: skip
                next_hb = now + 1.0 / self.hb_hz
            if now >= next_pos and not self.silent.is_set():
                # the heading first: a link that takes the position as it comes has the heading with it
                self.conn.mav.attitude_send(0, 0.0, 0.0, self.yaw_ned, 0.0, 0.0, 0.0)
                if self.local_ned is not None:
                    x, y, z = (float(v) for v in self.local_ned)
                    self.conn.mav.local_position_ned_send(0, x, y, z, 0.0, 0.0, 0.0)
                next_pos = now + 1.0 / 30.0
            msg = self.conn.recv_match(blocking=True, timeout=0.01)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            with self.lock:
                self.log.append((msg.get_type(), msg, self.custom_mode, time.monotonic()))
            if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                self._last_setpoint = time.monotonic()
            if msg.get_type() == "COMMAND_LONG" and not self.silent.is_set():
                self._command(msg)

    def _command(self, msg: Any) -> None:
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            if int(msg.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self.origin is not None:
                lat, lon, alt = self.origin
                self.conn.mav.gps_global_origin_send(round(lat * 1e7), round(lon * 1e7), round(alt * 1e3))
                self.conn.mav.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED)
            return
        result = self.results.get(msg.command, mavlink.MAV_RESULT_ACCEPTED)
        offboard = msg.command == mavlink.MAV_CMD_DO_SET_MODE and int(msg.param2) == 6
        no_signal = time.monotonic() - self._last_setpoint > 0.5
        if offboard and result == mavlink.MAV_RESULT_ACCEPTED and no_signal:
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # PX4: no offboard signal, no OFFBOARD
        if result == mavlink.MAV_RESULT_ACCEPTED:
            if msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                self.custom_mode = (int(msg.param2) << 16) | (int(msg.param3) << 24)
            elif msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                self.armed = msg.param1 == 1.0
        self.conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def messages(self, kind: str) -> list[tuple[Any, int, float]]:
        with self.lock:
            return [(m, mode, t) for k, m, mode, t in self.log if k == kind]

    def commands(self, command: int) -> list[Any]:
        return [m for m, _, _ in self.messages("COMMAND_LONG") if m.command == command]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.conn.close()


def fast_cfg(**kw: Any) -> OffboardConfig:
    base = {
        "base_port": 0,
        "prestream_s": 0.3,
        "ack_timeout_s": 0.3,
        "heartbeat_hz": 5.0,
        "link_timeout_s": 1.0,
    }
    return OffboardConfig(**{**base, **kw})


@pytest.fixture
def px4_pair(request: pytest.FixtureRequest):
    """An OffboardLink on an OS-chosen port and a FakePX4 sending to it."""
    kw = getattr(request, "param", {})
    link = OffboardLink(fast_cfg(**kw.get("link", {})))
    peer = FakePX4(link.address[1], **kw.get("peer", {}))
    yield link, peer
    link.close()
    peer.close()


def _stream_hover(link: OffboardLink, p: np.ndarray, stop: threading.Event) -> None:
    t = 0.0
    while not stop.is_set():
        link.setpoint(t, p, np.zeros(3), np.zeros(3), 0.0, 0.0)
        t += 0.01
        time.sleep(0.01)


PX4_AT = {"peer": {"local_ned": (2.0, 1.0, -3.0), "yaw_ned": 0.3}}


@pytest.mark.alone
@pytest.mark.parametrize("px4_pair", [PX4_AT], indirect=True)
def test_holds_where_px4_is_until_offboard_shows_then_flies_the_planner(px4_pair):
    """Asked for control, the link streams a hold at PX4's own position and heading, switches to OFFBOARD,
    arms, and passes the planner's samples only once PX4's heartbeat shows OFFBOARD: the plan starts
    where PX4 holds (a real PX4 took the 1 m-ahead reference of a prestreamed plan and the planner
    judged itself off track at once)."""
    link, peer = px4_pair
    wait_until(lambda: link.connected, what="the PX4 heartbeat")
    assert (link.sysid, link.compid) == (1, 1)
    # our heartbeat: a companion computer of PX4's system, replying to the peer's own address
    wait_until(lambda: peer.messages("HEARTBEAT"), what="our heartbeat")
    hb = peer.messages("HEARTBEAT")[0][0]
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and hb.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    # the origin request came before any setpoint, and nothing happens until control is asked for
    wait_until(lambda: link.origin_enu is not None, what="the origin")
    np.testing.assert_allclose(link.origin_enu, 0.0, atol=1e-3)
    time.sleep(0.5)
    assert not peer.commands(mavlink.MAV_CMD_DO_SET_MODE)
    assert not peer.messages("SET_POSITION_TARGET_LOCAL_NED")
    assert link.estimate() is None

    stop = threading.Event()
    feeder = threading.Thread(target=_stream_hover, args=(link, np.array([1.5, 2.5, 3.0]), stop), daemon=True)
    feeder.start()  # the planner streams from the start; none of it may reach PX4 before OFFBOARD
    try:
        assert link.engaged.wait(5), link.error
        time.sleep(0.5)
    finally:
        stop.set()
        feeder.join()
    (set_mode,) = peer.commands(mavlink.MAV_CMD_DO_SET_MODE)
    assert set_mode.param1 == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert (set_mode.param2, set_mode.param3) == (6, 0)  # PX4 custom main mode OFFBOARD
    assert (set_mode.target_system, set_mode.target_component) == (1, 1)
    (arm,) = peer.commands(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    assert arm.param1 == 1.0 and arm.param2 == 0.0  # arm, no force
    assert peer.armed and peer.custom_mode == OFFBOARD

    sps = peer.messages("SET_POSITION_TARGET_LOCAL_NED")
    t_mode = next(t for m, _, t in peer.messages("COMMAND_LONG") if m.command == mavlink.MAV_CMD_DO_SET_MODE)
    before = [(m, t) for m, _, t in sps if t < t_mode]
    # streamed for prestream_s (0.3 s, at 50 Hz on a quiet machine; 5 seen with the machine overloaded)
    # before the switch, faster than PX4's "> 2 Hz before OFFBOARD": a hold at PX4's position and heading
    times = [t for _, t in before]
    assert len(before) >= 2 and times[-1] - times[0] >= 0.25 and np.max(np.diff(times)) < 0.5, times
    for m, _ in before:
        assert m.type_mask == TYPE_MASK_HOLD
        np.testing.assert_allclose([m.x, m.y, m.z, m.yaw], [2.0, 1.0, -3.0, 0.3], atol=1e-5)
    # the planner's samples only once PX4's heartbeat said OFFBOARD, then at >= 20 Hz (the median gap; a
    # loaded machine stretched one gap to 0.052 s), never near PX4's offboard loss timeout (COM_OF_LOSS_T 1 s)
    planned = [(m, mode, t) for m, mode, t in sps if m.type_mask == TYPE_MASK_TRAJECTORY]
    assert planned and all(mode == OFFBOARD for _, mode, _ in planned)
    gaps = np.diff([t for _, _, t in planned])
    assert len(planned) >= 15 and np.median(gaps) < 0.05 and np.max(gaps) < 0.5
    m = planned[-1][0]
    assert m.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED and m.type_mask == TYPE_MASK_TRAJECTORY == 0
    assert (m.target_system, m.target_component) == (1, 1)
    np.testing.assert_allclose([m.x, m.y, m.z], [2.5, 1.5, -3.0], atol=1e-6)  # ENU (1.5, 2.5, 3) -> NED


@pytest.mark.parametrize("px4_pair", [{"peer": {"local_ned": (4.0, -1.0, -2.5)}}], indirect=True)
def test_the_estimate_is_px4s_local_position_in_the_world_once_engaged(px4_pair):
    """What the planner plans from with --px4: PX4's LOCAL_POSITION_NED through its origin (from
    GPS_GLOBAL_ORIGIN; at the world origin here) into the ENU world, and PX4's heading."""
    link, peer = px4_pair
    wait_until(lambda: link.origin_enu is not None, what="the origin")
    assert link.estimate() is None  # not engaged: no plan may start from it
    link.engage()
    assert link.engaged.wait(5), link.error
    est = link.estimate()
    np.testing.assert_allclose(est.position, [-1.0, 4.0, 2.5], atol=6e-3)  # (n, e, d) -> (e, n, -d)
    np.testing.assert_allclose(est.velocity, 0.0, atol=1e-9)
    assert est.yaw == pytest.approx(math.pi / 2)  # NED yaw 0 (north) is ENU +90 deg
    peer.local_ned = np.array([5.0, -1.0, -2.5])
    wait_until(lambda: link.estimate().position[1] > 4.9, what="the new estimate")


EXPLICIT_ORIGIN = {"peer": {"origin_geodetic": None}, "link": {"origin_enu": (5.0, -8.0, 0.2)}}


@pytest.mark.parametrize("px4_pair", [EXPLICIT_ORIGIN], indirect=True)
def test_setpoint_fields_are_ned_about_the_origin(px4_pair):
    link, peer = px4_pair
    link.engage()
    assert link.engaged.wait(5), link.error
    p, v, a = np.array([3.0, -6.0, 2.2]), np.array([1.0, 0.5, -0.25]), np.array([0.2, -0.4, 0.8])

    def planned() -> list[Any]:
        link.setpoint(12.345, p, v, a, 0.3, 0.5)
        return [m for m, _, _ in peer.messages("SET_POSITION_TARGET_LOCAL_NED") if m.type_mask == 0]

    wait_until(planned, what="the planner's setpoint")
    m = planned()[-1]
    # written out by hand: NED = (north, east, down) = (y, x, -z) of the ENU offset from the origin
    np.testing.assert_allclose([m.x, m.y, m.z], [2.0, -2.0, -2.0], atol=1e-6)
    np.testing.assert_allclose([m.vx, m.vy, m.vz], [0.5, 1.0, 0.25], atol=1e-6)
    np.testing.assert_allclose([m.afx, m.afy, m.afz], [-0.4, 0.2, -0.8], atol=1e-6)
    assert m.yaw == pytest.approx(math.pi / 2 - 0.3, abs=1e-6)
    assert m.yaw_rate == pytest.approx(-0.5, abs=1e-6)  # counter-clockwise seen from above = negative in NED
    assert m.time_boot_ms == 12345
    assert m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET == 0  # PX4 drops force setpoints


@pytest.mark.parametrize(
    ("yaw_enu", "yaw_ned"),
    [(0.0, math.pi / 2), (math.pi / 2, 0.0), (math.pi, -math.pi / 2), (-math.pi / 2, math.pi),
     (math.pi / 4, math.pi / 4), (-3 * math.pi / 4, -3 * math.pi / 4), (0.1, math.pi / 2 - 0.1)],
)  # fmt: skip
def test_yaw_enu_to_ned_at_several_headings(yaw_enu: float, yaw_ned: float):
    # east (ENU 0) is NED +90 deg, north (ENU 90) is NED 0, west is NED -90, south is NED 180,
    # north-east is 45 deg in both, south-west -135 deg in both
    got = frames.yaw_enu_to_ned(yaw_enu)
    assert math.cos(got - yaw_ned) == pytest.approx(1.0, abs=1e-12)


def _follow_then_stop(link: OffboardLink) -> None:
    """Engage, then 0.4 s of a planner flying north at 1 m/s from (0, 0, 2) (ENU), then silence."""
    link.engage()
    assert link.engaged.wait(5), link.error
    for i in range(40):
        link.setpoint(
            i * 0.01, np.array([0.0, 0.1 * i, 2.0]), np.array([0.0, 1.0, 0.0]), np.zeros(3), 0.0, 0.1
        )
        time.sleep(0.01)


def test_hold_after_the_planner_goes_quiet_streams_the_last_position_only(px4_pair, caplog):
    link, peer = px4_pair
    caplog.set_level(logging.INFO, logger="droneulator.plan.offboard")
    wait_until(lambda: link.connected)
    _follow_then_stop(link)
    wait_until(lambda: "holding at the last position" in caplog.text, what="the hold")
    time.sleep(0.2)
    m = peer.messages("SET_POSITION_TARGET_LOCAL_NED")[-1][0]
    assert m.type_mask == TYPE_MASK_HOLD
    assert m.type_mask & 0b111 == 0 and m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE == 0
    np.testing.assert_allclose([m.x, m.y, m.z], [3.9, 0.0, -2.0], atol=1e-5)
    assert (m.vx, m.vy, m.vz, m.yaw_rate) == (0.0, 0.0, 0.0, 0.0)
    assert peer.custom_mode == OFFBOARD  # "hold" stays in OFFBOARD


@pytest.mark.parametrize("px4_pair", [{"link": {"on_stop": "land"}}], indirect=True)
def test_on_stop_land_switches_px4_to_auto_land(px4_pair):
    link, peer = px4_pair
    wait_until(lambda: link.connected)
    _follow_then_stop(link)
    wait_until(lambda: len(peer.commands(mavlink.MAV_CMD_DO_SET_MODE)) == 2, what="the land mode")
    land = peer.commands(mavlink.MAV_CMD_DO_SET_MODE)[-1]
    assert (land.param2, land.param3) == (4, 6)  # AUTO.LAND


@pytest.mark.parametrize("px4_pair", [{"peer": {}}], indirect=True)
def test_refused_offboard_gives_a_clear_error_and_no_arming(px4_pair, caplog):
    link, peer = px4_pair
    peer.results[mavlink.MAV_CMD_DO_SET_MODE] = mavlink.MAV_RESULT_DENIED
    wait_until(lambda: link.connected)
    link.setpoint(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
    wait_until(lambda: link.error is not None, what="the error")
    assert link.error == "PX4 refused mode OFFBOARD: MAV_RESULT_DENIED"
    assert "PX4 refused mode OFFBOARD: MAV_RESULT_DENIED" in caplog.text
    assert not link.engaged.is_set() and not peer.commands(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)


@pytest.mark.parametrize("px4_pair", [{"peer": {}}], indirect=True)
def test_refused_arming_gives_a_clear_error(px4_pair):
    link, peer = px4_pair
    peer.results[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    wait_until(lambda: link.connected)
    link.setpoint(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
    wait_until(lambda: link.error is not None, what="the error")
    assert link.error.startswith("PX4 refused to arm: MAV_RESULT_TEMPORARILY_REJECTED")
    assert not link.engaged.is_set() and not peer.armed


def test_an_airborne_armed_px4_is_switched_to_offboard_without_arming_again(px4_pair):
    link, peer = px4_pair
    peer.armed, peer.custom_mode = True, (4 << 16) | (3 << 24)  # took off, loitering
    wait_until(lambda: link.connected and link.armed)
    link.setpoint(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
    assert link.engaged.wait(5), link.error
    assert len(peer.commands(mavlink.MAV_CMD_DO_SET_MODE)) == 1
    assert not peer.commands(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)


def test_unanswered_command_is_retried_then_reported(px4_pair):
    link, peer = px4_pair
    wait_until(lambda: link.origin_enu is not None)
    peer.silent.set()  # nothing from now on
    link.setpoint(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
    wait_until(lambda: link.error is not None, timeout=5, what="the error")
    assert link.error == "PX4 refused mode OFFBOARD: no COMMAND_ACK"
    tries = peer.commands(mavlink.MAV_CMD_DO_SET_MODE)
    assert [m.confirmation for m in tries] == [0, 1, 2]


def test_px4_going_silent_is_reported_and_its_return_too(px4_pair, caplog):
    link, peer = px4_pair
    caplog.set_level(logging.INFO, logger="droneulator.plan.offboard")
    wait_until(lambda: link.connected)
    peer.silent.set()
    wait_until(lambda: not link.connected, timeout=3, what="the link to be lost")
    assert "PX4 silent for 1.0 s" in caplog.text and "offboard link lost" in caplog.text
    peer.silent.clear()
    wait_until(lambda: link.connected, timeout=3, what="the link to come back")
    # logged just after the link is marked connected again (a loaded machine ran the check in between)
    wait_until(lambda: "PX4 is back" in caplog.text, timeout=3, what="the return reported")


@pytest.mark.parametrize("px4_pair", [{"peer": {"hb_hz": 0.25}}], indirect=True)
def test_px4_in_a_slow_lockstep_is_not_lost_between_its_heartbeats(px4_pair, caplog):
    """PX4 in lockstep sends its 1 Hz HEARTBEAT on simulated time: a simulation at a quarter of real time
    sends one every 4 s of wall time, while its 30 Hz position still flows. Here heartbeats come 4 s
    apart against a 1 s link timeout: the link stays up, and nothing is reported lost."""
    link, _ = px4_pair
    caplog.set_level(logging.INFO, logger="droneulator.plan.offboard")
    wait_until(lambda: link.connected)
    until = time.monotonic() + 3.0
    while time.monotonic() < until:
        assert link.connected, caplog.text
        time.sleep(0.05)
    assert "offboard link lost" not in caplog.text


def test_no_px4_and_no_origin_are_reported():
    with OffboardLink(fast_cfg(connect_timeout_s=0.3)) as link:
        wait_until(lambda: link.error is not None, what="the error")
        assert link.error.startswith("no HEARTBEAT from PX4 on udp 127.0.0.1:")
    link = OffboardLink(fast_cfg(origin_timeout_s=0.5))
    peer = FakePX4(link.address[1], origin_geodetic=None)
    try:
        wait_until(lambda: link.error is not None, what="the error")
        assert "no GPS_GLOBAL_ORIGIN within" in link.error
        assert len(peer.commands(mavlink.MAV_CMD_REQUEST_MESSAGE)) >= 1
        assert (
            peer.commands(mavlink.MAV_CMD_REQUEST_MESSAGE)[0].param1
            == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN
        )
    finally:
        link.close()
        peer.close()


def test_origin_from_gps_global_origin_and_the_home():
    # PX4's EKF2 started 3 m east, 4 m north and 1 m above the simulator's world origin
    from droneulator import frames

    lat, lon, alt = frames.enu_to_geodetic(np.array([3.0, 4.0, 1.0]), *HOME)
    link = OffboardLink(fast_cfg(instance=7, base_port=14540))
    assert link.address == ("127.0.0.1", 14547)  # 14540 + instance
    peer = FakePX4(14547, origin_geodetic=(lat, lon, alt), sysid=8)
    try:
        wait_until(lambda: link.origin_enu is not None, what="the origin")
        # GPS_GLOBAL_ORIGIN carries 1e-7 deg (1.1 cm of latitude) and mm of altitude
        np.testing.assert_allclose(link.origin_enu, [3.0, 4.0, 1.0], atol=6e-3)
        assert link.sysid == 8
        np.testing.assert_allclose(link.local_ned(np.array([3.0, 4.0, 3.0])), [0.0, 0.0, -2.0], atol=6e-3)
    finally:
        link.close()
        peer.close()


def test_close_sends_px4_to_loiter(px4_pair):
    link, peer = px4_pair
    wait_until(lambda: link.connected)
    link.setpoint(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
    assert link.engaged.wait(5), link.error
    link.close()
    last = peer.commands(mavlink.MAV_CMD_DO_SET_MODE)[-1]
    assert (last.param2, last.param3) == (4, 3)  # AUTO.LOITER


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="rate_hz must exceed 2 Hz"):
        OffboardConfig(rate_hz=2.0)
    with pytest.raises(ValueError, match="on_stop"):
        OffboardConfig(on_stop="hover")  # type: ignore[arg-type]
    with OffboardLink(fast_cfg(connect_timeout_s=5.0)) as link:
        with pytest.raises(ValueError, match="finite"):
            link.setpoint(0.0, np.array([0.0, np.nan, 1.0]), np.zeros(3), np.zeros(3), 0.0, 0.0)
        with pytest.raises(ValueError, match="3-vectors"):
            link.setpoint(0.0, np.zeros(2), np.zeros(3), np.zeros(3), 0.0, 0.0)


@pytest.mark.slow
def test_plan_node_sends_its_trajectory_to_px4_as_ned_setpoints_on_a_real_run(caplog):
    """The real planner on a real `droneulator run` (no PX4 there: the simulator hovers by itself),
    its trajectory server feeding OffboardLink, and the peer checking the NED setpoints."""
    from droneulator import frames
    from droneulator.config import CameraConfig, load_config
    from droneulator.runtime.launch import launch_run
    from droneulator.workflows.planning.node import PlanNode, PlanNodeConfig

    caplog.set_level(logging.INFO, logger="droneulator.plan.offboard")
    cam = CameraConfig(name="front", width=320, height=240)
    cfg = load_config(scene="tree_inspection")
    cfg.render.cameras = [cam]
    cfg.render.shadow_map_size = 512
    origin = np.array([0.0, -8.0, 0.0])  # EKF2 started where the vehicle stood
    with launch_run(cfg) as run:
        client = run.client()
        link = OffboardLink(fast_cfg())
        # PX4 is up before the planner, as PX4 SITL is: the link gives a PX4 connect_timeout_s (wall) to
        # appear, and building the planner (its kernels compile on a fresh clone: 67 s seen on a busy
        # core) and the takeoff may take longer than that. Its estimate comes once the vehicle hovers
        peer = FakePX4(link.address[1], origin_geodetic=frames.enu_to_geodetic(origin, *HOME), local_ned=None,
                       yaw_ned=math.pi / 2)  # fmt: skip
        node = None
        try:
            client.reset(position=origin.tolist(), yaw=0.0)
            client.subscribe(["events"])
            client.takeoff(altitude=2.0)
            client.wait_for_event("arrived", timeout=60)
            start = np.array(client.state()["position"])
            # the planner starts at the hover, so its map is made of depth images taken there: one made
            # before the reset, at the spawn 15 m away (images that reached it late on a busy core), put
            # the goal outside the local map and the goal was refused ("no motion")
            # the vehicle does not follow (no PX4 flies it), so the off-track rule is off
            node_cfg = PlanNodeConfig(zenoh=run.zenoh_endpoint, namespace=cfg.bridge.namespace,
                                      camera=cam.name, max_tracking_error=math.inf)  # fmt: skip
            node = PlanNode(node_cfg, autopilot=link)
            # PX4's estimate: where the vehicle hovers, about the origin, facing east (ENU yaw 0)
            peer.local_ned = frames.enu_to_ned(start - origin)
            goal = start + [3.0, 0.0, 0.0]
            node.set_goal(goal)
            # ENU offset from the origin (e, n, u) -> NED (n, e, -u), written out
            off = goal - origin
            goal_ned = np.array([off[1], off[0], -off[2]])

            def at_goal() -> bool:
                sps = peer.messages("SET_POSITION_TARGET_LOCAL_NED")
                if not sps:
                    return False
                m = sps[-1][0]
                return (
                    np.linalg.norm([m.x, m.y, m.z] - goal_ned) < 0.02
                    and np.linalg.norm([m.vx, m.vy, m.vz]) < 0.01
                )

            # judged in sim time (30 s to plan and fly 3 m), not wall time: a loaded machine slows the
            # lockstep run, and with it the trajectory the setpoints follow
            t0, wall_end = client.state()["t"], time.monotonic() + 600
            while not at_goal():
                late = client.state()["t"] - t0 > 30.0 or time.monotonic() > wall_end
                assert not late, f"no setpoints at the goal in 30 s sim time; planner {node.last_failure!r}"
                time.sleep(0.1)
            assert link.engaged.wait(5), f"{link.error!r}; {caplog.text}"
            assert peer.armed and peer.custom_mode == OFFBOARD
            sps = [m for m, _, _ in peer.messages("SET_POSITION_TARGET_LOCAL_NED")]
            off0 = start - origin
            first = np.array([sps[0].x, sps[0].y, sps[0].z])
            assert np.linalg.norm(first - [off0[1], off0[0], -off0[2]]) < 0.15, first
            # flying east (ENU +x): NED velocity along +y, heading 90 deg in NED
            mid = max(sps, key=lambda m: m.vy)
            assert mid.vy > 0.3 and abs(mid.vx) < 0.2 * mid.vy
            assert all(abs(m.yaw - math.pi / 2) < 0.2 for m in sps)
            assert sps[-1].type_mask == TYPE_MASK_TRAJECTORY
            # the setpoints went to PX4 instead of the PositionCommand topic: the simulator held where it was
            state = client.state()
            assert state["mode"] != "track" and np.linalg.norm(np.array(state["position"]) - start) < 0.2
        finally:
            if node is not None:
                node.close()
            link.close()
            peer.close()
            client.close()
