"""A PX4 SITL stand-in for CI, where the real PX4 cannot be built: what the simulator and an offboard
client see of PX4 v1.16, scripted in Python with the real MAVLink codec (pymavlink).

It plays both of PX4's links, as ``px4 -i N`` does:

* **simulator_mavlink** (TCP client of ``127.0.0.1:sim_port``, retrying until the simulator listens):
  a HEARTBEAT from ``MAV_AUTOPILOT_PX4`` on connecting, then one lockstep HIL_ACTUATOR_CONTROLS
  (``flags`` bit 0, ``mode`` bit 7 while armed) per HIL_SENSOR, with quad-X motor outputs in [0, 1].
* **the onboard/offboard MAVLink instance** (UDP, sending to ``offboard_port`` as PX4 sends to
  14540+N and answering whoever talks to it) and, with ``gcs_port``, the ground-station instance (as
  PX4 sends to 14550): HEARTBEAT (1 Hz, custom mode and armed flag), LOCAL_POSITION_NED (30 Hz) and
  ATTITUDE (50 Hz) of its own estimate, GPS_GLOBAL_ORIGIN on request, COMMAND_ACKs (ARM,
  DO_SET_MODE, NAV_TAKEOFF, NAV_LAND), and SET_POSITION_TARGET_LOCAL_NED in OFFBOARD.

What it does as PX4 does, because the simulator and the planner depend on it:

* it flies **its estimate**, not the truth: the local origin is its first GPS fix (EKF2 does the same),
  position and velocity come from the accelerometer propagated between GPS fixes and corrected
  towards each fix (a complementary filter in place of EKF2), so a GPS error or bias shows up as the
  difference between where it thinks it is and where the vehicle is; the attitude is the simulator's
  HIL_STATE_QUATERNION (EKF2's attitude is close to the truth);
* it boots disarmed believing it is on the ground, arms only on command, outputs idle while armed and
  landed, accepts OFFBOARD only while setpoints stream (its offboard signal: one within 0.5 s of
  sim time), falls back to holding (AUTO.LOITER) when they stop, and flies MAV_CMD_NAV_TAKEOFF up to
  ``MIS_TAKEOFF_ALT`` (2.5 m) at PX4's climb speed;
* it flies **an uploaded mission** on MAV_CMD_MISSION_START (AUTO.MISSION and armed in one, as PX4's
  commander does; DENIED without a mission): NAV_TAKEOFF climbs straight up to the item's altitude,
  each NAV_WAYPOINT is flown to in a straight line at the cruise speed (MPC_XY_CRUISE, 5 m/s, or the
  last DO_CHANGE_SPEED) and reached within the item's acceptance radius (NAV_ACC_RAD, 10 m, where it
  is 0) and NAV_MC_ALT_RAD; MISSION_ITEM_REACHED carries the last item done (a waypoint's DO items are
  done with it: PX4 reports the last of them), sent when it changes and again once a second, as
  PX4 v1.16 does; DO_SET_ACTUATOR sets its
  actuator 1 ("Peripheral via Actuator Set 1"), which HIL_ACTUATOR_CONTROLS output 5 carries while
  ``PWM_MAIN_FUNC5`` is 301 (PARAM_SET, answered with PARAM_VALUE, integers bytewise as PX4 does);
  NAV_RETURN_TO_LAUNCH is PX4's RTL: climb to the return altitude of ``RTL::
  calculate_return_alt_from_cone_half_angle`` (RTL_RETURN_ALT above home beyond NAV_ACC_RAD), fly
  home, land and disarm;
* its position controller is the simulator's own SE(3) controller with PX4-like tilt and thrust
  bounds on its estimated state, allocated to motor outputs through the inverse of the simulator's
  output -> rotor speed map, so its outputs are what PX4 with its default mixer would send for
  those thrusts.

Its clock is the HIL_SENSOR ``time_usec`` (lockstep), as PX4's is: its streams and timeouts run in
sim time.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from droneulator import frames
from droneulator.controllers.se3 import FastSE3Control
from droneulator.px4.mixing import MotorMap
from droneulator.px4.transport import pack_next
from droneulator.state import FLAT_SIZE, STATE, STATE_SIZE
from droneulator.vehicles.params import get_params

#: PX4 custom main modes (px4_custom_mode.h) and the AUTO sub modes used here
MAIN_AUTO, MAIN_OFFBOARD = 4, 6
SUB_TAKEOFF, SUB_LOITER, SUB_MISSION, SUB_RTL, SUB_LAND = 2, 3, 4, 5, 6
G = 9.80665
#: MIS_TAKEOFF_ALT, MPC_TKO_SPEED, MPC_LAND_SPEED of PX4's defaults
TAKEOFF_ALT, TAKEOFF_SPEED, LAND_SPEED = 2.5, 1.5, 0.7
#: MPC_XY_CRUISE, MPC_Z_V_AUTO_UP, MPC_Z_V_AUTO_DN (above MPC_LAND_ALT1), NAV_ACC_RAD, NAV_MC_ALT_RAD
CRUISE, CLIMB_SPEED, DESCEND_SPEED, LAND_ALT1 = 5.0, 3.0, 1.5, 10.0
NAV_ACC_RAD, NAV_MC_ALT_RAD = 10.0, 0.8
#: PX4's offboard signal: a setpoint within this much sim time (COM_OF_LOSS_T is 1 s; the mode check 0.5 s)
OFFBOARD_SIGNAL_S = 0.5
#: the mission items PX4 stores (its dataman's default capacity), and the commands and frames its mission
#: manager takes (a subset of ``MavlinkMissionManager::parse_mavlink_mission_item``'s)
MISSION_MAX_ITEMS = 500
MISSION_COMMANDS = frozenset({
    mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_CMD_NAV_LOITER_TIME, mavlink.MAV_CMD_NAV_LOITER_UNLIM,
    mavlink.MAV_CMD_DO_CHANGE_SPEED, mavlink.MAV_CMD_DO_SET_ACTUATOR, mavlink.MAV_CMD_DO_SET_SERVO,
    mavlink.MAV_CMD_DO_JUMP,
})  # fmt: skip
MISSION_FRAMES = frozenset({
    mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_INT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_MISSION,
})  # fmt: skip
#: complementary filter gains per GPS fix (10 Hz): position and velocity towards the fix
GAIN_P, GAIN_V = 0.15, 0.25


def custom_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


class ScriptedPX4:
    """Connect to the simulator on ``sim_port`` and send offboard MAVLink to ``offboard_port``; runs in a
    thread until :meth:`close`. ``params``: the run's vehicle parameter set (``px4_quadx`` with --px4)."""

    def __init__(self, sim_port: int, offboard_port: int, params: str = "px4_quadx", sysid: int = 1,
                 connect_timeout: float = 60.0, gcs_port: int | None = None, rtl_return_alt: float = 60.0,
                 mission_max_items: int = MISSION_MAX_ITEMS) -> None:  # fmt: skip
        quad = get_params(params)
        self.motors = MotorMap(quad)
        self.se3 = FastSE3Control(quad, max_tilt_deg=35.0, min_lift=0.2)
        self.w_min, self.w_max = float(quad["rotor_speed_min"]), float(quad["rotor_speed_max"])
        self.sysid = sysid
        self._tx = mavlink.MAVLink(None, sysid, 1)
        self._rx = mavlink.MAVLink(None)
        self._rx.robust_parsing = True
        #: MAVLink instances: [socket, where it sends, its parser]
        self._links: list[list[Any]] = []
        for port in (offboard_port, gcs_port):
            if port is not None:
                udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                udp.bind(("127.0.0.1", 0))
                udp.setblocking(False)
                parser = mavlink.MAVLink(None)
                parser.robust_parsing = True
                self._links.append([udp, ("127.0.0.1", port), parser])
        self._sim_port, self._connect_timeout = sim_port, connect_timeout
        self._sock: socket.socket | None = None
        self.lock = threading.Lock()
        # flight state (under lock)
        self.armed = False
        self.landed = True
        self.mode = custom_mode(MAIN_AUTO, SUB_LOITER)
        self.t = 0.0
        self.origin: tuple[float, float, float] | None = None  # geodetic of the local NED origin
        self.p = np.zeros(3)  # estimate, local ENU about the origin
        self.v = np.zeros(3)
        self.q = np.array([0.0, 0.0, 0.0, 1.0])  # FLU -> ENU
        self.w = np.zeros(3)  # body rates FLU
        self._hold = np.zeros(3)
        self._hold_yaw = 0.0
        self._climb_to = 0.0
        self._setpoint: tuple[float, np.ndarray, np.ndarray, np.ndarray, float, float] | None = None
        self._next = {"heartbeat": 0.0, "local": 0.0, "attitude": 0.0, "reached": 0.0}
        self._last_t_us: int | None = None
        #: the stored mission (MISSION_ITEM_INT messages) and the upload under way
        self.mission: list[Any] = []
        self._upload: list[Any] | None = None
        self._upload_count = 0
        self._max_items = mission_max_items
        #: PX4 parameters it answers PARAM_SET for
        self.params: dict[str, float] = {"PWM_MAIN_FUNC5": 0, "RTL_RETURN_ALT": rtl_return_alt}
        #: the mission item flown, the cruise speed, actuator set 1 (DO_SET_ACTUATOR), home, the RTL's phase
        self._seq = 0
        self._cruise = CRUISE
        self._actuator1 = 0.0
        self._home = np.zeros(3)
        self._rtl: tuple[str, np.ndarray] | None = None
        #: the last mission item done (MISSION_ITEM_REACHED), and whether it is new
        self._reached: tuple[int, bool] | None = None
        #: MAVLink messages missed per (system, component) on the offboard port, by their sequence numbers
        self.rx_missed: dict[tuple[int, int], int] = {}
        self._last_rx_seq: dict[tuple[int, int], int] = {}
        #: every (sim t, mode, armed) change and every command result, for tests
        self.log: list[tuple[float, str, Any]] = []
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="scripted-px4", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public (a PX4 shell's commands)
    def takeoff(self) -> None:
        """``commander takeoff``: arm and climb to MIS_TAKEOFF_ALT above the take-off point."""
        with self.lock:
            self._takeoff()

    def estimate_world(self, origin_enu: np.ndarray) -> np.ndarray:
        """The position estimate in the simulator's world, given the world position of its origin."""
        with self.lock:
            return np.asarray(origin_enu, dtype=float) + self.p

    @property
    def custom_mode(self) -> int:
        return self.mode

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for s in (self._sock, *(link[0] for link in self._links)):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.close()

    # ------------------------------------------------------------------ the loop
    def _run(self) -> None:
        try:
            self._connect()
            buf = bytearray()
            while not self._stop.is_set():
                self._offboard_rx()
                try:
                    data = self._sock.recv(65536)
                except TimeoutError:
                    continue
                except ConnectionResetError:
                    return  # the simulator closed the link, as at EOF
                if not data:
                    return
                buf += data
                for msg in self._rx.parse_buffer(bytes(buf)) or []:
                    self._on_sim(msg)
                buf.clear()
        except OSError as exc:
            if not self._stop.is_set():
                self.error = exc  # e.g. the simulator never listened within connect_timeout
                raise
        except BaseException as exc:  # a test reads it: the thread must not die silently
            self.error = exc
            raise

    def _connect(self) -> None:
        end = time.monotonic() + self._connect_timeout
        while not self._stop.is_set():
            try:
                self._sock = socket.create_connection(("127.0.0.1", self._sim_port), timeout=5.0)
                break
            except ConnectionRefusedError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.005)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(0.05)
        hello = self._tx.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
        self._sock.sendall(pack_next(self._tx, hello))

    def _on_sim(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HIL_STATE_QUATERNION":
            q_ned = frames.wxyz_to_xyzw(np.array(msg.attitude_quaternion))
            with self.lock:
                self.q = frames.quat_ned_frd_to_enu_flu(q_ned)
        elif kind == "HIL_GPS":
            self._on_gps(msg)
        elif kind == "HIL_SENSOR":
            self._on_imu(msg)

    # ------------------------------------------------------------------ estimator
    def _on_gps(self, msg: Any) -> None:
        lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3
        v_gps = frames.ned_to_enu(np.array([msg.vn, msg.ve, msg.vd]) / 100.0)
        with self.lock:
            if self.origin is None:
                self.origin = (lat, lon, alt)  # EKF2: the local origin is the first good fix
                self.log.append((self.t, "origin", self.origin))
            p_gps = frames.geodetic_to_enu(lat, lon, alt, *self.origin)
            self.p += GAIN_P * (p_gps - self.p)
            self.v += GAIN_V * (v_gps - self.v)

    def _on_imu(self, msg: Any) -> None:
        dt = 0.0 if self._last_t_us is None else (msg.time_usec - self._last_t_us) * 1e-6
        self._last_t_us = msg.time_usec
        with self.lock:
            self.t = msg.time_usec * 1e-6
            self.w = frames.frd_to_flu(np.array([msg.xgyro, msg.ygyro, msg.zgyro]))
            f_body = frames.frd_to_flu(np.array([msg.xacc, msg.yacc, msg.zacc]))
            if self.origin is not None and 0.0 < dt < 0.1:
                a = frames.quat_to_matrix(self.q) @ f_body + np.array([0.0, 0.0, -9.81])
                self.p += self.v * dt + 0.5 * a * dt * dt
                self.v += a * dt
            u = self._control(dt)
            armed = self.armed
        self._offboard_tx()
        spray = self._actuator1 if self.params["PWM_MAIN_FUNC5"] == 301 else 0.0
        controls = [float(x) for x in u] + [spray] + [0.0] * 11
        out = self._tx.hil_actuator_controls_encode(msg.time_usec, controls, 128 * armed, 1)
        self._sock.sendall(pack_next(self._tx, out))

    # ------------------------------------------------------------------ control (lock held)
    def _flat(self, dt: float) -> np.ndarray | None:
        """The reference the position controller tracks, or None for idle outputs."""
        f = np.zeros(FLAT_SIZE)
        main, sub = (self.mode >> 16) & 0xFF, (self.mode >> 24) & 0xFF
        if not self.armed:
            return None
        if main == MAIN_OFFBOARD:
            sp = self._setpoint
            if sp is None or self.t - sp[0] > OFFBOARD_SIGNAL_S:
                self._set_mode(custom_mode(MAIN_AUTO, SUB_LOITER), "offboard signal lost")
                self._hold, self._hold_yaw = self.p.copy(), frames.yaw_of(self.q)
            else:
                _, p, v, a, yaw, yaw_rate = sp
                f[0:3], f[3:6], f[6:9], f[9], f[10] = p, v, a, yaw, yaw_rate
                return f
        if main == MAIN_AUTO and sub == SUB_TAKEOFF:
            self._hold[2] = min(self._climb_to, self._hold[2] + TAKEOFF_SPEED * dt)
            f[5] = TAKEOFF_SPEED if self._hold[2] < self._climb_to else 0.0
            if self._hold[2] >= self._climb_to and abs(self.p[2] - self._climb_to) < 0.1:
                self._set_mode(custom_mode(MAIN_AUTO, SUB_LOITER), "take-off done")
        elif main == MAIN_AUTO and sub == SUB_MISSION:
            return self._fly_mission(dt, f)
        elif main == MAIN_AUTO and sub == SUB_RTL:
            return self._fly_rtl(dt, f)
        elif main == MAIN_AUTO and sub == SUB_LAND:
            return self._descend(dt, f)
        elif self.landed:
            return None  # armed on the ground with nothing to do: idle
        f[0:3], f[9] = self._hold, self._hold_yaw
        return f

    def _descend(self, dt: float, f: np.ndarray) -> np.ndarray | None:
        """Land where it is (MPC_Z_V_AUTO_DN above MPC_LAND_ALT1 over home, MPC_LAND_SPEED below), then
        disarm."""
        speed = LAND_SPEED if self.p[2] - self._home[2] < LAND_ALT1 else DESCEND_SPEED
        self._hold[2] -= speed * dt
        f[5] = -speed
        if self.p[2] < 0.05 and abs(self.v[2]) < 0.2:
            self.landed = True
            self.armed = False
            self._set_mode(custom_mode(MAIN_AUTO, SUB_LOITER), "landed: disarmed")
            return None
        f[0:3], f[9] = self._hold, self._hold_yaw
        return f

    def _towards(self, target: np.ndarray, speed: float, dt: float, f: np.ndarray) -> np.ndarray:
        """Move the reference along the straight line to ``target`` at ``speed`` (velocity fed forward)."""
        d = target - self._hold
        n = float(np.linalg.norm(d))
        if n <= speed * dt:
            self._hold = target.copy()
        else:
            self._hold = self._hold + d / n * speed * dt
            f[3:6] = d / n * speed
        f[0:3], f[9] = self._hold, self._hold_yaw
        return f

    def _item_enu(self, m: Any) -> np.ndarray:
        return frames.geodetic_to_enu(m.x * 1e-7, m.y * 1e-7, m.z, *self.origin)

    def _fly_mission(self, dt: float, f: np.ndarray) -> np.ndarray | None:
        """AUTO.MISSION: the current item (see the module docstring); DO items take no time."""
        while self._seq < len(self.mission):
            m = self.mission[self._seq]
            if m.command == mavlink.MAV_CMD_DO_CHANGE_SPEED:
                if m.param2 > 0:
                    self._cruise = float(m.param2)
            elif m.command == mavlink.MAV_CMD_DO_SET_ACTUATOR:
                if np.isfinite(m.param1):
                    self._actuator1 = float(m.param1)
            elif m.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self._seq += 1
                self._set_mode(custom_mode(MAIN_AUTO, SUB_RTL), "mission: RTL")
                return self._fly_rtl(dt, f)
            elif m.command in (mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_WAYPOINT):
                target = self._item_enu(m)
                takeoff = m.command == mavlink.MAV_CMD_NAV_TAKEOFF
                if takeoff:
                    target[:2] = self._hold[:2]  # a multicopter climbs straight up
                    reached = self.p[2] >= target[2] - NAV_MC_ALT_RAD
                else:
                    radius = m.param2 if m.param2 > 0 else NAV_ACC_RAD
                    reached = (np.hypot(*(self.p[:2] - target[:2])) <= radius
                               and abs(self.p[2] - target[2]) <= NAV_MC_ALT_RAD)  # fmt: skip
                if not reached:
                    return self._towards(target, TAKEOFF_SPEED if takeoff else self._cruise, dt, f)
            self._reached = (self._seq, True)
            self._seq += 1
        self._set_mode(custom_mode(MAIN_AUTO, SUB_LOITER), "mission done")
        f[0:3], f[9] = self._hold, self._hold_yaw
        return f

    def _fly_rtl(self, dt: float, f: np.ndarray) -> np.ndarray | None:
        """AUTO.RTL: climb to the return altitude, fly home at it, land."""
        if self._rtl is None:
            d = float(np.hypot(*(self.p[:2] - self._home[:2])))
            top = self._home[2] + self.params["RTL_RETURN_ALT"]
            alt = self._home[2] + 2.0 * d if d <= NAV_ACC_RAD else top
            self._rtl = ("climb", np.array([*self._hold[:2], min(max(alt, self.p[2]), max(top, self.p[2]))]))
        phase, target = self._rtl
        if phase == "climb":
            if self.p[2] < target[2] - NAV_MC_ALT_RAD:
                return self._towards(target, CLIMB_SPEED, dt, f)
            self._rtl = phase, target = ("return", np.array([*self._home[:2], target[2]]))
        if phase == "return":
            if np.hypot(*(self.p[:2] - target[:2])) > NAV_ACC_RAD or np.linalg.norm(self._hold - target) > 0:
                return self._towards(target, self._cruise, dt, f)
            self._rtl = ("land", target)
        return self._descend(dt, f)

    def _control(self, dt: float) -> np.ndarray:
        flat = self._flat(dt)
        if flat is None:
            return np.zeros(4)
        s = np.zeros(STATE_SIZE)
        s[STATE.x], s[STATE.v], s[STATE.q], s[STATE.w] = self.p, self.v, self.q, self.w
        w = np.clip(self.se3.motor_speeds(s, flat), self.w_min, self.w_max)
        return self.motors.speed_to_output(w[list(self.motors.order)])

    def _set_mode(self, mode: int, why: str) -> None:
        if mode != self.mode:
            self.mode = mode
            self.log.append((self.t, "mode", (mode, why)))

    def _takeoff(self) -> None:
        if self.origin is None:
            raise RuntimeError("no position estimate yet: PX4 refuses to take off")
        self.armed, self.landed = True, False
        self._hold, self._hold_yaw = self.p.copy(), frames.yaw_of(self.q)
        self._climb_to = self.p[2] + TAKEOFF_ALT
        self._set_mode(custom_mode(MAIN_AUTO, SUB_TAKEOFF), "takeoff")

    # ------------------------------------------------------------------ offboard link
    def _send(self, msg: Any, link: list[Any] | None = None) -> None:
        """To one MAVLink instance's peer, or to every instance's."""
        data = pack_next(self._tx, msg)
        for sock, peer, _ in [link] if link is not None else self._links:
            with contextlib.suppress(OSError):
                sock.sendto(data, peer)

    def _due(self, name: str, hz: float) -> bool:
        if self.t < self._next[name]:
            return False
        self._next[name] = self.t + 1.0 / hz
        return True

    def _offboard_tx(self) -> None:
        with self.lock:
            t, mode, armed, origin = self.t, self.mode, self.armed, self.origin
            p, v, q = self.p.copy(), self.v.copy(), self.q.copy()
            reached = self._reached
            if reached is not None:
                self._reached = (reached[0], False)
        if reached is not None and (reached[1] or self._due("reached", 1.0)):
            self._send(self._tx.mission_item_reached_encode(reached[0]))
        if self._due("heartbeat", 1.0):
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED * armed)
            kind, autopilot = mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4
            self._send(self._tx.heartbeat_encode(kind, autopilot, base, mode, mavlink.MAV_STATE_ACTIVE))
        if origin is not None and self._due("local", 30.0):
            pn, vn = frames.enu_to_ned(p), frames.enu_to_ned(v)
            self._send(self._tx.local_position_ned_encode(round(t * 1000), *map(float, pn), *map(float, vn)))
        if self._due("attitude", 50.0):
            yaw, pitch, roll = Rotation.from_quat(frames.quat_enu_flu_to_ned_frd(q)).as_euler("ZYX")
            self._send(self._tx.attitude_encode(round(t * 1000), roll, pitch, yaw, 0.0, 0.0, 0.0))

    def _offboard_rx(self) -> None:
        for link in self._links:
            while True:
                try:
                    data, addr = link[0].recvfrom(65535)
                except (BlockingIOError, OSError):
                    break
                link[1] = addr  # PX4 answers whoever talks to it
                for msg in link[2].parse_buffer(data) or []:
                    self._count_sequence(msg)
                    if msg.get_type() == "COMMAND_LONG":
                        self._command(msg, link)
                    elif msg.get_type() in ("MISSION_COUNT", "MISSION_ITEM_INT"):
                        self._mission(msg, link)
                    elif msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                        self._on_setpoint(msg)
                    elif msg.get_type() == "PARAM_SET":
                        self._param_set(msg, link)

    def _count_sequence(self, msg: Any) -> None:
        """PX4's receive statistics (MavlinkReceiver::updateRxStats): per sending system and component, the
        messages missed by the MAVLink sequence numbers; one sender packing with two codecs shows as loss."""
        key = (msg.get_srcSystem(), msg.get_srcComponent())
        last = self._last_rx_seq.get(key)
        if last is not None:
            self.rx_missed[key] = self.rx_missed.get(key, 0) + (msg.get_seq() - last - 1) % 256
        self._last_rx_seq[key] = msg.get_seq()

    def _on_setpoint(self, m: Any) -> None:
        mask = m.type_mask
        p = frames.ned_to_enu(np.array([m.x, m.y, m.z]))
        v = np.zeros(3) if mask & mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE else frames.ned_to_enu(
            np.array([m.vx, m.vy, m.vz]))  # fmt: skip
        a = np.zeros(3) if mask & mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE else frames.ned_to_enu(
            np.array([m.afx, m.afy, m.afz]))  # fmt: skip
        yaw_rate = 0.0 if mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE else -m.yaw_rate
        with self.lock:
            self._setpoint = (self.t, p, v, a, frames.yaw_ned_to_enu(m.yaw), yaw_rate)

    def _mission(self, msg: Any, link: list[Any]) -> None:
        """The mission upload as PX4's MavlinkMissionManager answers it: MISSION_COUNT starts it (0 items
        clears the mission), each item is asked for in turn with MISSION_REQUEST_INT, an item out of turn
        is ignored (its request repeated), an unsupported command or frame ends it with that MISSION_ACK,
        and the last item with MAV_MISSION_ACCEPTED; the mission then replaces the stored one."""
        if msg.mission_type != mavlink.MAV_MISSION_TYPE_MISSION:
            return self._mission_ack(msg, mavlink.MAV_MISSION_UNSUPPORTED, link)
        if msg.get_type() == "MISSION_COUNT":
            if msg.count > self._max_items:
                return self._mission_ack(msg, mavlink.MAV_MISSION_NO_SPACE, link)
            self._upload = []
            self._upload_count = msg.count
            if msg.count == 0:
                self.mission = []
                return self._mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED, link)
            return self._mission_request(msg, link)
        if self._upload is None:
            return  # an item outside an upload: PX4 ignores it
        if msg.seq != len(self._upload):
            return self._mission_request(msg, link)
        if msg.command not in MISSION_COMMANDS:
            self._upload = None
            return self._mission_ack(msg, mavlink.MAV_MISSION_UNSUPPORTED, link)
        if msg.frame not in MISSION_FRAMES:
            self._upload = None
            return self._mission_ack(msg, mavlink.MAV_MISSION_UNSUPPORTED_FRAME, link)
        self._upload.append(msg)
        if len(self._upload) < self._upload_count:
            return self._mission_request(msg, link)
        with self.lock:
            self.mission, self._upload = self._upload, None
            self.log.append((self.t, "mission", len(self.mission)))
        self._mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED, link)

    def _param_set(self, msg: Any, link: list[Any]) -> None:
        """PARAM_SET of a known parameter: stored and echoed with PARAM_VALUE (an INT32's bytes in the
        float, as PX4 encodes it); an unknown one is ignored."""
        name = msg.param_id
        if name not in self.params:
            return
        integer = msg.param_type == mavlink.MAV_PARAM_TYPE_INT32
        value = struct.unpack("<i", struct.pack("<f", msg.param_value))[0] if integer else msg.param_value
        with self.lock:
            self.params[name] = value
        index = list(self.params).index(name)
        self._send(self._tx.param_value_encode(name.encode(), msg.param_value, msg.param_type,
                                               len(self.params), index), link)  # fmt: skip

    def _mission_request(self, msg: Any, link: list[Any]) -> None:
        self._send(self._tx.mission_request_int_encode(msg.get_srcSystem(), msg.get_srcComponent(),
                                                       len(self._upload), mavlink.MAV_MISSION_TYPE_MISSION),
                   link)  # fmt: skip

    def _mission_ack(self, msg: Any, result: int, link: list[Any]) -> None:
        self._send(self._tx.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                               msg.mission_type), link)  # fmt: skip

    def _ack(self, msg: Any, result: int, link: list[Any]) -> None:
        self._send(self._tx.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(),
                                               msg.get_srcComponent()), link)  # fmt: skip
        with self.lock:
            self.log.append((self.t, "ack", (msg.command, result)))

    def _command(self, msg: Any, link: list[Any]) -> None:
        c = msg.command
        ok, denied = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        if c == mavlink.MAV_CMD_REQUEST_MESSAGE:
            if int(msg.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self.origin is not None:
                lat, lon, alt = self.origin
                self._send(self._tx.gps_global_origin_encode(round(lat * 1e7), round(lon * 1e7),
                                                             round(alt * 1e3)), link)  # fmt: skip
                self._ack(msg, ok, link)
            else:
                self._ack(msg, denied, link)
            return
        with self.lock:
            if c == mavlink.MAV_CMD_DO_SET_MODE:
                main, sub = int(msg.param2), int(msg.param3)
                signal = self._setpoint is not None and self.t - self._setpoint[0] <= OFFBOARD_SIGNAL_S
                if main == MAIN_OFFBOARD and not signal:
                    result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                else:
                    result = ok
                    if main == MAIN_AUTO and sub == SUB_LAND:
                        self._hold = self.p.copy()
                    elif main == MAIN_AUTO:
                        self._hold, self._hold_yaw = self.p.copy(), frames.yaw_of(self.q)
                    self._set_mode(custom_mode(main, sub if main == MAIN_AUTO else 0), "commanded")
            elif c == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if msg.param1 == 1.0:
                    result = ok if self.origin is not None else denied
                    if result == ok:
                        self.armed = True
                        self._hold, self._hold_yaw = self.p.copy(), frames.yaw_of(self.q)
                else:
                    result = ok if self.landed else denied
                    self.armed = self.armed and not self.landed
            elif c == mavlink.MAV_CMD_NAV_TAKEOFF:
                result = ok if self.origin is not None and self.armed else denied  # PX4: arm first
                if result == ok:
                    self._takeoff()
            elif c == mavlink.MAV_CMD_MISSION_START:
                result = ok if self.mission and self.origin is not None else denied
                if result == ok:
                    self.armed, self.landed = True, False
                    self._hold, self._hold_yaw = self.p.copy(), frames.yaw_of(self.q)
                    self._home, self._seq, self._rtl = self.p.copy(), int(msg.param1), None
                    self._set_mode(custom_mode(MAIN_AUTO, SUB_MISSION), "mission start")
            elif c == mavlink.MAV_CMD_NAV_LAND:
                result = ok if self.armed else denied
                if result == ok:
                    self._hold = self.p.copy()
                    self._set_mode(custom_mode(MAIN_AUTO, SUB_LAND), "land")
            else:
                result = mavlink.MAV_RESULT_UNSUPPORTED
        self._ack(msg, result, link)
