"""``droneulator spray``: a trial written as JSON and a figure, its refusals, and a short coverage mission
whose report balances and doses the row it flew over."""

from __future__ import annotations

import json

import numpy as np
import pytest

from droneulator.cli import main
from droneulator.config import load_config
from droneulator.scenes import get_scene
from droneulator.workflows.spraying.coverage import CoveragePlan, Leg, coverage_plan, first_lanes
from droneulator.workflows.spraying.mission import fly_plan


def test_a_hover_trial_writes_its_json_and_figure(tmp_path, capsys):
    out = tmp_path / "hover"
    code = main(["spray", "--trial", "hover", "--duration", "1", "--out", str(out),
                 "--set", "spray.parcels_per_s=300", "--set", "wind.speed_m_s=2"])  # fmt: skip
    assert code == 0
    data = json.loads((out / "trial_hover.json").read_text())
    assert data["setup"]["wind_m_s"] == 2.0 and data["sprayed_l"] == pytest.approx(1.8 / 60.0, rel=1e-6)
    assert abs(sum(data["ledger"].values()) - 1.0) < 1e-9
    assert max(data["share_of_peak"]) == 1.0 and len(data["collectors_m"]) == len(data["deposit_ul_cm2"])
    assert (out / "trial_hover.png").stat().st_size > 10_000
    assert "hover trial" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--height", "-1"], "--height must be > 0"),
        (["--airframe", "hummingbird"], "invalid choice"),
        (["--set", "spray.nozzles=[]"], "at least one nozzle"),
        (["--set", "weather.relative_humidity=60"], "relative_humidity"),
    ],
)
def test_bad_input_is_one_clear_error(tmp_path, capsys, args, message):
    try:
        code = main(["spray", "--trial", "hover", "--out", str(tmp_path / "x"), *args])
    except SystemExit as e:  # argparse's own refusals
        code = e.code
    assert code == 2
    assert message in capsys.readouterr().err


def test_the_coverage_plan_covers_the_rows():
    scene = get_scene("vineyard", 0)
    plan = coverage_plan(scene, height=1.5, speed=3.0)
    rows = scene.landmarks["row_y"]
    spraying = [leg for leg in plan.legs if leg.spray]
    assert [float(leg.start[1]) for leg in spraying] == pytest.approx(list(rows))
    assert plan.altitude == pytest.approx(max(scene.landmarks["canopy_z"]) + 1.5)
    assert all(leg.start[0] != spraying[0].start[0] for leg in spraying[1::2])  # back and forth
    with pytest.raises(ValueError, match="height and speed"):
        coverage_plan(scene, height=0.0)
    two = first_lanes(plan, 2)  # a short flight: the first two rows and the turn between them
    assert [leg.spray for leg in two.legs] == [True, False, True]
    assert two.target[2:] == pytest.approx((rows[0] - 1.65, rows[1] + 1.65))
    assert first_lanes(plan, 99) is plan


def test_a_short_mission_balances_and_doses_the_row_it_flew():
    cfg = load_config(overrides=["vehicle.params=sprayer10", "scene=vineyard", "spray.parcels_per_s=300"])
    scene = get_scene("vineyard", 0)
    row = float(scene.landmarks["row_y"][2])
    z = max(scene.landmarks["canopy_z"]) + 1.5
    plan = CoveragePlan([Leg(np.array([-17.0, row, z]), np.array([17.0, row, z]), 3.0, True)],
                        (-15.5, 15.5, row - 1.65, row + 1.65), z)  # fmt: skip
    report, spraying = fly_plan(cfg, plan)
    assert report["mass_balance_error"] < 1e-9
    # the row is 31 m of target at 3 m/s with 1.8 L/min (less where it speeds up and slows down)
    assert 0.7 * 0.31 < report["sprayed_l"] <= 0.32
    assert 0.05 < report["canopy_share"] < 0.9
    dose = np.asarray(report["plants"]["dose_ul"]).sum(1)
    plants = np.asarray(report["plants"]["positions"])
    on_row = np.abs(plants[:, 1] - row) < 0.5
    assert dose[on_row].min() > 0.0 and dose[on_row].sum() > 5 * dose[~on_row].sum()
    assert report["tank"]["level_l"] == pytest.approx(10.0 - report["sprayed_l"], abs=1e-9)


