"""Control at every level (docs/control.md): an aggressive figure-eight flown by the SE(3) controller and by
collective thrust and body rates (CTBR) from the reference's flat outputs, and the latency from a command's
acceptance to the first motion at each level.

1. **Figure-eight.** A lemniscate of Gerono, ``x = A sin(phi)``, ``y = A/2 sin(2 phi)``, at 5 m, constant
   yaw, its phase speeding up smoothly (a quintic ramp of ``dphi/dt``, jerk continuous) over one period and
   then flown for ``--laps`` periods; the errors are over those laps. The same analytic reference
   (position, velocity, acceleration, jerk) on the same airframe at the same 100 Hz control rate, flown:

   * **SE(3)**: the vehicle's ``track`` mode (position, velocity and acceleration feed-forward; RotorPy's
     SE(3) controller), given the reference every control period through ``FlightController.track``, the
     method the ``track`` op calls after its checks (the op itself refuses accelerations above 10 m/s^2
     and speeds above ``flight.max_speed``: most of these figures it would not even take). Twice: as
     configured by default (its thrust vector within ``flight.max_tilt_deg`` = 45 degrees of vertical, as
     PX4's ``MPC_TILTMAX_AIR``) and unbounded (``flight.max_tilt_deg=null``, RotorPy's own controller);
   * **CTBR**: :class:`~droneulator.controllers.flatness.CTBRTracker` through ``Vehicle.rates`` (the
     ``rates`` op's checks): the thrust and body rates of Mellinger and Kumar's differential flatness from
     the reference's acceleration and jerk, with the SE(3) controller's position feedback (RotorPy's
     gains) and an attitude correction of ``0.8 k_w`` (the airframe's body-rate gain).

   Each with RotorPy's aerodynamics (rotor and parasitic drag, translational lift, the default) and without
   (``vehicle.aero=false``, the drag-free model the flat feed-forward is exact for). With them, on an
   airframe with rotor drag (``k_d`` > 0: the Hummingbird, not the PX4 quad), the unbounded SE(3) and CTBR
   fly once more (``+drag``) with the rotor drag at the reference velocity added to the reference's
   acceleration (:func:`rotor_drag`), the same for both. A controller **cannot
   hold** a figure when its largest position error over the laps exceeds :data:`HOLD_MAX_ERROR` (0.25 m, a
   twelfth of the 3 m half-width): beyond that it flies a different figure.
2. **Latency.** A real :class:`~droneulator.api.ApiServer` over a world stepped in real time (one 10 ms
   control period per 10 ms of wall time, as the runtime paces it) and a WebSocket client. From hover, each
   level is commanded once per trial (velocity: 1 m/s forward; rates: 1 rad/s roll at the weight's thrust;
   attitude: 0.2 rad roll; rotors: every rotor 10 % above its hover speed) and the stepping thread records
   every state. The latency is from the command's acceptance (the reply's ``stamp_ns``; wall time when
   the server's command path returned) to the first state whose angular velocity or acceleration (from
   consecutive velocities) differs from its value before the command by more than 5 times its spread
   over the 20 states before it (at least 1e-3 rad/s, 1e-3 m/s^2): the first motion; and to the first
   state where the commanded quantity is half-way (forward speed, roll rate, roll angle, rotor speed).

Reproduce: ``python benchmarks/control.py`` (about a minute; ``--no-latency`` for the figure-eights only);
writes ``benchmarks/results/control.json`` and ``docs/img/control_levels.png``.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import write

from droneulator.api import ApiServer, DroneulatorClient
from droneulator.commands import CommandPath
from droneulator.config import load_config
from droneulator.controllers.flatness import CTBRTracker
from droneulator.frames import quat_to_euler, quat_to_matrix, world_to_body
from droneulator.state import STATE
from droneulator.vehicles.params import get_params
from droneulator.world import World

#: largest position error (m) over the laps of a figure that a controller holds
HOLD_MAX_ERROR = 0.25
ALTITUDE = 5.0
#: per airframe: the figure's half-width A (m) and the periods (s) flown, from gentle to what the airframe's
#: rotors can still give (on the Hummingbird, at 3.5 s the rotors saturate at the figure's ends)
FIGURES = {"hummingbird": (3.0, (6.0, 5.0, 4.0, 3.5)), "px4_quadx": (3.0, (8.0, 6.0, 5.0))}
#: the attitude correction of the CTBR tracker, per body-rate gain of the airframe
K_ATT_PER_RATE_GAIN = 0.8
FIGURE = Path(__file__).resolve().parent.parent / "docs" / "img" / "control_levels.png"

Reference = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def figure_eight(t: float, half_width: float, period: float) -> Reference:
    """Position, velocity, acceleration and jerk (world ENU) of the figure-eight at time ``t``: the phase
    speeds up over the first ``period`` (``dphi/dt = w (10u^3 - 15u^4 + 6u^5)``, ``u = t / period``), then
    turns at ``w = 2 pi / period``."""
    w = 2.0 * math.pi / period
    if t < period:
        u = t / period
        ph = w * period * (2.5 * u**4 - 3.0 * u**5 + u**6)
        d1 = w * (10.0 * u**3 - 15.0 * u**4 + 6.0 * u**5)
        d2 = w / period * (30.0 * u**2 - 60.0 * u**3 + 30.0 * u**4)
        d3 = w / period**2 * (60.0 * u - 180.0 * u**2 + 120.0 * u**3)
    else:
        ph, d1, d2, d3 = w * period / 2.0 + w * (t - period), w, 0.0, 0.0
    a, b = half_width, half_width / 2.0
    s1, c1, s2, c2 = math.sin(ph), math.cos(ph), math.sin(2.0 * ph), math.cos(2.0 * ph)
    f0 = np.array([a * s1, b * s2, ALTITUDE])
    f1 = np.array([a * c1, 2.0 * b * c2, 0.0])
    f2 = np.array([-a * s1, -4.0 * b * s2, 0.0])
    f3 = np.array([-a * c1, -8.0 * b * c2, 0.0])
    return f0, f1 * d1, f2 * d1**2 + f1 * d2, f3 * d1**3 + 3.0 * f2 * d1 * d2 + f1 * d3


def rotor_drag(quad_params: dict[str, Any], s: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """The acceleration (m/s^2, world) RotorPy's rotor drag takes from a vehicle in state ``s`` flying at
    ``velocity`` in still air: ``k_d`` times the sum of the rotor speeds times the airspeed in the rotor
    plane, over the mass (the first-order drag of Faessler et al. 2018; parasitic drag, translational lift
    and induced inflow are left out)."""
    z = quat_to_matrix(s[STATE.q])[:, 2]
    in_plane = velocity - float(velocity @ z) * z
    spin = float(np.sum(s[STATE.rotor_speeds]))
    return float(quad_params["k_d"]) * spin * in_plane / float(quad_params["mass"])


def peak_accel(half_width: float, period: float) -> float:
    """The figure's largest acceleration (m/s^2) once at full speed."""
    return float(
        max(np.linalg.norm(figure_eight(period * (1 + k / 400), half_width, period)[2]) for k in range(400))
    )


