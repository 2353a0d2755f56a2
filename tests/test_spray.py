"""The spray model: droplet physics against published data and closed forms, the parcel solver's mass
balance and symmetry, wind and shelter, the spray system's tank and payload, and its refusals."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from droneulator.commands.errors import CommandError
from droneulator.config import NozzleConfig, SprayConfig, WeatherConfig, WindConfig, load_config
from droneulator.spray import kernel
from droneulator.spray.cloud import Domain, Emitter, SprayCloud
from droneulator.spray.droplets import Air, lifetime_s, terminal_velocity, wet_bulb_c
from droneulator.spray.spectrum import Spectrum
from droneulator.spray.system import SpraySystem
from droneulator.spray.targets import SprayTargets
from droneulator.spray.trials import Airframe, drift_curve, effective_swath, swath_cv

#: Gunn & Kinzer (1949) Table 2, diameter (um) -> terminal velocity (m/s), 20 C, 1013 hPa
GUNN_KINZER = {
    200: 0.72,
    300: 1.17,
    400: 1.62,
    500: 2.06,
    600: 2.47,
    700: 2.87,
    800: 3.27,
    900: 3.67,
    1000: 4.03,
}
STD_AIR = WeatherConfig(temperature_c=20.0, relative_humidity=0.5, pressure_hpa=1013.25)


def _mono(d_um: float, speed: float = 0.01, kind: str = "flat_fan") -> NozzleConfig:
    """A nozzle of (nearly) one droplet size."""
    return NozzleConfig(
        dv10_um=0.999 * d_um, dv50_um=d_um, dv90_um=1.001 * d_um, exit_speed_m_s=speed, type=kind
    )


def _cloud(
    nozzle: NozzleConfig,
    wind: WindConfig | None = None,
    weather: WeatherConfig = STD_AIR,
    seed: int = 0,
    **kw,
) -> SprayCloud:
    spray = SprayConfig(nozzles=[nozzle], **kw)
    return SprayCloud(spray, weather, wind or WindConfig(), Domain(-30, 80, -30, 30, 30), seed=seed)


def _hover(
    cloud: SprayCloud,
    nozzle: NozzleConfig,
    height: float,
    seconds: float,
    litres_s: float,
    params="sprayer10",
):
    frame = Airframe.of(params, SprayConfig())
    pos = np.array([0.0, 0.0, height])
    for _ in range(round(seconds / cloud.dt)):
        cloud.step([frame.emitter(pos, np.zeros(3), np.zeros(3), [(nozzle, litres_s * cloud.dt)])])
    cloud.settle([frame.emitter(pos, np.zeros(3), np.zeros(3), [])], limit_s=90.0)
    return frame


def test_terminal_velocity_against_gunn_and_kinzer():
    air = Air.of(STD_AIR)
    for d, v in GUNN_KINZER.items():
        assert terminal_velocity(d * 1e-6, air) == pytest.approx(v, rel=0.05), d
    # below 200 um G&K's entries sit above every rigid-sphere drag law; Beard (1976)'s fit gives 0.2496 m/s
    assert terminal_velocity(100e-6, air) == pytest.approx(0.2496, rel=0.02)
    # Stokes' law where it holds (Re << 1)
    stokes = (998.2 - air.density) * 9.81 * (30e-6) ** 2 / (18 * air.viscosity)
    assert terminal_velocity(30e-6, air) == pytest.approx(stokes, rel=0.01)


def test_a_droplet_in_still_air_falls_at_its_terminal_velocity():
    cloud = _cloud(_mono(300.0), parcels_per_s=100.0)
    cloud.release(Emitter(np.array([0.0, 0.0, 20.0]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                          [(cloud.config.nozzles[0], 1e-6)]), 0.01)  # fmt: skip
    for _ in range(300):
        cloud.step([])
    alive = cloud.n[: cloud.count] > 0
    vz = cloud.v[: cloud.count][alive, 2]
    # the droplets shrink a little as they evaporate: compare with the velocity at their present size
    expect = np.array([terminal_velocity(d, cloud.air, 1000.0) for d in cloud.d[: cloud.count][alive]])
    assert np.allclose(-vz, expect, rtol=2e-3)
    assert np.allclose(cloud.v[: cloud.count][alive, :2], 0.0, atol=1e-9)


def test_evaporation_follows_the_d2_law():
    weather = WeatherConfig(temperature_c=30.0, relative_humidity=0.5)
    air = Air.of(weather)
    assert weather.temperature_c - wet_bulb_c(30.0, 0.5) == pytest.approx(7.7, abs=0.1)  # Stull (2011)
    d0 = 40e-6
    cloud = _cloud(_mono(40.0), weather=weather, parcels_per_s=100.0, min_diameter_um=1.0)
    cloud.release(Emitter(np.array([0.0, 0.0, 25.0]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                          [(cloud.config.nozzles[0], 1e-6)]), 0.01)  # fmt: skip
    t = cloud.settle([], limit_s=60.0)
    # the still-air lifetime d^2 / lambda, a little shorter for the ventilation of the falling droplet
    expect = lifetime_s(d0, air)
    assert 0.9 * expect < t <= expect
    ledger = cloud.ledger_now()
    assert ledger.parts["evaporated"] == pytest.approx(ledger.sprayed, rel=1e-9)


def test_hover_in_calm_air_deposits_symmetrically_and_balances_its_mass():
    nozzle = dataclasses.replace(_mono(200.0, 15.0), dv10_um=100.0, dv90_um=350.0)
    cloud = _cloud(nozzle, parcels_per_s=3000.0)
    _hover(cloud, nozzle, 2.5, 1.5, 0.02)
    ledger = cloud.ledger_now()
    assert abs(ledger.accounted - ledger.sprayed) <= 1e-6 * ledger.sprayed
    assert ledger.parts["airborne"] == 0.0 and ledger.parts["ground"] > 0.8 * ledger.sprayed
    g = cloud.ground_deposit()
    xs = cloud.ground_origin[0] + (np.arange(g.shape[0]) + 0.5) * cloud.ground_cell
    ys = cloud.ground_origin[1] + (np.arange(g.shape[1]) + 0.5) * cloud.ground_cell
    cx, cy = (g.sum(1) @ xs) / g.sum(), (g.sum(0) @ ys) / g.sum()
    assert abs(cx) < 0.1 and abs(cy) < 0.1
    # left and right of the vehicle (the fan's plane) alike, to the parcels' sampling noise
    left, right = g[:, ys < 0].sum(), g[:, ys > 0].sum()
    assert abs(left - right) / (left + right) < 0.05


def _downwind_centroid(d_um: float, wind: float) -> float:
    nozzle = _mono(d_um, 10.0)
    humid = WeatherConfig(temperature_c=15.0, relative_humidity=0.9)  # the fine droplets last
    cloud = _cloud(nozzle, WindConfig(speed_m_s=wind, turbulence="none"), humid, parcels_per_s=400.0)
    _hover(cloud, nozzle, 2.5, 1.0, 0.01)
    g = cloud.ground_deposit().sum(1)
    xs = cloud.ground_origin[0] + (np.arange(len(g)) + 0.5) * cloud.ground_cell
    return float(g @ xs / g.sum())


def test_wind_moves_the_deposit_downwind_more_for_finer_droplets():
    calm = _downwind_centroid(150.0, 0.0)
    fine, coarse = _downwind_centroid(120.0, 4.0), _downwind_centroid(400.0, 4.0)
    assert abs(calm) < 0.15  # the wall jet spreads 400 parcels over metres: the centroid's noise is ~0.1 m
    assert fine > coarse > calm + 0.05
    assert fine > 2.0 * coarse


def test_a_row_behind_another_is_sheltered():
    from droneulator.scenes import get_scene

    scene = get_scene("vineyard", 0)
    targets = SprayTargets.of(scene)
    rows = np.asarray(scene.landmarks["row_y"])
    # fine droplets released upwind (south) of the first row, the wind blowing north across the rows
    wind = WindConfig(speed_m_s=3.0, direction_deg=180.0, turbulence="none")
    spray = SprayConfig(nozzles=[_mono(60.0, 0.01)], parcels_per_s=1500.0)

    def row_doses(leaf: np.ndarray) -> np.ndarray:
        tg = dataclasses.replace(targets, leaf=leaf)
        cloud = SprayCloud(spray, STD_AIR, wind, Domain(-40, 40, -40, 40, 20), tg)
        y0 = rows[0] - 1.2
        for k in range(100):
            pos = np.array([-10.0 + 0.2 * k, y0, 1.6])
            cloud.release(Emitter(pos, np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                                  [(spray.nozzles[0], 1e-5)]), 0.01)  # fmt: skip
            cloud.step([])
        cloud.settle([], limit_s=40.0)
        dose = cloud.plant_dose().sum(1)
        py = targets.plants[:, 1]
        return np.array([dose[np.abs(py - y) < 0.5].sum() for y in rows])

    full = row_doses(targets.leaf)
    assert full[0] > full[1] > full[2]
    # take the first row's leaves away: the second row gets what the first caught
    first = (
        np.abs((targets.origin[1] + (np.arange(targets.leaf.shape[1]) + 0.5) * targets.cell) - rows[0]) < 0.6
    )
    bare = targets.leaf.copy()
    bare[:, first, :] = 0.0
    opened = row_doses(bare)
    assert opened[0] == 0.0 and opened[1] > 1.5 * full[1]


def test_targets_hold_the_vineyards_leaves_by_plant_and_third():
    from droneulator.scenes import get_scene

    scene = get_scene("vineyard", 0)
    tg = SprayTargets.of(scene)
    assert tg.plant_count == len(scene.landmarks["trunks"])
    lai = tg.leaf_area.sum() / (30.0 * 3.3 * len(scene.landmarks["row_y"]))
    assert 0.5 < lai < 3.0  # a vineyard's leaf area index
    z = tg.origin[2] + (np.arange(tg.leaf.shape[2]) + 0.5) * tg.cell
    lo, hi = scene.landmarks["canopy_z"]
    leafy_z = z[np.nonzero(tg.leaf.any(axis=(0, 1)))[0]]
    assert leafy_z.min() > lo - 0.5 and leafy_z.max() < hi + 0.5
    assert set(np.unique(tg.third[tg.third >= 0])) == {0, 1, 2}
    assert (tg.wood > 0).sum() > 0 and set(np.unique(tg.wood_class[tg.wood_class >= 0])) >= {0, 2}


def test_results_do_not_depend_on_the_thread_count(monkeypatch):
    nozzle = _mono(250.0, 5.0)
    wind = WindConfig(speed_m_s=3.0)

    def run() -> np.ndarray:
        cloud = _cloud(nozzle, wind, parcels_per_s=1000.0, seed=0)
        _hover(cloud, nozzle, 2.0, 0.5, 0.01)
        return cloud.ground_deposit()

    serial = run()
    monkeypatch.setattr(kernel, "PARALLEL_PARCELS", 1)
    assert np.array_equal(run(), serial)


def test_spectrum_fits_its_percentiles():
    s = Spectrum.fit(100e-6, 200e-6, 400e-6)
    assert s.dv(0.5) == pytest.approx(200e-6)
    assert s.dv(0.1) * s.dv(0.9) == pytest.approx(100e-6 * 400e-6)
    assert s.volume_below(200e-6) == pytest.approx(0.5)
    d = s.sample(np.random.default_rng(0), 200_000)
    assert np.median(d) == pytest.approx(200e-6, rel=0.01)
    with pytest.raises(ValueError, match="Dv0.1 < Dv0.5"):
        Spectrum.fit(200e-6, 100e-6, 400e-6)


def test_swath_rules_on_a_known_pattern():
    xs = np.arange(-20.0, 20.0, 0.05)
    tri = np.maximum(1.0 - np.abs(xs) / 3.0, 0.0)  # a triangle 6 m wide: flat when overlapped at 3 m
    assert swath_cv(xs, tri, 3.0) < 0.01
    assert swath_cv(xs, tri, 6.0) > 0.5
    assert 3.0 <= effective_swath(xs, tri) < 6.0
    out = drift_curve(xs, np.exp(-np.abs(xs)), 3.0)
    assert out["drift_percent"] == sorted(out["drift_percent"], reverse=True)


def test_the_tank_empties_at_the_pumps_rate_and_the_vehicle_gets_lighter():
    from droneulator.spray.spraying import Spraying
    from droneulator.world.world import World

    cfg = load_config(overrides=["vehicle.params=sprayer10", "scene=default", "spray.parcels_per_s=200"])
    world = World(cfg, render=False)
    spraying = Spraying(world, targets=SprayTargets.empty())
    v = world.vehicle()
    full = 16.0 + cfg.spray.load_l
    assert v.quad_params["mass"] == pytest.approx(full)
    v.takeoff(3.0)
    for _ in range(500):
        world.step()
        spraying.step()
    system = spraying.system(None)
    system.set(1.0)
    seconds = 6.0
    for _ in range(round(seconds / 0.01)):
        world.step()
        spraying.step()
    assert system.config.flow_l_min == pytest.approx(1.8)  # the sprayer10's own four flat fans
    flow = system.config.flow_l_min / 60.0
    assert system.level_l == pytest.approx(cfg.spray.load_l - flow * seconds, rel=1e-6)
    assert v.quad_params["mass"] == pytest.approx(16.0 + system.level_l, abs=0.011)
    assert world._gains[0][0] == pytest.approx(v.quad_params["mass"])  # the controller's feed-forward mass
    assert abs(v.state.position[2] - 3.0) < 0.1  # it holds its height as it grows lighter
    assert spraying.cloud.sprayed * 1000.0 == pytest.approx(flow * seconds, rel=1e-6)


def test_spray_system_refusals_leave_it_as_it_was():
    system = SpraySystem(SprayConfig(load_l=0.001))
    for rate, code in ((1.5, "out_of_range"), (-0.1, "out_of_range"), (math.nan, "invalid_argument"),
                       (True, "invalid_argument")):  # fmt: skip
        with pytest.raises(CommandError) as err:
            system.set(rate)
        assert err.value.code == code
    with pytest.raises(CommandError, match="no nozzle boom"):
        system.set(1.0, ["boom"])
    assert system.rate == 0.0
    system.set(1.0, ["left"])
    assert system.draw(1.0) == {"left": pytest.approx(0.001)}  # the last drop, from the open nozzle
    assert system.level_l == 0.0 and not system.on
    with pytest.raises(CommandError) as err:
        system.set(0.5)
    assert err.value.code == "tank_empty"
    with pytest.raises(CommandError):
        system.refill(99.0)
    system.refill()
    assert system.level_l == pytest.approx(0.001)


def test_bad_spray_config_is_a_clear_error():
    with pytest.raises(ValueError, match="spectrum must be an ASABE class"):
        NozzleConfig(spectrum="XXL")
    with pytest.raises(ValueError, match="dv10_um < dv50_um < dv90_um"):
        NozzleConfig(dv10_um=300.0, dv50_um=200.0, dv90_um=400.0)
    with pytest.raises(ValueError, match="load_l"):
        SprayConfig(tank_l=10.0, load_l=12.0)
    with pytest.raises(ValueError, match="relative_humidity"):
        WeatherConfig(relative_humidity=60.0)
    with pytest.raises(ValueError, match="at least one nozzle"):
        SprayConfig(nozzles=[])


def test_spray_conditions_are_drawn_and_applied():
    from droneulator.config import RandomizeConfig

    r = RandomizeConfig(enabled=True, droplet_scale=(0.5, 0.5), temperature_c=(30.0, 30.0))
    draw = r.draw(np.random.default_rng(3))
    before = RandomizeConfig(enabled=True).draw(np.random.default_rng(3))
    assert draw.wind == before.wind and draw.vegetation == before.vegetation  # earlier draws unchanged
    cfg = r.apply(load_config(), draw)
    assert cfg.spray.droplet_scale == 0.5 and cfg.weather.temperature_c == 30.0
    nozzle = _mono(200.0)
    cloud = SprayCloud(
        dataclasses.replace(SprayConfig(nozzles=[nozzle]), droplet_scale=cfg.spray.droplet_scale),
        cfg.weather, WindConfig(), Domain(-5, 5, -5, 5, 10),
    )  # fmt: skip
    cloud.release(Emitter(np.array([0.0, 0.0, 2.0]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                          [(nozzle, 1e-6)]), 0.01)  # fmt: skip
    assert np.allclose(cloud.d[: cloud.count], 100e-6, rtol=2e-3)
    with pytest.raises(ValueError, match="droplet_scale"):
        RandomizeConfig(droplet_scale=(2.0, 1.0))


def test_the_spray_reward_pays_for_the_canopy_and_charges_drift():
    from droneulator.scenes import get_scene
    from droneulator.spray.reward import SprayReward

    scene = get_scene("vineyard", 0)
    targets = SprayTargets.of(scene)
    row = float(scene.landmarks["row_y"][2])
    target = (-15.0, 15.0, row - 1.65, row + 1.65)

    def episode(wind: float, y: float) -> float:
        nozzle = _mono(150.0, 5.0)
        cloud = SprayCloud(SprayConfig(nozzles=[nozzle], parcels_per_s=2000.0), STD_AIR,
                           WindConfig(speed_m_s=wind, direction_deg=180.0), Domain(-40, 40, -40, 40, 20),
                           targets)  # fmt: skip
        reward = SprayReward(target=target)
        reward.reset(cloud)
        total = 0.0
        for k in range(100):
            pos = np.array([-10.0 + 0.2 * k, y, 2.4])
            cloud.release(Emitter(pos, np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                                  [(nozzle, 1e-4)]), 0.01)  # fmt: skip
            cloud.step([])
            total += reward(cloud)
        cloud.settle([], limit_s=60.0)
        total += reward(cloud)
        t = reward.totals(cloud)
        assert sum(t[:4]) == pytest.approx(t[4], rel=1e-6)  # every litre scored once
        return total / t[4]

    over_the_row = episode(0.0, row)
    # north of the last row, the wind blowing north: nothing below but the ground off the target
    beside_in_wind = episode(5.0, float(scene.landmarks["row_y"][-1]) + 4.0)
    assert over_the_row > 0.0 > beside_in_wind


def test_a_trailing_vortex_pair_blows_down_between_its_cores_and_out_beside_them():
    row = kernel.vortex_row(np.zeros(3), np.array([5.0, 0.0]), 255.0, 1.9, 2.2, 2.5)
    assert row is not None and 0.0 < row[13] < 1.0  # it shares the wake with the jets at 5 m/s
    out = np.zeros(kernel.AIR_SIZE)
    none = np.zeros((0, kernel.ROTOR_SIZE))
    wind = kernel.wind_row(WindConfig())

    def at(x: float, y: float, z: float) -> np.ndarray:
        kernel.air_velocity(x, y, z, wind, none, row[None, :], out)
        return out[3:6].copy()

    assert at(-3.0, 0.0, 2.0)[2] < -0.5  # behind the vehicle, down between the cores
    assert np.allclose(at(3.0, 0.0, 2.0), 0.0)  # nothing ahead of it
    half = row[7]
    left, right = at(-3.0, 2.0 * half, 0.3), at(-3.0, -2.0 * half, 0.3)
    assert left[1] > 0.0 > right[1]  # beside the cores near the ground, out to either side
    assert left[1] == pytest.approx(-right[1])


def test_a_droplet_dries_to_its_non_volatile_residue_and_flies_on():
    weather = WeatherConfig(temperature_c=30.0, relative_humidity=0.5)
    cloud = _cloud(_mono(40.0), weather=weather, parcels_per_s=100.0, min_diameter_um=1.0,
                   nonvolatile_fraction=0.01)  # fmt: skip
    cloud.release(Emitter(np.array([0.0, 0.0, 25.0]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros((0, 8)),
                          [(cloud.config.nozzles[0], 1e-6)]), 0.01)  # fmt: skip
    for _ in range(round(2.0 * lifetime_s(40e-6, Air.of(weather)) / cloud.dt)):
        cloud.step([])
    alive = cloud.n[: cloud.count] > 0
    assert alive.all()  # still airborne: residues of 40 * 0.01^(1/3) = 8.6 um fall at 2 mm/s
    assert np.allclose(cloud.d[: cloud.count], 40e-6 * 0.01 ** (1 / 3), rtol=2e-3)
    ledger = cloud.ledger_now()
    assert ledger.parts["evaporated"] == pytest.approx(0.99 * ledger.sprayed, rel=2e-3)
    assert ledger.accounted == pytest.approx(ledger.sprayed, rel=1e-9)
    with pytest.raises(ValueError, match="nonvolatile_fraction"):
        SprayConfig(nonvolatile_fraction=1.0)


def test_a_rotor_wake_turns_into_a_wall_jet_at_the_ground():
    """Under a hovering rotor (thrust axis up) the air at the ground flows out, not down; above it, down."""
    rows = np.zeros((1, kernel.ROTOR_SIZE))
    rows[0, :12] = [0.0, 0.0, 2.5, 0.0, 0.0, 1.0, 7.0, 0.4, 0.0, 0.0, 0.0, 1.0]
    rows[:, 10] = kernel.reach(rows)
    kernel.ground_jets(rows)
    out = np.empty(kernel.AIR_SIZE)
    wind = kernel.wind_row(WindConfig(speed_m_s=0.0))
    none = np.zeros((0, kernel.VORTEX_SIZE))
    kernel.air_velocity(0.0, 0.0, 1.5, wind, rows, none, out)
    assert out[5] < -5.0
    kernel.air_velocity(1.0, 0.0, 0.05, wind, rows, none, out)
    assert out[3] > 3.0 and abs(out[5]) < 0.2 * out[3]


def test_a_trials_rotors_have_the_airframes_disks():
    spray = SprayConfig()
    frame = Airframe.of("sprayer40", spray)
    rows = frame.emitter(np.array([0.0, 0.0, 2.5]), np.zeros(3), np.zeros(3), []).rotors
    assert rows[:, 7].sum() == pytest.approx(4.0 * math.pi * 0.6858**2, rel=1e-3)