def test_a_coverage_plan_uploads_to_the_scripted_px4_as_a_mission():
    """The plan's mission goes up by the mission protocol (MISSION_COUNT, MISSION_REQUEST_INT per item,
    MISSION_ACK) and lands item for item: the spray switched on before each spraying leg and off after
    it, every waypoint back on the plan's ENU position through the site's origin."""
    import math
    import socket

    from pymavlink import mavutil
    from pymavlink.dialects.v20 import common as mavlink
    from scripted_px4 import ScriptedPX4

    from droneulator.config.site import SiteConfig
    from droneulator.frames import geodetic_to_enu
    from droneulator.workflows.spraying.px4_mission import mission_items, upload_mission

    plan = coverage_plan(get_scene("vineyard", 0))
    site = SiteConfig()
    items = mission_items(plan, site)
    sim = socket.create_server(("127.0.0.1", 0))  # the simulator's port: the peer connects and waits
    px4 = ScriptedPX4(sim.getsockname()[1], offboard_port=sim.getsockname()[1])
    conn = None
    try:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{px4._links[0][0].getsockname()[1]}",
                                          source_system=255, source_component=190)  # fmt: skip
        conn.mav = mavlink.MAVLink(conn, 255, 190)  # MAVLink 2 (mission_type)
        upload_mission(conn, items)
        assert px4.error is None
        got = px4.mission
        assert [m.seq for m in got] == list(range(len(items)))
        assert [m.command for m in got] == [i.command for i in items]
        spraying = [leg for leg in plan.legs if leg.spray]
        on_off = [m.param1 for m in got if m.command == mavlink.MAV_CMD_DO_SET_ACTUATOR]
        assert on_off == [1.0, -1.0] * len(spraying)
        waypoints = [m for m in got if m.command == mavlink.MAV_CMD_NAV_WAYPOINT]
        ends = [plan.legs[0].start] + [leg.end for leg in plan.legs]
        for m, p in zip(waypoints, ends, strict=True):
            enu = geodetic_to_enu(m.x * 1e-7, m.y * 1e-7, m.z, site.latitude_deg, site.longitude_deg,
                                  site.altitude_m)  # fmt: skip
            assert np.allclose(enu, p, atol=0.02)
        assert math.isnan(got[1].param4)  # keep the yaw
        # an unsupported command ends the upload with PX4's answer
        bad = [items[0].__class__(mavlink.MAV_CMD_DO_SET_RELAY, mavlink.MAV_FRAME_MISSION, (0.0,) * 4)]
        with pytest.raises(RuntimeError, match="MAV_MISSION_UNSUPPORTED"):
            upload_mission(conn, bad)
        assert len(px4.mission) == len(items)
    finally:
        px4.close()
        sim.close()
        if conn is not None:
            conn.close()


def test_the_spray_follows_px4s_spray_output_with_a_dead_band():
    from droneulator.px4.link import spray_switch

    assert spray_switch(1.0, False) is True and spray_switch(-1.0, True) is False
    assert spray_switch(1.0, True) is None and spray_switch(-1.0, False) is None
    for idle in (0.0, 0.3, -0.3, float("nan")):  # unassigned or not sent: the API's setting stands
        assert spray_switch(idle, True) is None and spray_switch(idle, False) is None


def _free_port(kind: int) -> int:
    import socket

    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _px4_args(tmp_path, sim: int, udp: int, *more: str) -> list[str]:
    return ["spray", "--px4", "--rows", "2", "--px4-port", str(udp), "--set", f"px4.base_port={sim}",
            "--set", "spray.parcels_per_s=300", "--set", "spray.load_l=2", "--out", str(tmp_path / "px4"),
            *more]  # fmt: skip


