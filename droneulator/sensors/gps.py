"""GPS: a delayed 3D fix in WGS84 with a correlated position error, and a noisy NED velocity.

The position error follows PX4's Gazebo GPS plugin (``gazebo_gps_plugin.cpp``): a random-walk
bias pulled back over a correlation time (a first-order Gauss-Markov process) plus white noise,
and fixes leave late from a delay buffer. Unlike the plugin (whose bias update omits ``dt`` in its
decay term and whose fixed eph/epv of 1 m do not describe its error), the process is integrated
exactly, so its stationary 1-sigma is the model's horizontal (vertical) sigma and the
reported eph/epv are the actual 1-sigma of the error. A slowly wandering error is what keeps PX4's
at-rest drift check (EKF2 ``EKF2_REQ_HDRIFT``, a 10 s low-pass of the fix-to-fix position rate)
quiet: white noise of the same size makes that filtered rate about ``sigma / 10 s`` per axis.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from droneulator.config.site import SiteConfig
from droneulator.frames import enu_to_geodetic, enu_to_ned, geodetic_to_enu
from droneulator.sensors.registry import register
from droneulator.sensors.truth import Truth

#: eph / epv floor (m): a zero accuracy would tell PX4 the fix is perfect
MIN_ACCURACY_M = 0.01


@dataclass(frozen=True)
class GpsSample:
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    #: velocity north, east, down (m/s)
    vel_ned: np.ndarray
    ground_speed: float
    #: course over ground, degrees in [0, 360)
    course_deg: float
    #: horizontal (per axis, as EKF2 uses it) / vertical 1-sigma position accuracy (m)
    eph_m: float
    epv_m: float
    #: MAVLink GPS_FIX_TYPE: 3 (3D fix), 6 (RTK fixed) as the preset says
    fix_type: int
    satellites: int
    #: sim time (ns) of the state this fix describes: the sampling time less ``gps_delay_s``
    time_ns: int


@register("gps")
class Gps:
    """The fix of the world position at ``site`` (the world origin's geodetic point); ``cfg`` (a
    :class:`~droneulator.config.PX4Config`) gives the position error
    (:meth:`~droneulator.config.PX4Config.gps_error`: ``gps_preset`` and the ``gps_*_m`` overrides),
    ``gps_vel_noise``, ``gps_vel_vertical_noise``, ``gps_delay_s``, ``gps_bias_m`` and ``gps_satellites``.

    :meth:`observe` records the truth of every step into the delay line (the sensor suite calls it
    on every sample of any sensor); :meth:`sample` reports the state ``gps_delay_s`` earlier,
    interpolated linearly between the recorded steps.
    """

    def __init__(self, cfg: Any, rng: np.random.Generator, site: SiteConfig | None = None) -> None:
        self.cfg = cfg
        self.site = site or SiteConfig()
        self.rng = rng
        #: the position error model in effect (the preset, with explicitly set fields instead)
        self._model = cfg.gps_error()
        self._delay_ns = round(cfg.gps_delay_s * 1e9)
        #: recorded truths (t_ns, position ENU, velocity ENU), oldest first
        self._history: deque[tuple[int, np.ndarray, np.ndarray]] = deque()
        #: the correlated position error (m, NED) and the fix time it belongs to
        self._error: np.ndarray | None = None
        self._error_t_ns = 0

    @property
    def error_ned(self) -> np.ndarray | None:
        """The correlated part of the position error (m, NED) at the last fix; None before one."""
        return None if self._error is None else self._error.copy()

    def observe(self, truth: Truth) -> None:
        """Record ``truth`` for the delay line. A time earlier than the last one (a reset) restarts
        it; the same time again replaces the last entry (a reset can land on the same step time)."""
        hist = self._history
        if hist and truth.t_ns < hist[-1][0]:
            hist.clear()
        elif hist and truth.t_ns == hist[-1][0]:
            hist.pop()
        pos, vel = np.array(truth.position, dtype=float), np.array(truth.velocity, dtype=float)
        hist.append((truth.t_ns, pos, vel))
        horizon = truth.t_ns - self._delay_ns
        while len(hist) > 1 and hist[1][0] <= horizon:
            hist.popleft()  # keep one entry at or before the horizon to interpolate from

    def _delayed(self, t_ns: int) -> tuple[int, np.ndarray, np.ndarray]:
        """(time, position, velocity) at ``t_ns - gps_delay_s``; before the history reaches back that
        far, its oldest entry (as the plugin's delay buffer sends its oldest fix)."""
        hist = self._history
        target = t_ns - self._delay_ns
        if target <= hist[0][0]:
            return hist[0]
        for (t0, p0, v0), (t1, p1, v1) in zip(hist, list(hist)[1:], strict=False):
            if t1 >= target:
                w = (target - t0) / (t1 - t0)
                return target, p0 + w * (p1 - p0), v0 + w * (v1 - v0)
        return hist[-1]

    def _advance_error(self, t_ns: int) -> np.ndarray:
        """Step the Gauss-Markov error to fix time ``t_ns`` with its exact discretisation
        ``e' = phi e + sigma sqrt(1 - phi^2) n``, ``phi = exp(-dt / tau)``; it starts (and restarts
        after a reset) from its stationary distribution, so eph holds from the first fix."""
        e = self._model
        sigma = np.array([e.horizontal_m, e.horizontal_m, e.vertical_m])
        n = self.rng.standard_normal(3)
        if self._error is None or t_ns < self._error_t_ns:
            self._error = sigma * n
        else:
            phi = math.exp(-(t_ns - self._error_t_ns) / 1e9 / e.correlation_time_s)
            self._error = phi * self._error + sigma * math.sqrt(1.0 - phi * phi) * n
        self._error_t_ns = t_ns
        return self._error

    def sample(self, truth: Truth) -> GpsSample:
        """The fix sent at ``truth.t_ns``: the state ``gps_delay_s`` earlier plus the errors."""
        c, e, rng = self.cfg, self._model, self.rng
        self.observe(truth)
        t_fix, pos_enu, vel_enu = self._delayed(truth.t_ns)
        error = self._advance_error(t_fix) + e.jitter_m * rng.standard_normal(3)
        pos_ned = enu_to_ned(pos_enu) + np.asarray(c.gps_bias_m, dtype=float) + error
        vel_sigma = np.array([c.gps_vel_noise, c.gps_vel_noise, c.gps_vel_vertical_noise])
        vel_ned = enu_to_ned(vel_enu) + vel_sigma * rng.standard_normal(3)
        lat, lon, alt = enu_to_geodetic(enu_to_ned(pos_ned), *self.site.geodetic)
        course = math.degrees(math.atan2(vel_ned[1], vel_ned[0])) % 360.0
        return GpsSample(
            lat,
            lon,
            alt,
            vel_ned,
            float(math.hypot(vel_ned[0], vel_ned[1])),
            course,
            eph_m=max(math.hypot(e.horizontal_m, e.jitter_m), MIN_ACCURACY_M),
            epv_m=max(math.hypot(e.vertical_m, e.jitter_m), MIN_ACCURACY_M),
            fix_type=e.fix_type,
            satellites=c.gps_satellites,
            time_ns=int(t_fix),
        )


class Ekf2DriftCheck:
    """PX4 EKF2's at-rest GNSS checks (``runOnGroundGnssChecks`` in ``gps_checks.cpp``), replayed.

    Per fix: the position change since the last fix (PX4's map projection), divided by the time
    between fixes, low-passed with a 10 s time constant (coefficient ``dt / 10``) and clamped to ten
    times the limits; the horizontal drift rate is the norm of its north/east part and fails above
    ``EKF2_REQ_HDRIFT`` (0.1 m/s), the vertical one above ``EKF2_REQ_VDRIFT`` (0.2 m/s). The GNSS
    velocity is low-passed the same way ("hspeed", against ``EKF2_REQ_HDRIFT``).
    """

    FILTER_TIME_CONSTANT_S = 10.0

    def __init__(self, req_hdrift: float = 0.1, req_vdrift: float = 0.2) -> None:
        self.req_hdrift = req_hdrift
        self.req_vdrift = req_vdrift
        self._prev: tuple[float, float, float, float] | None = None  # (t s, lat, lon, alt)
        self._pos_rate = np.zeros(3)
        self._vel_ne = np.zeros(2)
        #: the filtered horizontal and vertical position drift rates and horizontal speed (m/s)
        self.hdrift = 0.0
        self.vdrift = 0.0
        self.hspeed = 0.0

    def update(self, t_s: float, sample: GpsSample) -> None:
        """Feed one fix received at ``t_s`` (s)."""
        tau = self.FILTER_TIME_CONSTANT_S
        if self._prev is None:
            dt, delta = tau, np.zeros(3)
        else:
            t0, lat0, lon0, alt0 = self._prev
            dt = min(max(t_s - t0, 0.001), tau)
            east, north, _ = geodetic_to_enu(sample.lat_deg, sample.lon_deg, 0.0, lat0, lon0, 0.0)
            delta = np.array([north, east, alt0 - sample.alt_msl_m])
        coef = dt / tau
        limit = 10.0 * np.array([self.req_hdrift, self.req_hdrift, self.req_vdrift])
        self._pos_rate = np.clip(delta / dt * coef + self._pos_rate * (1.0 - coef), -limit, limit)
        self.hdrift = float(np.hypot(self._pos_rate[0], self._pos_rate[1]))
        self.vdrift = float(abs(self._pos_rate[2]))
        vel_ne = np.clip(np.asarray(sample.vel_ned[:2], dtype=float), -limit[0], limit[0])
        self._vel_ne = vel_ne * coef + self._vel_ne * (1.0 - coef)
        self.hspeed = float(np.hypot(*self._vel_ne))
        self._prev = (t_s, sample.lat_deg, sample.lon_deg, sample.alt_msl_m)

    @property
    def failed(self) -> bool:
        """True while any of the three checks fails."""
        return self.hdrift > self.req_hdrift or self.vdrift > self.req_vdrift or self.hspeed > self.req_hdrift
