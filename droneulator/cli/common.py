"""What several commands share: the configuration options and their loading, the bag options and report."""

from __future__ import annotations

import argparse

from droneulator.config import SimConfig, fleet
from droneulator.runtime import preflight
from droneulator.runtime.preflight import StartupError

#: commands the PyInstaller bundle leaves out (torch, pycolmap), with the pip extra each needs
PIP_ONLY = {"train": "rl", "evaluate": "rl", "reconstruct": "colmap"}
#: the Zenoh endpoint of a run's bridge by default (bridge.listen)
DEFAULT_ZENOH = "tcp/127.0.0.1:7448"


def add_file_args(p: argparse.ArgumentParser, example: str) -> None:
    """``--config FILE`` and repeatable ``--set KEY=VALUE`` (applied in that order over the defaults)."""
    p.add_argument("--config", default=None, help="JSON, TOML or YAML file with SimConfig fields")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override one option, e.g. {example}",
    )


def add_config_args(
    p: argparse.ArgumentParser, scene_default: str | None = None, fleet: bool = False
) -> None:
    """``--scene``, ``--seed`` and the file arguments: what :func:`config_from_args` reads; ``fleet``:
    also ``--vehicles N``, for the commands that handle a world of several vehicles."""
    p.add_argument("--scene", default=scene_default, help="scene name (see `droneulator scenes`)")
    p.add_argument("--seed", type=int, default=None, help="scene and noise seed (default 0)")
    if fleet:
        p.add_argument(
            "--vehicles",
            type=int,
            default=None,
            metavar="N",
            help="N vehicles, uav0 .. uav<N-1>, on free points near the scene's spawn, each with the "
            "single-vehicle sections' settings (default: the config's 'vehicles' list, or one)",
        )
    add_file_args(p, "--set render.shadows=false --set vehicle.params=crazyflie")


def add_rl_config_args(p: argparse.ArgumentParser) -> None:
    """``--scene-seed`` and the file arguments of ``train`` and ``evaluate``."""
    p.add_argument("--scene-seed", type=int, default=None, help="vineyard scene seed (default 0)")
    add_file_args(p, "--set rl.heading=goal --set rl.safety_margin=0.4")


def config_from_args(args: argparse.Namespace) -> SimConfig:
    """The configuration of :func:`add_config_args`'s options, checked (a :class:`StartupError`)."""
    cfg = preflight.load(args.config, args.overrides, scene=args.scene, seed=args.seed)
    n = getattr(args, "vehicles", None)
    if n is not None:
        if n < 1:
            raise StartupError(f"--vehicles {n}: need at least one vehicle", preflight.USAGE)
        if cfg.vehicles:
            raise StartupError(
                f"--vehicles {n} and the config's 'vehicles' list ({len(cfg.vehicles)} named) both say "
                "which vehicles fly: give one of them",
                preflight.USAGE,
            )
        cfg.vehicles = fleet(n)
    return cfg


def simulation_config(args: argparse.Namespace) -> SimConfig:
    """The config of an in-process simulator (snapshot, demo), checked with its output folder and EGL."""
    cfg = config_from_args(args)
    preflight.check_simulation(cfg)
    preflight.check_output_dir(args.out)
    preflight.check_egl()
    return cfg


def add_compression_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="MCAP chunk compression of the bag (default zstd)",
    )


def bag_size(text: str) -> int:
    """``--max-bag-size``'s value: bytes, or with a K/M/G suffix (KiB, MiB, GiB)."""
    units = {"K": 1024, "M": 1024**2, "G": 1024**3}
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    try:
        n = float(t[:-1]) * units[t[-1]] if t and t[-1] in units else float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a size: {text!r} (bytes, or e.g. 500M, 2G)") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"a size must be >= 0, got {text!r}")
    return int(n)


def add_bag_split_args(p: argparse.ArgumentParser, when: str = "") -> None:
    """``--max-bag-size`` and ``--max-bag-duration``, as ``ros2 bag record`` names them."""
    p.add_argument(
        "--max-bag-size",
        type=bag_size,
        default=0,
        metavar="SIZE",
        help=f"{when}split the bag directory into files of about SIZE (bytes, or 500M, 2G; default 0: one "
        "file). An hour of images should split: the writer holds each file's chunk index until it closes",
    )
    p.add_argument(
        "--max-bag-duration",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help=f"{when}split the bag directory every SECONDS of simulated time (default 0: never)",
    )


def add_key_mode_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--key-mode", choices=("ros2dds", "rmw_zenoh"), default="ros2dds", help="the run's bridge.key_mode"
    )
    p.add_argument("--domain-id", type=int, default=0, help="rmw_zenoh key mode: the ROS domain id")
    p.add_argument(
        "--ros2dds-namespace", default="/", help="ros2dds key mode: the run's bridge.ros2dds_namespace"
    )


def check_bag_output(path: str, option: str, max_bytes: int = 0, max_duration_s: float = 0.0) -> None:
    """A bag that cannot be written at ``path`` (or split as asked) is a usage error naming ``option``."""
    from droneulator.recording.bag import check_output, check_split

    try:
        check_output(path)
        check_split(path, max_bytes, max_duration_s)
    except ValueError as exc:
        raise StartupError(f"{option}: {exc}", preflight.USAGE) from None


def report_recording(stats: object) -> None:
    """Print what a recorder wrote (its ``close()``): messages per topic, and the topics left out."""
    from droneulator.recording.recorder import RecordingStats

    assert isinstance(stats, RecordingStats)
    total = sum(stats.written.values())
    files = f" in {len(stats.files)} files" if len(stats.files) > 1 else ""
    print(
        f"recorded {total} messages on {len(stats.written)} topics to {stats.path} "
        f"({stats.bytes / 1e6:.1f} MB{files})",
        flush=True,
    )
    for topic, n in sorted(stats.written.items()):
        print(f"  {n:8d}  {topic}", flush=True)
    for topic, n in sorted(stats.untyped.items()):
        print(f"  {n:8d}  {topic}  NOT RECORDED: its type was never announced", flush=True)


def add_ray_arg(p: argparse._ActionsContainer, what: str) -> None:
    """``--ray ADDRESS`` (:mod:`droneulator.runtime.cluster`): ``what`` the command runs on Ray."""
    p.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help=f"{what}: 'local' (start Ray here), 'auto' (the cluster this machine belongs to) or "
        "the head node's HOST:PORT",
    )
