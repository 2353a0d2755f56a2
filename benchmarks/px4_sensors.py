"""The IMU, GPS and magnetometer statistics PX4's estimator checks, re-measured without PX4.

1. Accelerometer peak at touchdown: the vehicle descends onto the default scene's ground at a
   steady 0.2..2 m/s on PX4's path (rotor speeds set directly, ``Vehicle.set_rotor_speeds``) and
   the IMU is read the way ``PX4Link`` reads it (``Truth.from_sim`` -> ``SensorSuite.imu``); PX4's
   simulator interface holds +-16 g, so a peak beyond that is a corrupted sample.
2. GPS drift at rest: EKF2's at-rest checks replayed on the fixes (``Ekf2DriftCheck``: the 10 s
   low-pass of the fix-to-fix position rate against ``EKF2_REQ_HDRIFT`` 0.1 m/s, the vertical one
   against ``EKF2_REQ_VDRIFT`` 0.2 m/s, the filtered GNSS speed against 0.1 m/s), for the
   configured Gauss-Markov error and for white noise of the same size (the model before issue 10).
3. eph/epv against the actual position error, and its autocorrelation.
4. Magnetometer declination, inclination and strength at home, measured through the sensor, against
   the World Magnetic Model and against the old fixed field.

Runs in well under a minute on one core; writes ``benchmarks/results/px4_sensors.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from typing import Any

import numpy as np
from _common import write

from droneulator import frames as F
from droneulator.config import PX4Config, SiteConfig, load_config
from droneulator.sensors import SensorSuite, Truth
from droneulator.sensors.gps import Ekf2DriftCheck
from droneulator.sensors.mag import field_elements, wmm_field_ned_gauss
from droneulator.world import World

G0 = 9.80665
#: PX4's simulator interface accelerometer range (m/s^2)
ACCEL_RANGE = 16.0 * G0
FIX_NS = 100_000_000
#: the magnetometer's field before issue 10 (gauss, NED)
OLD_FIELD_NED = (0.19, -0.005, 0.45)


def touchdowns(speeds: list[float], drop_m: float, seed: int) -> list[dict[str, Any]]:
    """Descend from ``drop_m`` with constant thrust so the vehicle meets the ground at each speed."""
    cfg = load_config(overrides=["vehicle.control_hz=250", "vehicle.params=px4_quadx"])
    world = World(scene="default", render=False, config=cfg)
    uav = world.vehicle()
    suite = SensorSuite(cfg.px4, seed)
    ground = float(world.scene.spawn_position[2])
    out = []
    for v in speeds:
        world.reset(position=world.scene.spawn_position + np.array([0.0, 0.0, drop_m]), airborne=True)
        # thrust (1 - a/g) of hover accelerates the descent at a = v^2 / (2 h)
        accel_down = v * v / (2.0 * drop_m)
        uav.set_rotor_speeds([uav.hover_speed * math.sqrt(1.0 - accel_down / 9.81)] * 4)
        accel, vz, z = [], [], []
        for _ in range(round((2.0 * drop_m / v + 1.0) * 250)):  # the descent and 1 s on the ground
            world.step()
            truth = Truth.from_sim(uav)
            accel.append(suite.imu(truth)[0])
            vz.append(truth.velocity[2])
            z.append(truth.position[2])
        a = np.array(accel)
        k = int(np.argmax(np.linalg.norm(a, axis=1)))
        peak = float(np.abs(a).max())
        out.append(
            {
                "commanded_m_s": v,
                "touchdown_m_s": round(float(-min(vz[: k + 1])), 3),
                "peak_accel_frd_m_s2": [round(float(x), 2) for x in a[k]],
                "peak_axis_m_s2": round(peak, 2),
                "peak_g": round(peak / G0, 2),
                "within_16g": peak <= ACCEL_RANGE,
                "bounce_m": round(max(z[k:]) - ground, 3),
            }
        )
    world.close()
    return out


def drift_at_rest(cfg: PX4Config, seeds: range, minutes: float) -> dict[str, Any]:
    """EKF2's filtered drift rates over ``minutes`` at rest per seed, after the first minute."""
    z3, level = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    rates = []
    for seed in seeds:
        suite, check = SensorSuite(cfg, seed), Ekf2DriftCheck()
        for k in range(round(minutes * 600)):
            check.update(0.1 * k, suite.gps(Truth(k * FIX_NS, z3, z3, level, z3, z3, z3)))
            if k >= 600:
                rates.append((check.hdrift, check.vdrift, check.hspeed))
    r = np.array(rates)

    def stats(x: np.ndarray) -> dict[str, float]:
        return {
            "median": round(float(np.median(x)), 4),
            "p99": round(float(np.percentile(x, 99)), 4),
            "max": round(float(x.max()), 4),
        }

    return {
        "hours": round(len(seeds) * (minutes - 1.0) / 60.0, 2),
        "hdrift_m_s": stats(r[:, 0]),
        "vdrift_m_s": stats(r[:, 1]),
        "hspeed_m_s": stats(r[:, 2]),
        "fraction_failing": round(
            float(np.mean((r[:, 0] > 0.1) | (r[:, 1] > 0.2) | (r[:, 2] > 0.1))), 5
        ),
    }


