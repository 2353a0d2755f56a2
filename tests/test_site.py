"""The ``site`` section: where the world origin lies, read by the GPS, barometer and magnetometer; the old
``px4.home_*`` keys still load, with a warning."""

import contextlib
import json
import logging

import numpy as np
import pytest

from droneulator import frames as F
from droneulator.cli import main
from droneulator.config import ConfigError, PX4Config, SiteConfig, load_config
from droneulator.sensors.baro import isa_pressure_pa
from droneulator.sensors.mag import wmm_field_ned_gauss
from droneulator.sensors.rig import build_rig
from droneulator.sensors.truth import Truth

Z3 = np.zeros(3)
LEVEL = np.array([0.0, 0.0, 0.0, 1.0])
#: the home the px4 section held before the site section existed
OLD_HOME = (53.2281, -0.5470, 10.0)


def suite_of(overrides: list[str]):
    cfg = load_config(overrides=overrides)
    return build_rig([], cfg.vehicle.sensors, cfg.px4, cfg.seed, site=cfg.site).suite


def test_the_default_site_is_the_old_home_and_the_gps_fixes_there():
    cfg = load_config()
    assert cfg.site.geodetic == OLD_HOME and cfg.site.utc_offset_h is None
    truth = Truth(0, np.array([3.0, -4.0, 2.0]), Z3, LEVEL, Z3, Z3, Z3)
    fix = suite_of([]).gps(truth)
    off = F.geodetic_to_enu(fix.lat_deg, fix.lon_deg, fix.alt_msl_m, *OLD_HOME) - truth.position
    assert np.linalg.norm(off) < 0.2  # the "sitl" preset's few centimetres
    assert suite_of([]).baro(truth).pressure_hpa == pytest.approx(isa_pressure_pa(12.0) / 100, abs=0.05)


def test_a_moved_site_moves_the_gps_fix_the_barometer_and_the_magnetic_field():
    moved = ["site.latitude_deg=-33.87", "site.longitude_deg=151.21", "site.altitude_m=500"]
    suite = suite_of(moved)
    fix = suite.gps(Truth(0, Z3, Z3, LEVEL, Z3, Z3, Z3))
    assert fix.lat_deg == pytest.approx(-33.87, abs=1e-5) and fix.lon_deg == pytest.approx(151.21, abs=1e-5)
    assert fix.alt_msl_m == pytest.approx(500.0, abs=0.3)
    assert suite.baro(Truth(0, Z3, Z3, LEVEL, Z3, Z3, Z3)).pressure_alt_m == pytest.approx(500.0, abs=1.0)
    want = wmm_field_ned_gauss(-33.87, 151.21, 500.0, PX4Config().mag_wmm_year)
    np.testing.assert_allclose(suite.models["mag"].field_ned, want)
    assert want[2] < 0  # southern hemisphere: the field points up, unlike at the default site


@pytest.mark.parametrize(
    ("old", "new", "value"),
    [
        ("px4.home_lat_deg", "site.latitude_deg", 44.84),
        ("px4.home_lon_deg", "site.longitude_deg", -0.58),
        ("px4.home_alt_m", "site.altitude_m", 120.0),
    ],
)
def test_an_old_key_loads_with_a_warning_into_the_site(tmp_path, caplog, old, new, value):
    section, key = old.split(".")
    _, new_key = new.split(".")
    f = tmp_path / "old.toml"
    f.write_text(f"[{section}]\n{key} = {value}\ngps_hz = 5.0\n")
    with caplog.at_level(logging.WARNING), pytest.warns(DeprecationWarning, match=rf"{old}.*set {new}"):
        from_file = load_config(f)
    assert getattr(from_file.site, new_key) == value and from_file.px4.gps_hz == 5.0
    assert new in caplog.text
    with pytest.warns(DeprecationWarning, match=new):
        from_set = load_config(overrides=[f"{old}={value}"])
    assert from_set.site == from_file.site and from_set.site != SiteConfig()
    assert not hasattr(from_set.px4, key)


def test_an_old_key_and_its_new_key_disagreeing_is_an_error(tmp_path):
    f = tmp_path / "both.json"
    f.write_text(json.dumps({"px4": {"home_lat_deg": 40.0}, "site": {"latitude_deg": 41.0}}))
    both = r"px4\.home_lat_deg.*site\.latitude_deg"
    with pytest.raises(ConfigError, match=both):
        load_config(f)
    f.write_text(json.dumps({"px4": {"home_lat_deg": 40.0}, "site": {"latitude_deg": 40.0}}))
    with pytest.warns(DeprecationWarning):
        assert load_config(f).site.latitude_deg == 40.0
    with pytest.warns(DeprecationWarning):  # a later --set wins over the file, as for any key
        assert load_config(f, ["px4.home_lat_deg=42"]).site.latitude_deg == 42.0


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("site.latitude_deg=91", r"site\.latitude_deg must lie in \[-90, 90\] degrees, got 91"),
        ("px4.home_lat_deg=-90.5", r"site\.latitude_deg must lie in \[-90, 90\]"),
        ("site.longitude_deg=180.5", r"site\.longitude_deg must lie in \[-180, 180\]"),
        ("site.altitude_m=NaN", r"site\.altitude_m must be a finite number"),
        ("site.utc_offset_h=15", r"site\.utc_offset_h must lie in \[-14, 14\] hours"),
        ("site.latitude_deg=north", r"site\.latitude_deg: expected float"),
    ],
)
def test_a_bad_site_is_a_clear_error(override, message):
    warned = pytest.warns(DeprecationWarning) if override.startswith("px4.") else contextlib.nullcontext()
    with warned, pytest.raises(ValueError, match=message):
        load_config(overrides=[override])


def test_cli_config_prints_the_site_section(capsys):
    assert main(["config", "--set", "site.latitude_deg=44.84", "--set", "site.utc_offset_h=2"]) == 0
    out = json.loads(capsys.readouterr().out)
    want = {"latitude_deg": 44.84, "longitude_deg": -0.547, "altitude_m": 10.0, "utc_offset_h": 2.0}
    assert out["site"] == want
    assert not any(k.startswith("home_") for k in out["px4"])
