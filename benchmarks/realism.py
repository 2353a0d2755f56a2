"""The field, not the lab: how the wind field moves a hovering vehicle.

wind: a vehicle hovers 3 m up in the open (the ``default`` scene's spawn, no canopy upwind) under the
wind field for each mean wind W20 in ``--speeds`` (MIL-F-8785C Dryden turbulence, whose intensity
follows W20, plus 1-cosine gusts of half W20 every 8 s on average), ``--seconds`` of simulated time
per run after a 5 s settle, ``--seeds`` realisations each. Figures: the RMS and the largest
horizontal and vertical position error, the mean and the standard deviation of the wind felt, and
the same hover between two of the vineyard's rows, 1.5 m up in a wind across them (the canopy's
shelter), against a hover above the canopy.

Prints the table, writes ``benchmarks/results/realism.json`` and the figure
``benchmarks/results/realism_wind.png`` (copied to ``docs/img/wind_hover.png``).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from _common import RESULTS, write

from droneulator.config import load_config
from droneulator.scenes import get_scene
from droneulator.world import World

SETTLE_S = 5.0


def hover(
    scene: str,
    speed: float,
    seed: int,
    seconds: float,
    height: float,
    at: Any = None,
    direction: float = 270.0,
) -> dict[str, Any]:
    """Hover at ``height`` over ``at`` (default: the scene's spawn) in a W20 = ``speed`` gusty wind from
    ``direction`` (degrees clockwise from north)."""
    cfg = load_config(
        scene=scene,
        overrides=[
            f"seed={seed}",
            f"wind.speed_m_s={speed}",
            f"wind.direction_deg={direction}",
            f"wind.gust_speed_m_s={speed / 2}",
            "wind.gust_interval_s=8",
        ],
    )
    world = World(cfg, render=False)
    v = world.vehicle()
    base = v.state.position if at is None else np.asarray(at, dtype=float)
    target = base + [0.0, 0.0, height]
    world.reset(position=target)
    world.step(round(SETTLE_S * cfg.vehicle.control_hz))
    n = round(seconds * cfg.vehicle.control_hz)
    err = np.empty((n, 3))
    wind = np.empty((n, 3))
    for k in range(n):
        world.step()
        st = v.state
        err[k] = st.position - target
        wind[k] = st.wind
    horiz = np.hypot(err[:, 0], err[:, 1])
    speed_felt = np.linalg.norm(wind[:, :2], axis=1)
    return {
        "rms_horizontal_m": float(np.sqrt(np.mean(horiz**2))),
        "max_horizontal_m": float(horiz.max()),
        "rms_vertical_m": float(np.sqrt(np.mean(err[:, 2] ** 2))),
        "max_vertical_m": float(np.abs(err[:, 2]).max()),
        "wind_mean_m_s": float(speed_felt.mean()),
        "wind_std_m_s": float(speed_felt.std()),
        "collided": v.mode.value == "collided",
    }


def mean_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    keys = [k for k in runs[0] if k != "collided"]
    out: dict[str, Any] = {k: float(np.mean([r[k] for r in runs])) for k in keys}
    out["max_horizontal_m"] = max(r["max_horizontal_m"] for r in runs)
    out["max_vertical_m"] = max(r["max_vertical_m"] for r in runs)
    out["collided"] = sum(r["collided"] for r in runs)
    return out


def wind_part(args: argparse.Namespace) -> dict[str, Any]:
    rows = []
    head = ("W20 m/s", "felt m/s", "std", "rms xy m", "max xy m", "rms z m", "max z")
    print(" ".join(f"{h:>9}" for h in head))
    for speed in args.speeds:
        runs = [hover("default", speed, s, args.seconds, 3.0) for s in range(args.seeds)]
        row = {"speed_m_s": speed, **mean_of(runs)}
        rows.append(row)
        keys = ("wind_mean_m_s", "wind_std_m_s", "rms_horizontal_m", "max_horizontal_m")
        keys += ("rms_vertical_m", "max_vertical_m")
        print(f"{speed:9.1f} " + " ".join(f"{row[k]:9.3f}" for k in keys))
    # the vineyard's shelter: a wind from the south, across the rows (they run along x); a hover in the
    # middle of an alley 1.5 m up (the hedge's height), against the same hover above the canopy
    marks = get_scene("vineyard", 0).landmarks
    alley = [
        (marks["row_x_min"][0] + marks["row_x_max"][0]) / 2,
        marks["alley_y"][len(marks["alley_y"]) // 2],
        0,
    ]
    shelter = {}
    for label, height in (("between rows, 1.5 m", 1.5), ("above the canopy, 4 m", 4.0)):
        runs = [
            hover("vineyard", args.shelter_speed, s, args.seconds, height, alley, direction=180.0)
            for s in range(args.seeds)
        ]
        shelter[label] = mean_of(runs)
        r = shelter[label]
        print(
            f"vineyard, W20 {args.shelter_speed} m/s, {label}: wind felt {r['wind_mean_m_s']:.2f} m/s "
            f"(std {r['wind_std_m_s']:.2f}), rms xy error {r['rms_horizontal_m']:.3f} m"
        )
    return {"hover": rows, "shelter": shelter, "shelter_speed_m_s": args.shelter_speed}


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["hover"]
    w = [r["speed_m_s"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    ax.plot(w, [r["rms_horizontal_m"] for r in rows], "o-", label="horizontal, RMS")
    ax.plot(w, [r["max_horizontal_m"] for r in rows], "o--", label="horizontal, largest")
    ax.plot(w, [r["rms_vertical_m"] for r in rows], "s-", label="vertical, RMS")
    ax.plot(w, [r["max_vertical_m"] for r in rows], "s--", label="vertical, largest")
    ax.set_xlabel("mean wind W20 (m/s), Dryden turbulence + 1-cosine gusts of W20/2")
    ax.set_ylabel("position error (m)")
    ax.set_title("Hover 3 m up, hummingbird, SE(3) controller")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.0, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per hover")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--shelter-speed", type=float, default=5.0)
    ap.add_argument("--out", help="JSON path (default benchmarks/results/realism.json)")
    args = ap.parse_args()
    result = {"wind": wind_part(args), "seconds": args.seconds, "seeds": args.seeds}
    write("realism", result, args.out)
    fig = RESULTS / "realism_wind.png"
    plot(result["wind"], fig)
    docs = Path(__file__).resolve().parent.parent / "docs" / "img" / "wind_hover.png"
    shutil.copyfile(fig, docs)
    print(f"wrote {fig} and {docs}")


if __name__ == "__main__":
    main()
