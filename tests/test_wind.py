"""The wind field against its definitions: Dryden's spectra and variances (MIL-F-8785C), the log
profile, 1-cosine gusts, the canopy's shelter; and the wind a flying vehicle feels, sets and publishes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from droneulator.commands.errors import CommandError
from droneulator.commands.ops import execute, make_request
from droneulator.config import VehicleSpec, WindConfig, load_config
from droneulator.scenes.collision import Box, build_collision
from droneulator.state import STATE
from droneulator.wind.field import WindField
from droneulator.world.world import World

FT = 0.3048


def _dryden_reference(
    h_m: float, w20: float, V: float, f_hz: np.ndarray
) -> dict[str, tuple[float, np.ndarray]]:
    """MIL-F-8785C low altitude, written out here from the standard in its own units (ft, ft/s):
    per axis the intensity (m/s) and the one-sided PSD in (m/s)^2/Hz at ``f_hz`` for airspeed ``V``."""
    h = h_m / FT
    sw = 0.1 * w20 / FT
    su = sw / (0.177 + 0.000823 * h) ** 0.4
    Lu = h / (0.177 + 0.000823 * h) ** 1.2
    Lw = h
    Vf = V / FT
    omega = 2 * np.pi * f_hz
    out = {}
    for axis, sigma, L in (("u", su, Lu), ("v", su, Lu), ("w", sw, Lw)):
        Om = omega / Vf  # spatial frequency, rad/ft
        if axis == "u":
            phi = sigma**2 * 2 * L / np.pi / (1 + (L * Om) ** 2)
        else:
            phi = sigma**2 * L / np.pi * (1 + 3 * (L * Om) ** 2) / (1 + (L * Om) ** 2) ** 2
        # Phi(Omega) dOmega = Phi(omega) domega = S(f) df: S(f) = Phi(Omega) * 2 pi / V; ft^2 -> m^2
        out[axis] = (sigma * FT, phi * 2 * np.pi / Vf * FT**2)
    return out


def _run(field: WindField, steps: int, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
    return np.stack([field.update(pos, vel) for _ in range(steps)])


def test_dryden_turbulence_matches_the_standards_spectra_and_variances():
    """Vehicles flying at 10 m/s into a 5 m/s wind 10 ft up: each axis' variance within 10 % of the
    standard's and its power spectrum within 10 % of Dryden's in every band from 0.1 to 10 Hz."""
    n, dt, steps = 96, 0.01, 12_000
    h, w20, ground_speed = 10 * FT, 5.0, -10.0
    cfg = WindConfig(speed_m_s=w20, direction_deg=270.0, profile="uniform")
    field = WindField(cfg, n, dt, seed=4)
    pos = np.tile([0.0, 0.0, h], (n, 1))
    vel = np.tile([ground_speed, 0.0, 0.0], (n, 1))
    wind = _run(field, steps, pos, vel)
    turb = wind - np.array([w20, 0.0, 0.0])  # the mean is known: the variance about it is unbiased
    ref = _dryden_reference(h, w20, w20 - ground_speed, np.array([1.0]))
    for k, axis in enumerate("uvw"):
        sigma = ref[axis][0]
        assert np.mean(turb[:, :, k] ** 2) == pytest.approx(sigma**2, rel=0.1), axis
    f, psd = signal.welch(turb, fs=1 / dt, nperseg=4096, axis=0, detrend=False)
    psd = psd.mean(axis=1)  # over the vehicles
    edges = np.geomspace(0.1, 10.0, 9)
    for k, axis in enumerate("uvw"):
        want = _dryden_reference(h, w20, w20 - ground_speed, f)[axis][1]
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            band = (f >= lo) & (f < hi)
            ratio = psd[band, k].sum() / want[band].sum()
            assert ratio == pytest.approx(1.0, abs=0.1), f"{axis} {lo:.2f}-{hi:.2f} Hz: {ratio:.3f}"


def test_mean_wind_follows_the_log_profile_and_direction():
    """Without turbulence the wind is W20 ln(h/z0)/ln(20 ft/z0) along the direction it blows to."""
    cfg = WindConfig(speed_m_s=4.0, direction_deg=225.0, turbulence="none", roughness_m=0.05)
    heights = np.array([0.02, 1.0, 20 * FT, 30.0])
    field = WindField(cfg, len(heights), 0.01)
    pos = np.column_stack([np.zeros(4), np.zeros(4), heights])
    wind = field.update(pos, np.zeros((4, 3)))
    speed = 4.0 * np.maximum(np.log(np.maximum(heights, 0.05) / 0.05), 0) / math.log(20 * FT / 0.05)
    from_sw = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)  # from the south-west: towards north-east
    np.testing.assert_allclose(wind, speed[:, None] * from_sw, atol=1e-12)
    assert wind[2] == pytest.approx(4.0 * from_sw)  # W20 is the wind 20 ft up


def test_gusts_are_one_minus_cosine_pulses_arriving_at_the_configured_rate():
    dt, steps, n = 0.01, 20_000, 4
    cfg = WindConfig(
        gust_speed_m_s=3.0, gust_interval_s=4.0, gust_duration_s=1.5, turbulence="none", profile="uniform"
    )
    field = WindField(cfg, n, dt, seed=1)
    speed = _run(field, steps, np.tile([0.0, 0.0, 5.0], (n, 1)), np.zeros((n, 3)))[:, :, 0]
    assert speed.min() >= 0.0 and speed.max() == pytest.approx(3.0, abs=0.01)
    starts = []
    for k in range(n):
        on = speed[:, k] > 0
        rises = np.flatnonzero(on[1:] & ~on[:-1]) + 1
        falls = np.flatnonzero(~on[1:] & on[:-1]) + 1
        for a, b in zip(rises, falls, strict=False):
            assert (b - a) * dt == pytest.approx(1.5, abs=2 * dt)  # each gust lasts its duration
            t = np.arange(a, b) * dt - (a - 1) * dt
            # the shape, up to the step that the gust's start falls in (its steepest slope is pi A / D)
            slope = np.pi * 3.0 / 1.5
            np.testing.assert_allclose(
                speed[a:b, k], 1.5 * (1 - np.cos(2 * np.pi * t / 1.5)), atol=slope * dt
            )
        starts.append(len(rises))
    expected = n * steps * dt / (4.0 + 1.5)  # Poisson gaps of 4 s mean between gusts of 1.5 s
    assert sum(starts) == pytest.approx(expected, rel=0.2)


def test_the_canopy_shelters_the_wind_and_it_recovers_behind_the_row():
    """A 1 m thick, 2 m high hedgerow across a westerly wind: inside and just downwind the wind is
    weaker, recovering with distance; above the row and upwind of it the full wind blows."""
    row = Box(np.array([0.0, 0.0, 1.0]), np.array([0.5, 20.0, 1.0]))
    col = build_collision([row], np.array([-30.0, -25.0, 0.0]), np.array([30.0, 25.0, 6.0]))
    cfg = WindConfig(speed_m_s=5.0, turbulence="none", profile="uniform")
    xs = np.array([-3.0, 0.0, 1.0, 3.0, 8.0, 20.0])
    pos = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 1.5)])
    field = WindField(cfg, len(xs), 0.01, collision=col)
    factor = field.shelter_factor(pos)
    assert factor[0] == pytest.approx(1.0)  # upwind of the row
    assert factor[1] < 0.85  # inside it
    assert np.all(np.diff(factor[2:]) > 0) and factor[2] < 0.7  # downwind: recovering
    assert factor[-1] > 0.95
    # the same points above the row feel the open wind
    above = pos + [0.0, 0.0, 2.0]
    np.testing.assert_allclose(field.shelter_factor(above), 1.0)
    # the field applies it: a vehicle leaving the row's lee feels the wind rise
    wind = field.update(pos, np.zeros_like(pos))
    np.testing.assert_allclose(wind[:, 0], 5.0 * factor)
    off = WindField(dataclasses.replace(cfg, shelter=False), len(xs), 0.01, collision=col)
    np.testing.assert_allclose(off.update(pos, np.zeros_like(pos))[:, 0], 5.0)


def test_field_is_seeded():
    cfg = WindConfig(speed_m_s=6.0, gust_speed_m_s=2.0)
    pos, vel = np.tile([0.0, 0.0, 3.0], (3, 1)), np.zeros((3, 3))
    a = _run(WindField(cfg, 3, 0.01, seed=7), 500, pos, vel)
    b = _run(WindField(cfg, 3, 0.01, seed=7), 500, pos, vel)
    c = _run(WindField(cfg, 3, 0.01, seed=8), 500, pos, vel)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert not np.allclose(a[:, 0], a[:, 1])  # every vehicle its own turbulence


def test_bad_wind_settings_are_clear_errors():
    for field, value in (
        ("speed_m_s", -1.0),
        ("direction_deg", math.nan),
        ("profile", "power"),
        ("turbulence", "karman"),
        ("gust_duration_s", 0.0),
        ("roughness_m", -0.1),
    ):
        with pytest.raises(ValueError, match=f"wind.{field}"):
            WindConfig(**{field: value})
    with pytest.raises(ValueError, match="two wind models"):
        load_config(overrides=["vehicle.wind=constant", "wind.speed_m_s=3"])


def test_hover_in_gusty_wind_holds_position_and_reports_the_wind():
    """A hover 3 m up in a 5 m/s gusty wind: the vehicle feels the wind (its state and the wind row
    agree), is pushed off by it, and the controller holds it within a metre."""
    cfg = load_config(overrides=["wind.speed_m_s=5", "wind.gust_speed_m_s=2", "wind.gust_interval_s=3"])
    world = World(cfg, scene="default", render=False)
    v = world.vehicle()
    start = v.state.position + [0.0, 0.0, 3.0]
    world.reset(position=start)
    errors, winds = [], []
    for _ in range(1500):
        world.step()
        st = v.state
        errors.append(np.linalg.norm(st.position - start))
        winds.append(st.wind)
        np.testing.assert_array_equal(st.wind, world.states[0, 0, STATE.wind])
    winds_a = np.array(winds)
    assert np.mean(winds_a[:, 0]) > 2.5 and np.std(winds_a[:, 0]) > 0.3  # a gusty wind blows east
    errors_a = np.array(errors[300:])
    assert 0.02 < np.sqrt(np.mean(errors_a**2)) < 1.0
    assert v.state.to_dict()["wind"] == pytest.approx(list(winds_a[-1]))


def test_a_goto_in_wind_arrives_within_the_acceptance_radius_and_in_calm_air_settled():
    """This controller has no integral term: a steady wind holds it off its target, so the tight arrival
    criterion never holds; the goto arrives, unsettled, once it is within flight.acceptance_radius
    flight.arrive_timeout_s after its reference ended. In calm air it settles as before."""
    for speed, settled in ((0.0, True), (5.0, False)):
        cfg = load_config(overrides=[f"wind.speed_m_s={speed}", "wind.turbulence=none", "wind.shelter=false"])
        world = World(cfg, scene="default", render=False)
        v = world.vehicle()
        start = v.state.position + [0.0, 0.0, 3.0]
        world.reset(position=start)
        target = start + [2.0, 0.0, 0.0]
        duration = v.goto(target)
        events = []
        for _ in range(round((duration + 10.0) * cfg.vehicle.control_hz)):
            events += [e for e in world.step().events if e.type == "arrived"]
            if events:
                break
        (arrived,) = events
        error = np.linalg.norm(np.array(arrived.data["position"]) - target)
        assert arrived.data["settled"] is settled
        if settled:
            assert error < cfg.flight.arrive_tolerance and arrived.t < duration + 1.0
        else:  # pushed off by the steady wind (from the west: downwind is +x), and accepted on time
            assert cfg.flight.arrive_tolerance < error <= cfg.flight.acceptance_radius
            assert arrived.t == pytest.approx(duration + cfg.flight.arrive_timeout_s, abs=0.02)
        assert v.mode.value == "hold"
    with pytest.raises(ValueError, match="flight.acceptance_radius must be a positive number"):
        load_config(overrides=["flight.acceptance_radius=0"])


def test_set_wind_changes_the_wind_of_one_vehicle_or_all_and_rejects_bad_values():
    cfg = load_config()
    cfg.vehicles = [VehicleSpec(name="a"), VehicleSpec(name="b")]
    world = World(cfg, scene="default", render=False)
    world.step()
    assert np.all(world.states[0, :, STATE.wind] == 0.0)

    def run(**args):
        try:
            reply = execute(world, make_request("set_wind", args, 1))
        except CommandError as e:  # rejected by the op table's rules
            return {"ok": False, "error": {"code": e.code, "message": e.message}}
        return reply

    out = run(speed=4.0, turbulence=False, vehicle="b", shelter=False)
    assert out["ok"], out
    assert out["result"]["wind"]["speed_m_s"] == 4.0 and out["result"]["wind"]["turbulence"] == "none"
    beside_a = world.vehicle("a").state.position + [4.0, 0.0, 20 * FT]  # out of a's way: no wake
    world.reset(position=beside_a, vehicle="b")
    world.step()
    wind = world.states[0, :, STATE.wind]
    np.testing.assert_allclose(wind[0], 0.0)
    np.testing.assert_allclose(wind[1], [4.0, 0.0, 0.0], atol=1e-9)  # from the west, 20 ft up
    assert run(speed=2.0, direction_deg=180.0, turbulence=False, shelter=False)["ok"]
    world.step()
    np.testing.assert_allclose(
        world.states[0, :, STATE.wind][1], [0.0, 2.0, 0.0], atol=1e-3
    )  # from the south
    for bad, code in (
        ({"speed": -1.0}, "out_of_range"),
        ({"gust_duration": 0.0}, "out_of_range"),
        ({"vehicle": "c"}, "invalid_argument"),
        ({"turbulence": "yes"}, "invalid_argument"),
    ):
        reply = run(**bad)
        assert not reply["ok"] and reply["error"]["code"] == code, (bad, reply)
    world.step()  # the world goes on


def test_many_worlds_fly_each_in_its_own_wind():
    """Domain randomisation's hook: one calm world hovers still, two worlds in a 6 m/s wind each feel
    their own turbulence and are pushed off their hover."""
    from droneulator.world import World

    worlds = World(load_config(scene="default"), render=False, worlds=3)
    start = worlds.scene.spawn_position + [0.0, 0.0, 3.0]
    worlds.place(None, np.tile(start, (3, 1)), np.zeros(3))
    worlds.set_wind_rows([WindConfig(), WindConfig(speed_m_s=6.0), WindConfig(speed_m_s=6.0)])
    for _ in range(60):
        worlds.step_frame()
    wind = worlds.states[:, 0, STATE.wind]
    np.testing.assert_array_equal(wind[0], 0.0)
    assert wind[1, 0] > 2.0 and wind[2, 0] > 2.0 and not np.allclose(wind[1], wind[2])
    drift = np.linalg.norm(worlds.states[:, 0, STATE.x] - start, axis=1)
    assert drift[0] < 1e-3 and drift[1] > 0.02 and drift[2] > 0.02
    profile = World(load_config(overrides=["vehicle.wind=constant"]), render=False, worlds=2)
    with pytest.raises(ValueError, match="RotorPy"):
        profile.step_frame()
