"""Cost of ``droneulator run --record``: lockstep real-time factor with and without the recorder, and
the bag's size per minute of flight.

Alternates plain runs and recorded runs of ``droneulator run`` (lockstep, the default 640x480 front
camera with RGB + depth + segmentation at 30 Hz sim time), each hovering for ``--wall`` wall seconds
after a warm-up; the real-time factor is simulated seconds / wall seconds read from the WebSocket API
over that window. The recorder writes every message (JPEG colour, 32FC1 depth, PNG segmentation, their
camera_info, pose, odometry, TF and /clock) as zstd-compressed MCAP.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from _common import write

from droneulator.config import load_config
from droneulator.runtime.launch import launch_run


def measure(scene: str, wall_s: float, record: Path | None, compression: str) -> dict[str, float]:
    """Real-time factor over ``wall_s`` wall seconds of one run (after a 2 s sim warm-up)."""
    cfg = load_config(scene=scene)
    args = ["--record", str(record), "--compression", compression] if record is not None else []
    with launch_run(cfg, args) as run, run.client(timeout=120) as c:
        c.takeoff(2.0)
        while c.state()["t"] < 2.0:
            time.sleep(0.1)
        t0, w0 = c.state()["t"], time.monotonic()
        time.sleep(wall_s)
        t1, w1 = c.state()["t"], time.monotonic()
    out = {"sim_seconds": t1 - t0, "wall_seconds": w1 - w0, "real_time_factor": (t1 - t0) / (w1 - w0)}
    if record is not None:
        size = record.stat().st_size
        out["bag_bytes"] = size
        out["bag_sim_seconds"] = t1  # the bag holds the whole run, from sim time 0 to about t1
        out["mb_per_sim_minute"] = size / 1e6 / t1 * 60.0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="orchard", help="scene name (default orchard)")
    ap.add_argument("--wall", type=float, default=20.0, help="wall seconds timed per run (default 20)")
    ap.add_argument("--pairs", type=int, default=2, help="plain/recorded pairs, alternated (default 2)")
    ap.add_argument("--compression", default="zstd", choices=("zstd", "lz4", "none"))
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/recording.json)")
    args = ap.parse_args()

    plain: list[dict[str, float]] = []
    recorded: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory(prefix="droneulator-bench-") as tmp:
        for i in range(args.pairs):
            plain.append(measure(args.scene, args.wall, None, args.compression))
            recorded.append(measure(args.scene, args.wall, Path(tmp, f"run{i}.mcap"), args.compression))
            print(
                f"pair {i}: RTF {plain[-1]['real_time_factor']:.3f} plain, "
                f"{recorded[-1]['real_time_factor']:.3f} recorded, "
                f"{recorded[-1]['mb_per_sim_minute']:.0f} MB per sim minute"
            )
    rtf_plain = sum(r["real_time_factor"] for r in plain) / len(plain)
    rtf_rec = sum(r["real_time_factor"] for r in recorded) / len(recorded)
    mb_min = sum(r["mb_per_sim_minute"] for r in recorded) / len(recorded)
    res = {
        "scene": args.scene,
        "camera": "front 640x480 rgb+depth+seg at 30 Hz (defaults)",
        "compression": args.compression,
        "wall_seconds_per_run": args.wall,
        "plain": plain,
        "recorded": recorded,
        "real_time_factor_plain": rtf_plain,
        "real_time_factor_recorded": rtf_rec,
        "rtf_change_percent": (rtf_rec / rtf_plain - 1.0) * 100.0,
        "mb_per_sim_minute": mb_min,
        "mb_per_wall_minute": mb_min * rtf_rec,
    }
    print(
        f"{args.scene}: lockstep RTF {rtf_plain:.3f} without, {rtf_rec:.3f} with recording "
        f"({res['rtf_change_percent']:+.1f} %); {mb_min:.0f} MB per minute of sim time"
    )
    write("recording", res, args.json)


if __name__ == "__main__":
    main()
