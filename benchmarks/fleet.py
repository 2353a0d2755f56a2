"""A fleet through the full runtime: lockstep real-time factor for N vehicles, each with a 640x480 rig.

For each N, ``droneulator run --vehicles N`` (dynamics server, render server, bridge; lockstep, every
vehicle's front camera at 30 Hz with RGB, depth and segmentation, shadows on) runs on the scene while
every vehicle flies straight on at 0.3 m/s (velocity mode, over the API) and a Zenoh subscriber takes
every image of every vehicle (lockstep: the clock waits for it, nothing is skipped). Measured over
``--seconds`` of wall time after a warm-up: sim seconds per wall second (the real-time factor), camera
frames delivered per wall second, and each process's CPU use (CPU seconds per wall second, from /proc),
against N = 1 in the same run. The single-vehicle run is today's ``droneulator run``. With
``--encode-threads 1 0`` each N runs twice, the bridge encoding its images in one thread and then in
its default pool (one thread per CPU, up to 8), for the ratio between them.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from typing import Any

import zenoh
from _common import children, write

from droneulator.config import fleet, load_config
from droneulator.ros.publishers import encode_threads as bridge_encode_threads
from droneulator.runtime.launch import launch_run

CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()  # noqa: SIM115
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def measure(
    n: int, scene: str, seconds: float, warmup: float, encode_threads: int = 0, frame_slots: int = 3
) -> dict[str, Any]:
    cfg = load_config(scene=scene)
    cfg.bridge.encode_threads = encode_threads
    cfg.runtime.frame_slots = frame_slots
    if n > 1:
        cfg.vehicles = fleet(n)
    run = launch_run(cfg)
    counts = {"frames": 0}
    lock = threading.Lock()

    def on_image(_sample: zenoh.Sample) -> None:
        with lock:
            counts["frames"] += 1

    zc = zenoh.Config()
    zc.insert_json5("mode", '"client"')
    zc.insert_json5("connect/endpoints", f'["{run.zenoh_endpoint}"]')
    session = zenoh.open(zc)
    sub = session.declare_subscriber("droneulator/**/color/image_raw/compressed", on_image)
    try:
        with run.client(timeout=60) as c:
            names = [v["name"] for v in c.scene_info()["vehicles"]]
            for k, name in enumerate(names):
                c.takeoff(2.0 + 0.5 * (k % 4), vehicle=name)
            for name in names:
                c.wait_until(lambda s: s["mode"] == "hold", timeout=300, vehicle=name)
            for name in names:  # straight on, into the orchard: every camera sees trees for the whole
                c.velocity(0.3, 0.0, vehicle=name)  # window, however fast the clock runs (a turning one
                # saw open ground half the time at N = 1 and not at N = 8, which skewed the comparison)
            time.sleep(warmup)
            procs = {"run (supervisor)": run.pid, **children(run.pid)}
            cpu0 = {k: cpu_seconds(p) for k, p in procs.items()}
            with lock:
                f0 = counts["frames"]
            t0, w0 = c.state()["t"], time.monotonic()
            time.sleep(seconds)
            t1, w1 = c.state()["t"], time.monotonic()
            with lock:
                f1 = counts["frames"]
            cpu1 = {k: cpu_seconds(p) for k, p in procs.items()}
    finally:
        sub.undeclare()
        session.close()
        run.stop()
    wall = w1 - w0
    return {
        "vehicles": n,
        "encode_threads": bridge_encode_threads(encode_threads),
        "frame_slots": frame_slots,
        "sim_seconds": t1 - t0,
        "wall_seconds": wall,
        "real_time_factor": (t1 - t0) / wall,
        "camera_frames_per_wall_s": (f1 - f0) / wall,
        "cpu_per_process": {k: (cpu1[k] - cpu0[k]) / wall for k in procs},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--vehicles", type=int, nargs="+", default=[1, 2, 4, 8], help="fleet sizes (default 1 2 4 8)"
    )
    ap.add_argument("--scene", default="orchard", help="scene (default orchard)")
    ap.add_argument("--seconds", type=float, default=15.0, help="wall seconds measured per size (default 15)")
    ap.add_argument("--warmup", type=float, default=3.0, help="wall seconds before measuring (default 3)")
    ap.add_argument(
        "--encode-threads",
        type=int,
        nargs="+",
        default=[0],
        help="bridge.encode_threads settings, each size measured with each in turn (default 0: one per CPU, "
        "up to 8; '1 0' compares one encoding thread with the default)",
    )
    ap.add_argument(
        "--frame-slots",
        type=int,
        nargs="+",
        default=[3],
        help="runtime.frame_slots settings (frames in flight + 1), each measured in turn (default 3)",
    )
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/fleet.json)")
    args = ap.parse_args()
    rows = []
    for n in args.vehicles:
        for threads, slots in ((t, s) for t in args.encode_threads for s in args.frame_slots):
            row = measure(n, args.scene, args.seconds, args.warmup, threads, slots)
            rows.append(row)
            cpu = ", ".join(f"{k} {v:.2f}" for k, v in row["cpu_per_process"].items())
            print(
                f"N={n}, {row['encode_threads']} encoding threads, {slots} frame slots: "
                f"RTF {row['real_time_factor']:.2f}, "
                f"{row['camera_frames_per_wall_s']:.1f} camera frames/s, CPU s/s: {cpu}",
                flush=True,
            )

    def setting(r: dict[str, Any]) -> tuple[int, int]:
        return r["encode_threads"], r["frame_slots"]

    for r in rows:
        same = [b for b in rows if setting(b) == setting(r)]
        base = next((b for b in same if b["vehicles"] == 1), same[0])
        r["rtf_vs_one_vehicle"] = r["real_time_factor"] / base["real_time_factor"]
        r["frames_vs_one_vehicle"] = r["camera_frames_per_wall_s"] / base["camera_frames_per_wall_s"]
        one = next((b for b in rows if b["vehicles"] == r["vehicles"] and setting(b) == (1, 3)), None)
        if one is not None:  # against one encoding thread and 3 frame slots (the default before 2026-11-30)
            r["frames_vs_one_encoding_thread"] = (
                r["camera_frames_per_wall_s"] / one["camera_frames_per_wall_s"]
            )
    rig = "front 640x480, 30 Hz, shadows on"
    write("fleet", {"scene": args.scene, "camera": rig, "runs": rows}, args.json)


if __name__ == "__main__":
    main()