def accuracy(cfg: PX4Config, seeds: range, minutes: float) -> dict[str, Any]:
    """Reported eph/epv against the RMS of the actual position error, and its autocorrelation."""
    z3, level = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    home = SiteConfig().geodetic  # the suites' default site
    errors, rho = [], []
    tau = cfg.gps_error().correlation_time_s
    tau_lag = max(1, round(tau * 10))
    for seed in seeds:
        suite = SensorSuite(cfg, seed)
        fixes = [suite.gps(Truth(k * FIX_NS, z3, z3, level, z3, z3, z3)) for k in range(round(minutes * 600))]
        enu = [F.geodetic_to_enu(g.lat_deg, g.lon_deg, g.alt_msl_m, *home) for g in fixes]
        e = F.enu_to_ned(np.array(enu))
        errors.append(e)
        for lag in (1, tau_lag):
            x = e[:, 0] - e[:, 0].mean()
            rho.append((lag, float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))))
    e = np.concatenate(errors)
    rms = np.sqrt(np.mean(e**2, axis=0))
    return {
        "eph_m": round(fixes[0].eph_m, 3),
        "epv_m": round(fixes[0].epv_m, 3),
        "rms_error_north_east_down_m": [round(float(x), 3) for x in rms],
        "autocorrelation_north_lag_0.1s": round(float(np.mean([r for lag, r in rho if lag == 1])), 3),
        f"autocorrelation_north_lag_{tau:g}s": round(
            float(np.mean([r for lag, r in rho if lag == tau_lag])), 3
        ),
        "expected_at_correlation_time": round(math.exp(-1.0), 3),
        "note": f"{len(seeds)} x {minutes:g} min at rest; with a {tau:g} s "
        "correlation time the RMS has ~10 % sampling spread",
    }


