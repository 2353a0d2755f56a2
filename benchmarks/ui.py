"""What the browser UI costs the simulation, and how old the images it shows are.

Side by side in one benchmark run, ``droneulator run`` in lockstep (640x480 rig, default scene) flies
the same slow velocity-mode circle twice, ``--windows`` times each, alternating:

1. without a UI,
2. with ``--ui`` and a headless Chromium showing the flight view (every camera stream at the UI's
   default 10 Hz).

Real-time factor = simulated seconds / wall seconds over ``--seconds`` of wall time (after a warm-up).
The UI's requirement (issue 12) is a drop of at most 10 %.

Image latency: the dynamics server logs the wall time at the end of each physics step that produced a
state (``bridge.latency_log``, stream ``odom``; where a stamp has none, the bridge's mark right after the
render is used); the page logs, per image it shows, the image's stamp and
the wall time it appeared (``window.droneulatorUI.cameras.shown``). The difference is render -> shown:
render, publish over Zenoh, the UI's encoding and the WebSocket to the page, and the page's decoding.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from _common import write

from droneulator.config import load_config
from droneulator.runtime.launch import free_port, launch_run


def fly(run) -> object:
    client = run.client(timeout=120)
    client.subscribe(["events"])
    client.takeoff(altitude=2.0)
    client.wait_for_event("arrived", timeout=300)
    client.velocity(0.5, 0.3)
    return client


def measure_rtf(client, seconds: float, warmup: float) -> dict:
    time.sleep(warmup)
    t0, w0 = client.state()["t"], time.monotonic()
    time.sleep(seconds)
    t1, w1 = client.state()["t"], time.monotonic()
    return {"sim_seconds": t1 - t0, "wall_seconds": w1 - w0, "real_time_factor": (t1 - t0) / (w1 - w0)}


def without_ui(args: argparse.Namespace) -> dict:
    with launch_run(load_config(scene=args.scene), ["--lockstep"], start_timeout=180) as run:
        client = fly(run)
        res = measure_rtf(client, args.seconds, args.warmup)
        client.close()
    return res


def with_ui(args: argparse.Namespace, chromium: str) -> dict:
    from playwright.sync_api import sync_playwright

    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "latency.log"
        overrides = [f"bridge.latency_log={log}", f"ui.image_hz={args.image_hz}"]
        cfg = load_config(scene=args.scene, overrides=overrides)
        with launch_run(cfg, ["--lockstep", "--ui-port", str(port)], start_timeout=180) as run:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
                page = browser.new_page(viewport={"width": 1500, "height": 1000})
                page.goto(f"http://127.0.0.1:{port}/#fly")
                page.wait_for_function("window.droneulatorUI.cameras.count > 5", timeout=180000)
                client = fly(run)
                res = measure_rtf(client, args.seconds, args.warmup)
                shown = page.evaluate("window.droneulatorUI.cameras.shown")
                browser.close()
            client.close()
        # per image stamp: the end of the physics step that produced it (odom) if logged, else the
        # bridge's mark right after the render (rgb/depth): the earliest wall time known for the image
        steps: dict[int, int] = {}
        for line in log.read_text().splitlines():
            _stream, stamp, wall = line.split()
            steps[int(stamp)] = min(int(wall), steps.get(int(stamp), int(wall)))
    lat = {}
    for kind in ("rgb", "depth", "seg"):
        ms = [
            s["shown_ms"] - steps[s["stamp_ns"]] / 1e6
            for s in shown
            if s["kind"] == kind and s["stamp_ns"] in steps
        ]
        if len(ms) > 1:
            q = statistics.quantiles(ms, n=20)
            lat[kind] = {"n": len(ms), "p50_ms": statistics.median(ms), "p95_ms": q[18], "max_ms": max(ms)}
    res["images_matched"] = sum(v["n"] for v in lat.values())
    res["latency_render_to_shown"] = lat
    res["images_shown"] = len(shown)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="default", help="scene (default: default)")
    ap.add_argument("--seconds", type=float, default=20.0, help="wall seconds timed per window (default 20)")
    ap.add_argument("--warmup", type=float, default=3.0, help="wall seconds before timing (default 3)")
    ap.add_argument("--windows", type=int, default=2, help="windows per variant, alternating (default 2)")
    ap.add_argument("--image-hz", type=float, default=10.0, help="UI images/s per stream (default 10)")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/ui.json)")
    args = ap.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("benchmarks/ui.py needs Chromium: scripts/setup.sh --dev installs it")

    runs: dict[str, list[dict]] = {"without_ui": [], "with_ui": []}
    for i in range(args.windows):
        runs["without_ui"].append(without_ui(args))
        runs["with_ui"].append(with_ui(args, chromium))
        print(
            f"window {i + 1}: RTF without UI {runs['without_ui'][-1]['real_time_factor']:.2f}, "
            f"with UI {runs['with_ui'][-1]['real_time_factor']:.2f}"
        )
    base = statistics.mean(r["real_time_factor"] for r in runs["without_ui"])
    ui = statistics.mean(r["real_time_factor"] for r in runs["with_ui"])
    drop = 1.0 - ui / base
    print(f"lockstep RTF: {base:.2f} without the UI, {ui:.2f} with it streaming -> {100 * drop:.1f} % drop")
    for kind, v in runs["with_ui"][-1]["latency_render_to_shown"].items():
        print(f"  {kind:5s} render -> shown: p50 {v['p50_ms']:.0f} ms, p95 {v['p95_ms']:.0f} ms (n={v['n']})")
    cams = load_config(scene=args.scene).render.cameras
    write(
        "ui",
        {
            "scene": args.scene,
            "cameras": [f"{c.name} {c.width}x{c.height}" for c in cams],
            "seconds_per_window": args.seconds,
            "rtf_without_ui": base,
            "rtf_with_ui": ui,
            "rtf_drop": drop,
            "runs": runs,
        },
        args.json,
    )


if __name__ == "__main__":
    main()
