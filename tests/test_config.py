"""Typed configuration: defaults, files, overrides and errors."""

import json
import re
from pathlib import Path

import pytest

from droneulator.cli import main
from droneulator.config import CameraConfig, SimConfig, load_config


def test_defaults():
    cfg = load_config()
    assert isinstance(cfg, SimConfig)
    assert cfg.scene == "default" and cfg.render.cameras[0].width == 640 and cfg.render.camera_hz == 30.0


def test_file_then_overrides_then_keywords(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(
        json.dumps(
            {
                "scene": "orchard",
                "render": {
                    "shadows": False,
                    "cameras": [{"name": "down", "rpy_deg": [0, 90, 0], "width": 320, "height": 240}],
                },
            }
        )
    )
    cfg = load_config(f, ["vehicle.params=crazyflie", "render.camera_hz=15"], seed=7)
    assert cfg.scene == "orchard" and cfg.seed == 7 and cfg.render.shadows is False
    assert cfg.render.cameras[0] == CameraConfig(name="down", rpy_deg=(0.0, 90.0, 0.0), width=320, height=240)
    assert cfg.vehicle.params == "crazyflie" and cfg.render.camera_hz == 15.0


def test_toml_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('scene = "vineyard"\n[flight]\ntakeoff_altitude = 3.5\n')
    cfg = load_config(f)
    assert cfg.scene == "vineyard" and cfg.flight.takeoff_altitude == 3.5


@pytest.mark.parametrize(
    "override",
    [
        "render.nonsense=1",
        "bogus=2",
        "no_equals_sign",
        "render.shadows=maybe",
        'render.cameras=[{"width": -5}]',
        "ui.nice=20",
        "ui.image_hz=0",
        "render.camera_trigger=sometimes",
        "runtime.max_speed=0",
        "capture.state_hz=1",
        "bridge.encode_threads=-1",
    ],
)
def test_bad_overrides_raise(override):
    with pytest.raises(ValueError):
        load_config(None, [override])
    key = override.split("=")[0]
    if key.count(".") == 1 and not key.startswith("render.cameras"):
        with pytest.raises(ValueError, match=key.rsplit(".", 1)[-1]):  # the message names the field
            load_config(None, [override])


def test_cli_config_prints_effective_json_and_reports_errors(capsys):
    assert main(["config", "--scene", "orchard", "--set", "vehicle.aero=false"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scene"] == "orchard" and out["vehicle"]["aero"] is False
    assert main(["config", "--set", "render.bogus=1"]) == 2
    assert "unknown RenderConfig option" in capsys.readouterr().err


def test_workflow_sections_keep_their_keys_in_files_and_overrides(tmp_path):
    from droneulator.config import CaptureConfig, RLConfig

    f = tmp_path / "c.toml"
    f.write_text('[capture]\nviews = 36\naltitudes = [4.0, 6.0]\n[rl]\nheading = "goal"\n')
    cfg = load_config(f, ["capture.radius=6.5", "rl.lookahead=3"])
    assert isinstance(cfg.capture, CaptureConfig) and isinstance(cfg.rl, RLConfig)
    assert (cfg.capture.views, cfg.capture.altitudes, cfg.capture.radius) == (36, [4.0, 6.0], 6.5)
    assert (cfg.rl.heading, cfg.rl.lookahead) == ("goal", 3.0)
    with pytest.raises(ValueError, match="unknown CaptureConfig option"):
        load_config(None, ["capture.nonsense=1"])
    with pytest.raises(ValueError, match="rl.heading"):
        load_config(None, ["rl.heading=sideways"])


def test_yaml_file(tmp_path):
    f = tmp_path / "c.yml"
    f.write_text("# a ROS-style file\nscene: vineyard\nflight:\n  takeoff_altitude: 3.5\n")
    f.write_text(f.read_text() + "render: {shadows: off}\n")
    cfg = load_config(f)
    assert cfg.scene == "vineyard" and cfg.flight.takeoff_altitude == 3.5 and cfg.render.shadows is False
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing set yet\n")
    assert load_config(empty) == load_config()


def _doc_block(doc: Path, lang: str, first_line: str) -> str:
    """The fenced ``lang`` block of ``doc`` whose first line starts with ``first_line``."""
    blocks = re.findall(rf"^```{lang}\n(.*?)^```", doc.read_text(), flags=re.S | re.M)
    found = [b for b in blocks if b.startswith(first_line)]
    assert len(found) == 1, f"{doc} has {len(found)} {lang} blocks starting {first_line!r}"
    return found[0]


def test_the_px4_docs_fleet_example_loads(tmp_path):
    doc = Path(__file__).resolve().parents[1] / "docs" / "px4.md"
    f = tmp_path / "fleet.yaml"
    f.write_text(_doc_block(doc, "yaml", "# fleet.yaml"))
    cfg = load_config(f)
    assert cfg.vehicle.control_hz == 250
    assert [(v.name, v.controlled_by) for v in cfg.vehicles] == [
        ("uav0", "internal"), ("uav1", "internal"), ("uav2", "px4")
    ]  # fmt: skip
    assert main(["config", "--config", str(f)]) == 0


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        ("vehicle: {control_hz: 250\nvehicles: []\n", ("not valid YAML", "flow mapping", "line 2 column 9")),
        ("scene: vineyard\n  seed: 3\n", ("not valid YAML", "mapping values are not allowed", "line 2")),
        ("- 1\n- 2\n", ("expected a table of options, got list",)),
        ("render:\n  shadowz: false\n", ("render.shadowz",)),
    ],
)
def test_a_bad_yaml_file_is_a_one_line_error_naming_the_file_and_line(tmp_path, capsys, text, needles):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    assert main(["config", "--config", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(f) in err and all(n in err for n in needles), err
    with pytest.raises(ValueError, match=re.escape(needles[0])):
        load_config(f)
