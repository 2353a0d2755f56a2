"""What the browser UI costs the simulation, and how old the images it shows are.

Side by side in one benchmark run, ``droneulator run`` in lockstep (640x480 rig, default scene) flies
the same slow velocity-mode circle twice, ``--windows`` times each, alternating:

1. without a UI,
2. with ``--ui`` and a headless Chromium showing the flight view (every camera stream at the UI's
   default 10 Hz).

The browser is a plain ``chromium --headless`` process, as a person's browser would be: no automation
framework is attached while the time is measured. Playwright (which the UI tests use) enables the
DevTools network domain, which copies every WebSocket frame the page receives (each camera image) to
its driver: that doubled the browser's CPU and is not a cost of the UI. The page is read through a
bare DevTools connection that only evaluates expressions (``Runtime.evaluate``), before and after the
timed window.

Real-time factor = simulated seconds / wall seconds over ``--seconds`` of wall time (after a warm-up).
The UI's requirement (issue 12) is a drop of at most 10 %. CPU time per process group (the simulation's
processes, the UI server, Chromium) over the same window is reported too, in cores (CPU seconds per
wall second), to say where the cost goes.

Image latency: the dynamics server logs the wall time at the end of each physics step that produced a
state (``bridge.latency_log``, stream ``odom``; where a stamp has none, the bridge's mark right after the
render is used); the page logs, per image it shows, the image's stamp and
the wall time it appeared (``window.droneulatorUI.cameras.shown``). The difference is render -> shown:
render, publish over Zenoh, the UI's encoding and the WebSocket to the page, and the page's decoding.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from _common import write
from websockets.sync.client import connect

from droneulator.config import load_config
from droneulator.runtime.launch import free_port, launch_run


def fly(run) -> object:
    client = run.client(timeout=120)
    client.subscribe(["events"])
    client.takeoff(altitude=2.0)
    client.wait_for_event("arrived", timeout=300)
    client.velocity(0.5, 0.3)
    return client


_TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds() -> dict[int, tuple[str, float]]:
    """Command line and user + system CPU seconds of every process."""
    out = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        out[int(pid)] = (cmd, (int(fields[11]) + int(fields[12])) / _TICK)
    return out


def cpu_group(cmd: str) -> str | None:
    if "chromium" in cmd or "chrome" in cmd:
        return "chromium"
    for module in ("render_server", "bridge", "dynamics_server"):
        if f"droneulator.runtime.{module}" in cmd:
            return module
    if "droneulator" in cmd and " run " in f" {cmd} ":
        return "run (supervisor, UI server)"
    return None


def cores_used(before: dict, after: dict, wall: float) -> dict[str, float]:
    """CPU seconds per wall second of each process group between two :func:`cpu_seconds` snapshots."""
    groups: dict[str, float] = {}
    for pid, (cmd, t) in after.items():
        group = cpu_group(cmd)
        if group is not None:
            t0 = before[pid][1] if pid in before and before[pid][0] == cmd else 0.0
            groups[group] = groups.get(group, 0.0) + (t - t0) / wall
    return {k: round(v, 3) for k, v in sorted(groups.items())}


def measure_rtf(client, seconds: float, warmup: float) -> dict:
    time.sleep(warmup)
    c0 = cpu_seconds()
    t0, w0 = client.state()["t"], time.monotonic()
    time.sleep(seconds)
    t1, w1 = client.state()["t"], time.monotonic()
    c1 = cpu_seconds()
    return {
        "sim_seconds": t1 - t0,
        "wall_seconds": w1 - w0,
        "real_time_factor": (t1 - t0) / (w1 - w0),
        "cores": cores_used(c0, c1, w1 - w0),
    }


class Page:
    """A bare DevTools connection to a Chromium tab that only evaluates expressions (no event domain
    enabled, so the browser sends nothing while the benchmark waits)."""

    def __init__(self, port: int, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            try:
                from urllib.request import urlopen

                tabs = json.loads(urlopen(f"http://127.0.0.1:{port}/json", timeout=2).read())
                url = next(t["webSocketDebuggerUrl"] for t in tabs if t.get("type") == "page")
                break
            except (OSError, StopIteration, ValueError):
                if time.monotonic() > deadline:
                    raise TimeoutError("Chromium's DevTools endpoint did not come up") from None
                time.sleep(0.2)
        self._connection = connect(url, max_size=None, open_timeout=10)
        self.ws = self._connection.__enter__()
        self.next_id = 0

    def evaluate(self, expression: str):
        self.next_id += 1
        self.ws.send(
            json.dumps(
                {
                    "id": self.next_id,
                    "method": "Runtime.evaluate",
                    "params": {"expression": expression, "returnByValue": True},
                }
            )
        )
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == self.next_id:
                break
        result = reply.get("result", {})
        if "exceptionDetails" in result or "error" in reply:
            raise RuntimeError(f"{expression}: {reply}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float) -> None:
        """Until ``expression`` is true (errors while the page loads count as false)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                if self.evaluate(expression):
                    return
            except RuntimeError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page never had {expression}")
            time.sleep(0.2)

    def close(self) -> None:
        self._connection.__exit__(None, None, None)


def devtools_port(profile: Path, timeout: float = 60.0) -> int:
    """The port Chromium chose for ``--remote-debugging-port=0`` (written to its profile folder)."""
    deadline = time.monotonic() + timeout
    path = profile / "DevToolsActivePort"
    while not path.is_file() or not path.read_text().strip():
        if time.monotonic() > deadline:
            raise TimeoutError("Chromium did not start")
        time.sleep(0.1)
    return int(path.read_text().split()[0])


def without_ui(args: argparse.Namespace) -> dict:
    """The baseline: the same run with the same latency log (only the UI and the browser differ)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(scene=args.scene, overrides=[f"bridge.latency_log={Path(tmp) / 'latency.log'}"])
        with launch_run(cfg, ["--lockstep"], start_timeout=180) as run:
            client = fly(run)
            res = measure_rtf(client, args.seconds, args.warmup)
            client.close()
    return res


def with_ui(args: argparse.Namespace, chromium: str) -> dict:
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "latency.log"
        overrides = [f"bridge.latency_log={log}", f"ui.image_hz={args.image_hz}"]
        cfg = load_config(scene=args.scene, overrides=overrides)
        with launch_run(cfg, ["--lockstep", "--ui-port", str(port)], start_timeout=180) as run:
            profile = Path(tmp) / "chromium-profile"
            browser = subprocess.Popen(
                [
                    chromium,
                    "--headless",
                    "--no-sandbox",
                    "--no-first-run",
                    "--window-size=1500,1000",
                    f"--user-data-dir={profile}",
                    "--remote-debugging-port=0",
                    f"http://127.0.0.1:{port}/#fly",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            try:
                page = Page(devtools_port(profile))
                page.wait_for("window.droneulatorUI && window.droneulatorUI.cameras.count > 5", 180)
                client = fly(run)
                res = measure_rtf(client, args.seconds, args.warmup)
                shown = page.evaluate("window.droneulatorUI.cameras.shown")
                res["page_errors"] = page.evaluate("window.droneulatorUI.cameras.errors")
                page.close()
            finally:
                browser.terminate()
                browser.wait(30)
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
            f"with UI {runs['with_ui'][-1]['real_time_factor']:.2f}; cores with UI: "
            + ", ".join(f"{k} {v:.2f}" for k, v in runs["with_ui"][-1]["cores"].items())
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
