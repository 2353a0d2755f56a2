"""The command path's Protocols (droneulator/commands/surface.py) name what the world really offers:
``World`` and its vehicles satisfy them, member for member."""

import inspect
import textwrap
from pathlib import Path

import pytest

from droneulator.commands.surface import CommandedVehicle, CommandedWorld
from droneulator.config import load_config
from droneulator.vehicles.vehicle import Vehicle
from droneulator.world.world import World


def _methods(protocol: type) -> list[str]:
    """The protocol's own methods (not properties)."""
    return [n for n, m in vars(protocol).items() if inspect.isfunction(m) and not n.startswith("_")]


def _parameters(fn: object) -> list[tuple[str, object]]:
    return [(p.name, p.default) for p in inspect.signature(fn).parameters.values()]


@pytest.fixture(scope="module")
def world():
    with World(load_config(scene="default"), render=False) as w:
        yield w


def test_the_world_and_its_vehicles_are_what_the_command_path_drives(world):
    assert isinstance(world, CommandedWorld)
    assert all(isinstance(v, CommandedVehicle) for v in world.vehicles.values())
    assert isinstance(world.vehicle(), CommandedVehicle)
    assert not isinstance(object(), CommandedWorld)  # the check looks at the members


@pytest.mark.parametrize(
    ("protocol", "cls", "methods"),
    [
        (CommandedWorld, World, {"vehicle", "reset", "trigger", "set_wind", "inject_fault", "clear_faults",
                                 "command_link_cut"}),
        (CommandedVehicle, Vehicle, {"takeoff", "land", "goto", "velocity", "track", "hold", "motors_off",
                                     "describe", "rotors", "rates", "attitude"}),  # fmt: skip
    ],
)
def test_every_method_the_command_path_calls_takes_the_same_arguments(protocol, cls, methods):
    """``isinstance`` sees only names; the ops call with keywords, so the names and defaults must agree."""
    assert set(_methods(protocol)) == methods
    for name in methods:
        assert _parameters(getattr(cls, name)) == _parameters(getattr(protocol, name)), name


def test_mypy_finds_the_world_satisfies_the_protocols(tmp_path, monkeypatch):
    """The typed check (signatures, attribute and return types)."""
    from mypy import api

    monkeypatch.setenv("MYPYPATH", str(Path(__file__).resolve().parents[1]))  # this checkout's droneulator
    probe = tmp_path / "probe.py"
    probe.write_text(
        textwrap.dedent(
            """
            from droneulator.commands.surface import CommandedVehicle, CommandedWorld
            from droneulator.vehicles.vehicle import Vehicle
            from droneulator.world.world import World

            def check(world: World, vehicle: Vehicle) -> None:
                w: CommandedWorld = world
                v: CommandedVehicle = vehicle
            """
        )
    )
    flags = ["--ignore-missing-imports", "--follow-imports=silent", "--cache-dir", str(tmp_path / "cache")]
    out, err, status = api.run([*flags, str(probe)])
    assert status == 0, out + err
