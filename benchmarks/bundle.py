"""Cold start of the PyInstaller bundle against the virtualenv, and the bundle's size.

Cold start = wall time from starting ``droneulator run --scene default`` to the first colour image
received on Zenoh (three processes started, scene built, first frame rendered, encoded and
published). Both installations run the same checkout, interleaved round by round (the order
alternates), in two numba cache states:

* ``warm``: numba's cache already holds the compiled kernels (every launch after the first);
* ``empty``: a fresh numba cache (the first launch after installing). Kernels compile when first
  called, so only those called before the first frame count here.

The bundle runs in a clean environment (``env -i``-like: HOME and PATH only); the venv runs this
interpreter with the checkout on PYTHONPATH. A Zenoh peer listens on a free port and each run
connects to it (``bridge.connect``), so no reconnection back-off enters the measurement.

    bash scripts/package.sh && python benchmarks/bundle.py --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh
from _common import write

from droneulator.runtime.launch import free_port

ROOT = Path(__file__).resolve().parents[1]
FRAME_KEY = "droneulator/front/color/image_raw/compressed"


def folder_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


class FirstFrame:
    """A Zenoh peer listening on ``endpoint``; :meth:`wait` returns when the next image arrives."""

    def __init__(self, endpoint: str) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.event = threading.Event()
        self.sub = self.session.declare_subscriber(FRAME_KEY, lambda _sample: self.event.set())

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def launch(cmd: list[str], env: dict[str, str], frames: FirstFrame, timeout: float, log: Path) -> float:
    """Start ``cmd`` (output to ``log``), return the seconds until its first image arrives, then stop it."""
    frames.event.clear()
    with open(log, "w") as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = t0 + timeout
            while not frames.event.wait(0.01):
                if proc.poll() is not None:
                    raise RuntimeError(f"{cmd[0]} exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
                if time.perf_counter() > deadline:
                    raise RuntimeError(
                        f"no frame from {cmd[0]} within {timeout:g} s:\n{log.read_text()[-3000:]}"
                    )
            return time.perf_counter() - t0
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--bundle", default=str(ROOT / "dist" / "droneulator" / "droneulator"), help="bundle program"
    )
    ap.add_argument("--rounds", type=int, default=3, help="launches per installation and cache state")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for a first frame")
    ap.add_argument("--json", default=None, help="output path (default benchmarks/results/bundle.json)")
    args = ap.parse_args()
    exe = Path(args.bundle).resolve()
    if not os.access(exe, os.X_OK):
        ap.error(f"no bundle at {exe}: build it with `bash scripts/package.sh`")
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")

    listen = f"tcp/127.0.0.1:{free_port()}"
    frames = FirstFrame(listen)
    tmp = tempfile.TemporaryDirectory(prefix="droneulator-bundle-bench-")
    warm_home, warm_numba = Path(tmp.name, "home-warm"), Path(tmp.name, "numba-warm")
    warm_home.mkdir()
    log = Path(tmp.name, "run.log")

    def command(kind: str) -> list[str]:
        base = [str(exe)] if kind == "bundle" else [sys.executable, "-m", "droneulator.cli"]
        return base + [
            "run",
            "--scene",
            "default",
            "--api-port",
            str(free_port()),
            "--set",
            f'bridge.listen=["tcp/127.0.0.1:{free_port()}"]',
            "--set",
            f'bridge.connect=["{listen}"]',
        ]

    def environment(kind: str, cache: str, i: int) -> dict[str, str]:
        if kind == "bundle":
            home = warm_home if cache == "warm" else Path(tmp.name, f"home-empty-{i}")
            home.mkdir(exist_ok=True)
            return {"HOME": str(home), "PATH": "/usr/bin:/bin"}
        numba = warm_numba if cache == "warm" else Path(tmp.name, f"numba-empty-{i}")
        return {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(numba)}

    results: dict[str, dict[str, list[float]]] = {"venv": {}, "bundle": {}}
    try:
        for kind in ("venv", "bundle"):  # fill the warm caches (not measured)
            launch(command(kind), environment(kind, "warm", 0), frames, args.timeout, log)
        for i in range(args.rounds):
            order = ("venv", "bundle") if i % 2 == 0 else ("bundle", "venv")
            for cache in ("warm", "empty"):
                for kind in order:
                    s = launch(command(kind), environment(kind, cache, i), frames, args.timeout, log)
                    results[kind].setdefault(cache, []).append(s)
                    print(
                        f"round {i + 1}: {kind:6s} {cache:5s} cache: first frame after {s:6.2f} s", flush=True
                    )
    finally:
        frames.close()
        tmp.cleanup()

    summary = {
        cache: {
            "venv_median_s": statistics.median(results["venv"][cache]),
            "bundle_median_s": statistics.median(results["bundle"][cache]),
            "ratio": statistics.median(results["bundle"][cache]) / statistics.median(results["venv"][cache]),
        }
        for cache in ("warm", "empty")
    }
    tarballs = sorted(exe.parent.parent.glob("droneulator-*.tar.gz"))
    sizes = {
        "folder_mb": folder_size(exe.parent) / 1e6,
        "tarball_mb": tarballs[-1].stat().st_size / 1e6 if tarballs else None,
        "tarball": tarballs[-1].name if tarballs else None,
    }
    for cache, s in summary.items():
        print(
            f"{cache:5s} numba cache: venv {s['venv_median_s']:.2f} s, bundle {s['bundle_median_s']:.2f} s "
            f"(bundle/venv {s['ratio']:.2f})"
        )
    print(f"bundle folder {sizes['folder_mb']:.0f} MB, tarball {sizes['tarball_mb'] or 0:.0f} MB")
    write(
        "bundle",
        {"rounds": args.rounds, "samples_s": results, "summary": summary, "size": sizes, "bundle": str(exe)},
        args.json,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