def magnetometer(cfg: PX4Config) -> dict[str, Any]:
    """Mean magnetometer reading, nose on true north and level (FRD = NED), against the WMM."""
    z3 = np.zeros(3)
    north = F.quat_from_yaw(math.pi / 2)
    suite = SensorSuite(cfg, 0)
    mean = np.mean([suite.mag(Truth(k * 10_000_000, z3, z3, north, z3, z3, z3)) for k in range(2000)], axis=0)
    measured = field_elements(mean)
    home = SiteConfig().geodetic  # the suites' default site
    wmm = field_elements(wmm_field_ned_gauss(*home, cfg.mag_wmm_year))
    old = field_elements(OLD_FIELD_NED)

    def row(el: Any) -> dict[str, float]:
        return {
            "declination_deg": round(el.declination_deg, 3),
            "inclination_deg": round(el.inclination_deg, 3),
            "strength_gauss": round(el.strength_gauss, 4),
        }

    return {
        "home": list(SiteConfig().geodetic),
        "wmm_year": cfg.mag_wmm_year,
        "measured": row(measured),
        "wmm2025": row(wmm),
        "old_fixed_field": row(old),
        "declination_error_deg": round(measured.declination_deg - wmm.declination_deg, 3),
        "old_declination_error_deg": round(old.declination_deg - wmm.declination_deg, 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.2, 0.4, 0.6, 0.7, 1.0, 1.5, 2.0])
    ap.add_argument("--drop", type=float, default=1.0, help="height the descent starts from (m)")
    ap.add_argument("--minutes", type=float, default=10.0, help="GPS minutes at rest per seed")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--gps-preset", default="realistic", choices=("sitl", "realistic"),
                    help="GPS error preset to check (px4.gps_preset; the drift checks matter for realistic)")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/px4_sensors.json)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    cfg = PX4Config(gps_preset=args.gps_preset)
    seeds = range(args.seeds)

    td = touchdowns(args.speeds, args.drop, 0)
    print("Touchdown (IMU through SensorSuite, PX4's accelerometer range +-16 g = 156.9 m/s^2):")
    print(f"  {'commanded':>9} {'touchdown':>9} {'peak':>9} {'peak':>6} {'in range':>8} {'bounce':>7}")
    for r in td:
        print(
            f"  {r['commanded_m_s']:7.2f}   {r['touchdown_m_s']:7.2f}   {r['peak_axis_m_s2']:7.1f}"
            f"   {r['peak_g']:5.1f}g {'yes' if r['within_16g'] else 'NO':>8} {r['bounce_m']:6.3f}m"
        )

    gm = drift_at_rest(cfg, seeds, args.minutes)
    white_cfg = PX4Config(gps_preset=args.gps_preset, gps_correlation_time_s=1e-6, gps_jitter_m=0.0)
    white = drift_at_rest(white_cfg, seeds, args.minutes)
    print(f"\nGPS at rest, EKF2's at-rest checks replayed ({gm['hours']} h per model):")
    head = f"{'hdrift median/p99/max (limit 0.1)':<35} {'vdrift max (0.2)':<18} hspeed max (0.1)"
    print(f"  {'model':<26} {head}")
    tau = cfg.gps_error().correlation_time_s
    models = ((f"Gauss-Markov, tau {tau:g} s", gm), ("white per fix (before)", white))
    for name, r in models:
        h = r["hdrift_m_s"]
        print(
            f"  {name:<26} {h['median']:.4f} / {h['p99']:.4f} / {h['max']:.4f}{'':<11}"
            f" {r['vdrift_m_s']['max']:<18.4f} {r['hspeed_m_s']['max']:.4f}"
        )

    acc = accuracy(cfg, seeds, 3 * args.minutes)
    print("\nGPS accuracy: reported vs actual")
    rms = acc["rms_error_north_east_down_m"]
    print(f"  eph {acc['eph_m']} m, epv {acc['epv_m']} m; RMS error N/E/D {rms} m")
    lag_key = f"autocorrelation_north_lag_{tau:g}s"
    print(
        f"  autocorrelation at 0.1 s {acc['autocorrelation_north_lag_0.1s']},"
        f" at {tau:g} s {acc[lag_key]} (first-order Gauss-Markov: e^-1 = 0.368)"
    )

    mag = magnetometer(cfg)
    print(f"\nMagnetometer at home {mag['home']} on {mag['wmm_year']} (measured through the sensor):")
    for key in ("declination_deg", "inclination_deg", "strength_gauss"):
        print(
            f"  {key:<16} measured {mag['measured'][key]:>9}  WMM {mag['wmm2025'][key]:>9}"
            f"  old fixed field {mag['old_fixed_field'][key]:>9}"
        )
    wall = time.perf_counter() - t0
    print(f"\n{wall:.1f} s")
    write(
        "px4_sensors",
        {
            "wall_s": round(wall, 1),
            "touchdown": td,
            "gps_drift_at_rest": {"gauss_markov": gm, "white_per_fix": white},
            "gps_accuracy": acc,
            "magnetometer": mag,
            "config": {
                "gps_preset": cfg.gps_preset,
                "gps_error": dataclasses.asdict(cfg.gps_error()),
            }
            | {
                k: getattr(cfg, k)
                for k in (
                    "gps_vel_noise",
                    "gps_vel_vertical_noise",
                    "gps_delay_s",
                    "gps_hz",
                    "imu_preset",
                    "mag_preset",
                )
            }
            # the noise in effect (the presets', or the fields set): per sample, the IMU at PX4's 250 Hz
            | {"mag_noise": cfg.mag_error(), "accel_noise": cfg.imu_error(250.0).accel_sigma},
        },
        args.out,
    )


if __name__ == "__main__":
    main()
