"""What the simulator sends PX4 each physics step, as ``simulator_mavlink`` expects it.

Per step: HIL_SENSOR (``id`` 0; accel and gyro every step, mag and baro at their rates, flagged in
``fields_updated``), HIL_GPS at ``gps_hz``, HIL_STATE_QUATERNION (ground truth), and a HEARTBEAT at
1 Hz; ``time_usec`` is simulation time. The readings come from the vehicle's sensor models
(:mod:`droneulator.sensors`); this module only packs them, as PX4 reads them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from droneulator.config import PX4Config, SiteConfig
from droneulator.frames import enu_to_geodetic, enu_to_ned, xyzw_to_wxyz
from droneulator.px4.transport import pack_next
from droneulator.sensors import SensorSuite, Truth
from droneulator.sensors.baro import BaroSample
from droneulator.sensors.suite import Schedule

G0 = 9.80665

#: HIL_SENSOR ``fields_updated`` groups PX4 checks (``SensorSource`` in SimulatorMavlink.hpp)
SENSOR_ACCEL = 0b111
SENSOR_GYRO = 0b111000
SENSOR_MAG = 0b111000000
#: abs_pressure, pressure_alt and temperature: PX4 takes the baro sample only with all three
SENSOR_BARO = 0b1101000000000

#: MAVLink identity of the simulator (as Gazebo-classic's mavlink_interface: system 1, IMU component)
SIM_SYSTEM_ID = 1
SIM_COMPONENT_ID = mavlink.MAV_COMP_ID_IMU

#: PX4 stores accel 0 and gyro 0 as int16 FIFO counts of these sizes (SimulatorMavlink::update_sensors)
ACCEL_FIFO_SCALE = np.float32(G0 / 2048.0)
GYRO_FIFO_SCALE = np.float32(math.radians(2000.0 / 32768.0))


def _i16(x: float) -> int:
    return int(np.clip(round(x), -32767, 32767))


def _u16(x: float) -> int:
    return int(np.clip(round(x), 0, 65534))


def fifo_clip(values: np.ndarray, scale: np.float32) -> np.ndarray:
    """``values`` clipped to what PX4's int16 FIFO holds at ``scale`` (-32768..32767 counts).

    PX4 divides each float32 HIL_SENSOR value by the FIFO scale and stores it in an ``int16_t``: a
    value at exactly +16 g (or +2000 deg/s) is +32768 counts and wraps to -32768, so the top of the
    range is one count lower than the bottom's mirror image.
    """
    lo, hi = np.float32(-32768.0) * scale, np.float32(32767.0) * scale
    return np.clip(np.asarray(values, dtype=np.float32), lo, hi)


class HilEncoder:
    """Packs one vehicle's sensor readings and ground truth into the MAVLink batch PX4 reads per step.

    ``sensors`` is the vehicle's sensor suite (an IMU, magnetometer and barometer; without a GPS no
    HIL_GPS is sent, without an airspeed sensor HIL_STATE_QUATERNION's airspeeds are zero); ``cfg`` has
    the sensor rates; ``site`` is the world origin's place, PX4's home.
    """

    def __init__(self, sensors: SensorSuite, cfg: PX4Config, site: SiteConfig) -> None:
        self.sensors, self.cfg, self.site = sensors, cfg, site
        self._tx = mavlink.MAVLink(None, SIM_SYSTEM_ID, SIM_COMPONENT_ID)
        self._last_mag = np.zeros(3)
        self._last_baro = BaroSample(0.0, 0.0, 0.0)
        self.reset()

    def reset(self) -> None:
        """Restart every sensor's schedule (a new connection)."""
        self._schedule = Schedule()
        self._last_t_ns: int | None = None

    def batch(self, truth: Truth) -> bytes:
        """HEARTBEAT (1 Hz), HIL_GPS (gps_hz), HIL_STATE_QUATERNION and HIL_SENSOR for ``truth``, packed."""
        t_ns = truth.t_ns
        if self._last_t_ns is not None and t_ns < self._last_t_ns:
            self._schedule.clear()  # the simulation was reset: restart every schedule
        self._last_t_ns = t_ns
        t_us = t_ns // 1000
        msgs = []
        if self._due("heartbeat", t_ns, 1.0):
            msgs.append(
                self._tx.heartbeat_encode(
                    mavlink.MAV_TYPE_GENERIC, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
                )
            )
        if "gps" in self.sensors and self._due("gps", t_ns, self.cfg.gps_hz):
            gps = self._gps_message(truth, t_us)
            if gps is not None:  # no fix while the GPS is lost (docs/faults.md)
                msgs.append(gps)
        msgs.append(self._state_message(truth, t_us))
        msgs.append(self._sensor_message(truth, t_us))
        return b"".join(pack_next(self._tx, m) for m in msgs)

    def _due(self, name: str, t_ns: int, hz: float) -> bool:
        """True when sensor ``name`` (sampled at ``hz`` in sim time) has a sample due at ``t_ns``."""
        return self._schedule.due(name, t_ns, hz)

    def _sensor_message(self, truth: Truth, t_us: int) -> Any:
        accel, gyro = self.sensors.imu(truth)
        accel, gyro = fifo_clip(accel, ACCEL_FIFO_SCALE), fifo_clip(gyro, GYRO_FIFO_SCALE)
        # what PX4 gets (float32, within its int16 FIFO) is the vehicle's newest IMU sample: ROS publishes it
        self.sensors.record("imu", truth.t_ns, (accel.astype(np.float64), gyro.astype(np.float64)))
        fields = SENSOR_ACCEL | SENSOR_GYRO
        if self._due("mag", truth.t_ns, self.cfg.mag_hz):
            self._last_mag = self.sensors.mag(truth)
            fields |= SENSOR_MAG
        if self._due("baro", truth.t_ns, self.cfg.baro_hz):
            self._last_baro = self.sensors.baro(truth)
            fields |= SENSOR_BARO
        b = self._last_baro
        return self._tx.hil_sensor_encode(
            t_us,
            *(float(v) for v in accel),
            *(float(v) for v in gyro),
            *self._last_mag,
            b.pressure_hpa,
            0.0,
            b.pressure_alt_m,
            b.temperature_c,
            fields,
            0,
        )

    def _gps_message(self, truth: Truth, t_us: int) -> Any:
        g = self.sensors.gps(truth)
        if g is None:
            return None
        return self._tx.hil_gps_encode(
            t_us,
            g.fix_type,
            round(g.lat_deg * 1e7),
            round(g.lon_deg * 1e7),
            round(g.alt_msl_m * 1000.0),
            _u16(g.eph_m * 100.0),
            _u16(g.epv_m * 100.0),
            _u16(g.ground_speed * 100.0),
            *(_i16(v * 100.0) for v in g.vel_ned),
            round(g.course_deg * 100.0) % 36000,
            g.satellites,
            0,
            0,
        )

    def _state_message(self, truth: Truth, t_us: int) -> Any:
        lat, lon, alt = enu_to_geodetic(truth.position, *self.site.geodetic)
        ias, tas = self.sensors.airspeed(truth) if "airspeed" in self.sensors else (0.0, 0.0)
        acc_mg = truth.acceleration_frd / G0 * 1000.0
        return self._tx.hil_state_quaternion_encode(
            t_us,
            [float(v) for v in xyzw_to_wxyz(truth.quaternion_ned_frd)],
            *(float(v) for v in truth.gyro_frd),
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000.0),
            *(_i16(v * 100.0) for v in enu_to_ned(truth.velocity)),
            _u16(ias * 100.0),
            _u16(tas * 100.0),
            *(_i16(v) for v in acc_mg),
        )