def fly_figure(
    airframe: str, controller: str, half_width: float, period: float, aero: bool, laps: int
) -> dict[str, Any]:
    """Fly the figure with ``controller`` (``se3``, ``se3_unbounded`` or ``ctbr``, each with ``+drag``: the
    reference's acceleration raised by the rotor drag, :func:`rotor_drag`); the errors over the laps after the
    ramp and the path flown."""
    overrides = [f"vehicle.params={airframe}", f"vehicle.aero={str(aero).lower()}", "flight.max_speed=50"]
    if controller.startswith("se3_unbounded"):
        overrides.append("flight.max_tilt_deg=null")
    world = World(load_config(overrides=overrides), scene="default", render=False)
    world.reset(position=[0.0, 0.0, ALTITUDE], yaw=0.0)
    uav = world.vehicle()
    limits = uav.control_limits()
    tracker = CTBRTracker(
        float(uav.quad_params["mass"]),
        limits["max_thrust"],
        np.array(limits["max_body_rate"]),
        k_att=K_ATT_PER_RATE_GAIN * min(limits["rate_gain"]),
    )
    dt = world.control_period_ns / 1e9
    errors, along, path, low_rotor = [], [], [], 0
    stopped = 0.01 * float(
        uav.quad_params["rotor_speed_max"]
    )  # a rotor this slow gives no thrust to speak of
    wall = time.perf_counter()
    for _ in range(round((laps + 1) * period / dt)):
        t = world.t
        p, v, a, j = figure_eight(t, half_width, period)
        if controller.endswith("+drag"):
            a = a + rotor_drag(uav.quad_params, uav.s, v)
        if controller.startswith("ctbr"):
            s = uav.s
            thrust, rates = tracker.command(s[STATE.x], s[STATE.v], s[STATE.q], (p, v, a, j, 0.0, 0.0))
            uav.rates(thrust, rates)
        else:
            uav.flight.track(t, p, v, a, 0.0, 0.0)
        world.step()
        x = uav.s[STATE.x].copy()
        path.append(x[:2])
        if world.t >= period - 1e-9:
            p_ref, v_ref = figure_eight(world.t, half_width, period)[:2]
            e = x - p_ref
            errors.append(float(np.linalg.norm(e)))
            along.append(float(e @ v_ref / np.linalg.norm(v_ref)))
            low_rotor += int(uav.s[STATE.rotor_speeds].min() < stopped)
    wall = time.perf_counter() - wall
    world.close()
    e_ = np.array(errors)
    w = 2.0 * math.pi / period
    return {
        "airframe": airframe,
        "controller": controller,
        "aero": aero,
        "half_width_m": half_width,
        "period_s": period,
        "peak_speed_m_s": half_width * math.sqrt(2.0) * w,
        "peak_accel_m_s2": peak_accel(half_width, period),
        "rms_error_m": float(np.sqrt(np.mean(e_**2))),
        "max_error_m": float(e_.max()),
        "mean_along_track_error_m": float(np.mean(along)),
        "holds": bool(e_.max() <= HOLD_MAX_ERROR),
        "share_of_periods_a_rotor_near_stop": low_rotor / len(errors),
        "wall_s": wall,
        "path_xy": np.array(path).round(4).tolist(),
    }