@pytest.mark.slow
def test_spray_px4_flies_the_plan_as_a_mission_and_sprays_only_its_rows(tmp_path, capsys):
    """`spray --px4` against the scripted PX4: the two-row plan goes up as a mission, PX4 sets its spray
    output from DO_SET_ACTUATOR, flies take-off, both rows and the turn at 3 m/s, RTLs and disarms; the
    spray is on only along the two rows (the tank drops only then) and the deposit lies under them."""
    import socket

    from scripted_px4 import ScriptedPX4

    sim, udp = _free_port(socket.SOCK_STREAM), _free_port(socket.SOCK_DGRAM)
    px4 = ScriptedPX4(sim, udp, params="sprayer10")
    try:
        code = main(_px4_args(tmp_path, sim, udp))
    finally:
        px4.close()
    assert code == 0 and px4.error is None
    out = tmp_path / "px4"
    assert all((out / name).stat().st_size > 1000 for name in
               ("report.json", "deposit_map.png", "canopy_dose.png", "drift_curve.png"))  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    rows = get_scene("vineyard", 0).landmarks["row_y"][:2]
    assert px4.params["PWM_MAIN_FUNC5"] == 301 and not px4.armed and px4.landed
    # the mission's and the link's messages are one sender's: one sequence, nothing counted as lost
    assert px4.rx_missed and not any(px4.rx_missed.values()), px4.rx_missed
    switches = report["px4"]["spray_switches"]
    assert [s["on"] for s in switches] == [True, False, True, False]
    for (on, off), row in zip(zip(switches[::2], switches[1::2], strict=True), rows, strict=True):
        assert abs(on["position"][1] - row) < 1.1 and abs(off["position"][1] - row) < 1.1
        assert abs(off["position"][0] - on["position"][0]) > 33.0  # the row and its run-ins
        assert on["tank_l"] - off["tank_l"] == pytest.approx(1.8 / 60.0 * (off["t"] - on["t"]), rel=0.02)
    assert switches[1]["tank_l"] == pytest.approx(switches[2]["tank_l"], abs=1e-3)  # off in the turn
    assert report["tank"]["level_l"] == pytest.approx(switches[-1]["tank_l"], abs=1e-3)
    assert report["mass_balance_error"] < 1e-9
    dose = np.asarray(report["plants"]["dose_ul"]).sum(1)
    plants = np.asarray(report["plants"]["positions"])
    sprayed = np.min(np.abs(plants[:, 1:2] - np.asarray(rows)[None, :]), axis=1) < 0.5
    assert dose[sprayed].min() > 0.0 and dose[sprayed].sum() > 5 * dose[~sprayed].sum()
    assert report["ground_in_target_l"] > report["ground_off_target_l"]
    assert "sprayed" in capsys.readouterr().out


def test_spray_px4_refusals_are_one_clear_error(tmp_path, capsys):
    """No PX4 within --px4-timeout, a vehicle that is not a sprayer, --px4 with a trial: one line each."""
    import socket

    sim, udp = _free_port(socket.SOCK_STREAM), _free_port(socket.SOCK_DGRAM)
    cases = [
        (["--px4-timeout", "1"], 1, "no PX4 connected to the simulator port"),
        (["--set", "vehicle.params=px4_quadx"], 2, "is not a sprayer"),
        (["--trial", "hover"], 2, "not a --trial"),
    ]
    for more, want, message in cases:
        assert main(_px4_args(tmp_path, sim, udp, *more)) == want
        err = capsys.readouterr().err
        assert message in err and err.count("error:") == 1


def test_spray_px4_reports_a_refused_mission_with_px4s_result(tmp_path, capsys):
    """PX4 with room for fewer items than the mission holds answers MAV_MISSION_NO_SPACE: the command
    stops with it before arming anything."""
    import socket

    from scripted_px4 import ScriptedPX4

    sim, udp = _free_port(socket.SOCK_STREAM), _free_port(socket.SOCK_DGRAM)
    px4 = ScriptedPX4(sim, udp, params="sprayer10", mission_max_items=5)
    try:
        code = main(_px4_args(tmp_path, sim, udp))
    finally:
        px4.close()
    assert code == 1 and not px4.armed
    assert "mission upload refused: MAV_MISSION_NO_SPACE" in capsys.readouterr().err