# --------------------------------------------------------------------------- latency
class TimedPath(CommandPath):
    """The server's command path, noting the wall time each command's execution returned (its acceptance)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.accepted: list[tuple[str, float]] = []

    def execute(self, request: Any, *args: Any, **kwargs: Any) -> dict[str, Any]:
        reply = super().execute(request, *args, **kwargs)
        self.accepted.append((request.op, time.perf_counter()))
        return reply


class Stepper:
    """A world stepped in real time (one control period per period of wall time) by a thread that records
    every state: (wall time, stamp_ns, packed state)."""

    def __init__(self) -> None:
        self.world = World(scene="default", render=False)
        self.lock = threading.Lock()
        self.path = TimedPath(self.world, self.lock)
        self.server = ApiServer(self.path, port=0)
        self.log: list[tuple[float, int, np.ndarray]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="control-bench-stepper", daemon=True)

    def _run(self) -> None:
        period = self.world.control_period_ns / 1e9
        due = time.perf_counter()
        while not self._stop.is_set():
            due += period
            with self.lock:
                self.world.step()
                self.log.append((time.perf_counter(), self.world.stamp_ns, self.world.vehicle().s.copy()))
            time.sleep(max(0.0, due - time.perf_counter()))

    def __enter__(self) -> Stepper:
        self.server.start()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.server.stop()
        self.world.close()


def _measure(s: np.ndarray, level: str) -> float:
    """The commanded quantity of ``level`` in packed state ``s``: body forward speed, roll rate, roll angle
    or mean rotor speed."""
    if level == "velocity":
        return float(world_to_body(s[STATE.q], s[STATE.v])[0])
    if level == "rates":
        return float(s[STATE.w][0])
    if level == "attitude":
        return quat_to_euler(s[STATE.q])[0]
    return float(np.mean(s[STATE.rotor_speeds]))


def latency_trial(
    rig: Stepper, client: DroneulatorClient, level: str, hover: float, weight: float
) -> dict[str, Any]:
    """Command ``level`` once from hover; the sim and wall time to the first motion and to half-way."""
    client.reset(position=[0.0, 0.0, ALTITUDE], yaw=0.0)
    with rig.lock:
        start = len(rig.log)
    time.sleep(0.3)
    if level == "velocity":
        send, target = (lambda: client.velocity(1.0, 0.0)), 1.0
    elif level == "rates":
        send, target = (lambda: client.rates(weight, [1.0, 0.0, 0.0])), 1.0
    elif level == "attitude":
        send, target = (lambda: client.attitude(weight / math.cos(0.2), roll=0.2, yaw=0.0)), 0.2
    else:
        send, target = (lambda: client.rotors([1.1 * hover] * 4)), 1.1 * hover
    reply = send()
    accepted_wall = rig.path.accepted[-1][1]
    end = time.perf_counter() + 0.4
    while time.perf_counter() < end:  # keep the stream alive past the first motion
        time.sleep(0.02)
        send()
    with rig.lock:
        log = rig.log[start:]
    dt = rig.world.control_period_ns / 1e9
    walls = np.array([r[0] for r in log])
    stamps = np.array([r[1] for r in log])
    states = np.array([r[2] for r in log])
    w = states[:, STATE.w]
    acc = np.vstack([np.zeros((1, 3)), np.diff(states[:, STATE.v], axis=0) / dt])
    before = np.flatnonzero(stamps <= reply["stamp_ns"])
    base = before[-20:]
    w0, a0 = w[base].mean(axis=0), acc[base[1:]].mean(axis=0)
    w_tol = max(5.0 * float(np.ptp(w[base], axis=0).max()), 1e-3)
    a_tol = max(5.0 * float(np.ptp(acc[base[1:]], axis=0).max()), 1e-3)
    after = np.flatnonzero(stamps > reply["stamp_ns"])
    moved = [i for i in after if np.abs(w[i] - w0).max() > w_tol or np.abs(acc[i] - a0).max() > a_tol]
    q0 = _measure(states[base[-1]], level)
    half = [i for i in after if abs(_measure(states[i], level) - q0) >= 0.5 * abs(target - q0)]
    first, mid = moved[0], half[0]
    return {
        "level": level,
        "first_motion_sim_s": float(stamps[first] - reply["stamp_ns"]) / 1e9,
        "first_motion_wall_s": float(walls[first] - accepted_wall),
        "half_way_sim_s": float(stamps[mid] - reply["stamp_ns"]) / 1e9,
        "half_way_wall_s": float(walls[mid] - accepted_wall),
        "trace": [
            (float(stamps[i] - reply["stamp_ns"]) / 1e9, (_measure(states[i], level) - q0) / (target - q0))
            for i in range(max(0, before[-1] - 2), len(log))
        ],
    }


def latency(trials: int) -> dict[str, Any]:
    """Every level ``trials`` times, interleaved, through a real server: the median and largest latency."""
    levels = ("velocity", "rates", "attitude", "rotors")
    with Stepper() as rig, DroneulatorClient(rig.server.url, timeout=5.0) as client:
        q = rig.world.vehicle().quad_params
        weight = float(q["mass"]) * 9.81
        hover = math.sqrt(weight / (4.0 * float(q["k_eta"])))
        runs = [latency_trial(rig, client, level, hover, weight) for _ in range(trials) for level in levels]
    out: dict[str, Any] = {}
    for level in levels:
        mine = [r for r in runs if r["level"] == level]
        row: dict[str, Any] = {"trials": len(mine), "trace": mine[0]["trace"]}
        for key in ("first_motion_sim_s", "first_motion_wall_s", "half_way_sim_s", "half_way_wall_s"):
            values = np.array([r[key] for r in mine])
            row[key] = {"median": float(np.median(values)), "max": float(values.max())}
        out[level] = row
    for level in levels:
        for key in ("first_motion_sim_s", "half_way_sim_s"):
            out[level][f"{key}_vs_velocity"] = out[level][key]["median"] / out["velocity"][key]["median"]
    return out


# --------------------------------------------------------------------------- report
def plot(figures: list[dict[str, Any]], lat: dict[str, Any] | None, headline: tuple[float, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 3 if lat else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 5.0))
    half_width, period = headline
    ref = np.array([figure_eight(period + k * period / 400, half_width, period)[0][:2] for k in range(401)])
    names = {"se3": "SE(3), 45 deg bound", "se3_unbounded": "SE(3), unbounded", "ctbr": "CTBR, flat",
             "ctbr+drag": "CTBR, flat + rotor drag"}  # fmt: skip
    for ax, aero in zip(axes[:2], (True, False), strict=True):
        ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.0, label="reference")
        for r in figures:
            shown = r["controller"] in names and r["airframe"] == "hummingbird"
            if shown and r["aero"] == aero and r["period_s"] == period:
                xy = np.array(r["path_xy"])[round(period / 0.01) :]
                rms, top = r["rms_error_m"], r["max_error_m"]
                label = f"{names[r['controller']]}: RMS {rms:.2f} m, max {top:.2f} m"
                ax.plot(xy[:, 0], xy[:, 1], lw=1.2, label=label)
        ax.set_title(f"Hummingbird, {2 * half_width:.0f} m figure-eight in {period:.0f} s, "
                     f"{'drag on' if aero else 'no drag'}", fontsize=9)  # fmt: skip
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    if lat:
        ax = axes[2]
        for level, row in lat.items():
            tr = np.array(row["trace"])
            ax.plot(tr[:, 0] * 1000, tr[:, 1], marker=".", ms=3, label=f"{level}")
        ax.axhline(0.5, color="grey", lw=0.5)
        ax.set_xlim(-20, 400)
        ax.set_xlabel("sim time since acceptance (ms)")
        ax.set_ylabel("share of the commanded change")
        ax.set_title("step from hover at each level (real server)", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=110)
    print(f"wrote {FIGURE}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--airframes", nargs="+", default=list(FIGURES), choices=list(FIGURES))
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--trials", type=int, default=10, help="latency trials per level")
    ap.add_argument("--no-latency", action="store_true")
    ap.add_argument("--out", help="JSON path (default benchmarks/results/control.json)")
    args = ap.parse_args(argv)

    figures = []
    print(f"{'airframe':12} {'drag':5} {'A m':>4} {'T s':>4} {'a max':>6} {'controller':18} {'RMS m':>6} "
          f"{'max m':>6} {'along m':>7} {'holds':>5} {'rotor stop':>10}")  # fmt: skip
    for airframe in args.airframes:
        half_width, periods = FIGURES[airframe]
        for aero in (True, False):
            for period in periods:
                drag = ("se3_unbounded+drag", "ctbr+drag") if aero and get_params(airframe).get("k_d") else ()
                for controller in ("se3", "se3_unbounded", "ctbr", *drag):
                    r = fly_figure(airframe, controller, half_width, period, aero, args.laps)
                    figures.append(r)
                    print(f"{airframe:12} {str(aero):5} {half_width:4.1f} {period:4.1f} "
                          f"{r['peak_accel_m_s2']:6.1f} {controller:18} {r['rms_error_m']:6.3f} "
                          f"{r['max_error_m']:6.3f} {r['mean_along_track_error_m']:7.3f} {r['holds']!s:>5} "
                          f"{r['share_of_periods_a_rotor_near_stop']:10.2f}", flush=True)  # fmt: skip
    lat = None
    if not args.no_latency:
        lat = latency(args.trials)
        print(f"\n{'level':9} {'first motion sim ms':>20} {'wall ms (median/max)':>21} "
              f"{'half-way sim ms':>16} {'wall ms':>8} {'vs velocity':>12}")  # fmt: skip
        for level, row in lat.items():
            fm, fw, hm, hw = (row[k] for k in ("first_motion_sim_s", "first_motion_wall_s", "half_way_sim_s",
                                               "half_way_wall_s"))  # fmt: skip
            print(f"{level:9} {1e3 * fm['median']:20.1f} {1e3 * fw['median']:10.1f}/{1e3 * fw['max']:<10.1f} "
                  f"{1e3 * hm['median']:16.1f} {1e3 * hw['median']:8.1f} "
                  f"{row['half_way_sim_s_vs_velocity']:12.2f}")  # fmt: skip
    headline = (FIGURES["hummingbird"][0], 4.0)
    if "hummingbird" in args.airframes:
        plot(figures, lat, headline)
    write("control", {
        "hold_max_error_m": HOLD_MAX_ERROR,
        "k_att_per_rate_gain": K_ATT_PER_RATE_GAIN,
        "laps": args.laps,
        "figure_eight": [{k: v for k, v in r.items() if k != "path_xy"} for r in figures],
        "latency": None if lat is None else {k: {f: v for f, v in row.items() if f != "trace"}
                                             for k, row in lat.items()},  # fmt: skip
    }, args.out)  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
