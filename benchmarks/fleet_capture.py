"""A capture flown by one vehicle and by two, camera triggered or continuous: wall time and
reconstruction figures, same views.

``droneulator capture`` of the photogrammetry benchmark's tree (tree_inspection, seed 0, 1024x768, 36
views on two rings) is flown with ``capture.vehicles`` 1 and 2 into fresh datasets, one after the
other, with the camera triggered at each view (the default: nothing rendered between views) and, with
``--modes`` naming it, continuous (``--continuous``: every vehicle's camera at ``capture.camera_hz`` of
sim time, which in lockstep on a CPU renderer sets the wall time); then ``droneulator reconstruct``
(defaults: SIFT masked to the tree, triangulation and BA with pose priors, CPU dense stereo, scoring
against the true tree) runs on each dataset of ``--reconstruct-modes``. Prints capture wall and sim
time, the camera frames rendered, the CPU time of each capture (client and simulator: whether the
cores were the limit) and the load average around it, how far each dataset's camera
poses are from the first one's, and the reconstruction figures as ``benchmarks/photogrammetry.py``
reports them; writes ``benchmarks/results/fleet_capture.json``.

    .venv/bin/python benchmarks/fleet_capture.py                  # 36 views, 1 and 2 vehicles, both modes
    .venv/bin/python benchmarks/fleet_capture.py --modes triggered --views 18 --no-reconstruct
    .venv/bin/python benchmarks/fleet_capture.py --reuse          # reconstruct the datasets again
    # at real time, as a crew in the field would wait (lockstep capped at 1 sim s per wall s)
    .venv/bin/python benchmarks/fleet_capture.py --modes triggered --no-reconstruct --set runtime.max_speed=1
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write  # noqa: E402

from droneulator.config import load_config  # noqa: E402
from droneulator.workflows.photogrammetry.capture import capture  # noqa: E402
from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct  # noqa: E402


def capture_row(
    out: Path, meta: dict[str, Any], camera_hz: float, vehicles: int, triggered: bool
) -> dict[str, Any]:
    """Capture figures of a dataset's metadata (its last run that captured anything). Frames rendered:
    triggered, one per view and one per vehicle for its camera_info; continuous, every vehicle's camera
    at ``camera_hz`` of sim time. ``legs_sim_s``: the sim time of the legs that brought each vehicle to
    its views (flight and settling; the busiest vehicle's), what a real vehicle would fly; the run's
    ``sim_s`` also counts the hovering while the capture records a view, which a lockstep simulator
    free of rendering spends at tens of times real time."""
    run = [r for r in meta["runs"] if r["captured"]][-1]
    t = run.get("timings", {})
    frames = run["captured"] + vehicles if triggered else round(run["sim_s"] * camera_hz) * vehicles
    legs: dict[str, float] = {}
    for v in json.loads((out / "poses.json").read_text())["views"]:
        name = v.get("vehicle", "uav0")
        legs[name] = legs.get(name, 0.0) + v["leg"]["flight_sim_s"] + v["leg"]["settle_sim_s"]
    return {
        "captured": run["captured"],
        "wall_s": run["wall_s"],
        "sim_s": run["sim_s"],
        "legs_sim_s": round(max(legs.values()), 2),
        "frames_rendered": frames,
        "startup_s": t.get("startup_s"),
        "flight_s": t.get("flight_s"),
        "views_per_vehicle": run.get("vehicles"),
        "max_path_error_m": meta["tracking"]["max_path_error_m"],
        "max_altitude_error_m": meta["tracking"]["max_altitude_error_m"],
    }


def cpu_seconds() -> float:
    """CPU time (user and system) of this process and of its children that have ended: a capture's
    client and the simulator it started (its processes end with it)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def reconstruction_row(report: dict[str, Any]) -> dict[str, Any]:
    """The figures ``benchmarks/photogrammetry.py`` reports of one reconstruction."""
    score = report.get("score") or {}
    sp, tree = score.get("sparse", {}), (score.get("dense") or {}).get("tree", {})
    return {
        "sparse_points": report["sparse_points"],
        "sparse_tree_points": sp.get("tree", {}).get("points"),
        "registered_images": report["registered_images"],
        "mean_track_length": report["mean_track_length"],
        "reproj_px": report["mean_reprojection_error_px"],
        "known_pose_reproj_px": report["known_pose_reprojection"]["mean_px"],
        "dense_points": report["dense"].get("dense_points"),
        "dense_tree_points": tree.get("points"),
        "accuracy_median_m": tree.get("accuracy_median_m"),
        "accuracy_p90_m": tree.get("accuracy_p90_m"),
        "completeness": tree.get("completeness"),
        "completeness_visible": tree.get("completeness_visible"),
        "sparse_time_s": report["times_s"]["sparse_total"],
        "dense_time_s": report["times_s"].get("dense"),
    }


def pose_differences(a: Path, b: Path) -> dict[str, Any]:
    """How far the optical frames of the same views of two datasets are apart (position, m; angle, deg)."""
    va = {v["name"]: v for v in json.loads((a / "poses.json").read_text())["views"]}
    vb = {v["name"]: v for v in json.loads((b / "poses.json").read_text())["views"]}
    dp, da = [], []
    for name in sorted(va.keys() & vb.keys()):
        oa, ob = va[name]["optical"], vb[name]["optical"]
        dp.append(float(np.linalg.norm(np.subtract(oa["position"], ob["position"]))))
        dot = abs(float(np.dot(oa["quaternion_xyzw"], ob["quaternion_xyzw"])))
        da.append(math.degrees(2 * math.acos(min(1.0, dot))))
    return {
        "same_names": sorted(va) == sorted(vb),
        "views": len(dp),
        "max_position_m": max(dp, default=None),
        "max_angle_deg": max(da, default=None),
        "vehicles": sorted({v.get("vehicle", "uav0") for v in vb.values()}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--views", type=int, default=36, help="views of each capture (default 36: two rings)")
    ap.add_argument(
        "--vehicles", type=int, nargs="+", default=[1, 2], help="vehicle counts to capture with (default 1 2)"
    )
    ap.add_argument(
        "--modes", nargs="+", choices=("triggered", "continuous"), default=["triggered", "continuous"]
    )
    ap.add_argument(
        "--reconstruct-modes",
        nargs="+",
        choices=("triggered", "continuous"),
        default=["triggered"],
        help="the modes whose datasets are reconstructed (default: triggered)",
    )
    ap.add_argument("--out", default="out/bench_fleet_capture", help="datasets go to OUT/vehicles_N")
    ap.add_argument("--reuse", action="store_true", help="keep complete datasets instead of capturing again")
    ap.add_argument("--no-reconstruct", action="store_true", help="captures only")
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override for every capture (e.g. runtime.max_speed=1: at real time)",
    )
    ap.add_argument("--json", default=None, help="output JSON (default: benchmarks/results/)")
    args = ap.parse_args()

    outs = {(mode, n): Path(args.out) / f"{mode}_vehicles_{n}" for mode in args.modes for n in args.vehicles}
    rows: dict[tuple[str, int], dict[str, Any]] = {}
    for (mode, n), out in outs.items():  # the captures first, one after the other, under the same load
        cfg = load_config(None, args.overrides, scene="tree_inspection")
        cfg.capture.views = args.views
        cfg.capture.vehicles = n
        cfg.capture.trigger = mode == "triggered"
        meta_path = out / "metadata.json"
        load = [os.getloadavg()[0]]
        cpu0 = cpu_seconds()
        if args.reuse and meta_path.exists() and json.loads(meta_path.read_text())["complete"]:
            meta = json.loads(meta_path.read_text())
        else:
            shutil.rmtree(out, ignore_errors=True)
            meta = capture(cfg, out, progress=False)
        load.append(os.getloadavg()[0])
        rows[mode, n] = {
            "mode": mode,
            "vehicles": n,
            "capture": capture_row(out, meta, cfg.capture.camera_hz, n, cfg.capture.trigger),
            "load_avg_1min": load,
            "cpu_s": round(cpu_seconds() - cpu0, 2),
        }
        print(f"{mode}, {n} vehicle(s): {rows[mode, n]['capture']}", flush=True)
    base = next(iter(outs.values()))
    for key, out in outs.items():
        rows[key]["poses_vs_first"] = pose_differences(base, out)
        if not args.no_reconstruct and key[0] in args.reconstruct_modes:
            rows[key]["reconstruction"] = reconstruction_row(reconstruct(out, ReconstructOptions()))

    c = load_config(None, args.overrides, scene="tree_inspection").capture
    print(
        f"\ntree_inspection (seed 0), {args.views} views, {c.width}x{c.height}, radius {c.radius} m, "
        f"speed {c.speed} m/s; captures one after the other, then the reconstructions"
    )
    head = (
        f"{'mode':>10} | {'vehicles':>8} | {'wall s':>7} | {'sim s':>6} | {'legs sim s':>10} | "
        f"{'startup s':>9} | "
        f"{'flight s':>8} | "
        f"{'frames':>6} | {'CPU s':>5} | {'load':>9} | "
        f"{'pose diff cm / deg':>18} | {'sparse (tree)':>15} | {'dense on tree':>13} | "
        f"{'acc med / p90 cm':>16} | {'compl. all / seen':>17}"
    )
    print(head)
    print("-" * len(head))
    for (mode, n), r in rows.items():
        cap, d, rec = r["capture"], r["poses_vs_first"], r.get("reconstruction") or {}
        acc = (
            f"{rec['accuracy_median_m'] * 100:.2f} / {rec['accuracy_p90_m'] * 100:.2f}"
            if rec.get("accuracy_median_m") is not None
            else "-"
        )
        comp = (
            f"{rec['completeness'] * 100:.1f} / {rec['completeness_visible'] * 100:.1f} %"
            if rec.get("completeness") is not None
            else "-"
        )
        sparse = f"{rec['sparse_points']} ({rec['sparse_tree_points']})" if rec else "-"
        diff = f"{d['max_position_m'] * 100:.2f} / {d['max_angle_deg']:.3f}"
        print(
            f"{mode:>10} | {n:>8} | {cap['wall_s']:>7.1f} | {cap['sim_s']:>6.1f} | "
            f"{cap['legs_sim_s']:>10.1f} | "
            f"{cap['startup_s'] or 0:>9.1f} | "
            f"{cap['flight_s'] or 0:>8.1f} | {cap['frames_rendered']:>6} | {r['cpu_s']:>5.1f} | "
            f"{r['load_avg_1min'][0]:>4.1f} {r['load_avg_1min'][1]:>4.1f} | {diff:>18} | {sparse:>15} | "
            f"{rec.get('dense_tree_points') or '-':>13} | {acc:>16} | {comp:>17}"
        )
    ratios, sim_ratios = {}, {}
    for (mode, n), r in rows.items():
        one = rows.get((mode, min(args.vehicles)))
        cont = rows.get(("continuous", n))
        if one is not None and one is not r:
            ratios[f"{mode} {n} vs 1 vehicle"] = round(r["capture"]["wall_s"] / one["capture"]["wall_s"], 3)
            ratios[f"{mode} {n} vs 1 vehicle, flight"] = round(
                (r["capture"]["flight_s"] or 0) / (one["capture"]["flight_s"] or 1), 3
            )
            for key in ("sim_s", "legs_sim_s"):
                sim_ratios[f"{mode} {n} vs 1 vehicle, {key}"] = round(
                    r["capture"][key] / one["capture"][key], 3
                )
        if mode == "triggered" and cont is not None:
            ratios[f"triggered vs continuous, {n} vehicle(s)"] = round(
                r["capture"]["wall_s"] / cont["capture"]["wall_s"], 3
            )
    for k, v in ratios.items():
        print(f"wall time, {k}: {v:.2f}x")
    for k, v in sim_ratios.items():
        print(f"sim time, {k}: {v:.2f}x")
    write(
        "fleet_capture",
        {
            "scene": "tree_inspection",
            "views": args.views,
            "capture": {
                "width": c.width,
                "height": c.height,
                "radius": c.radius,
                "speed": c.speed,
                "camera_hz": c.camera_hz,
                "state_hz_triggered": c.state_hz,
            },
            "overrides": args.overrides,
            "rows": list(rows.values()),
            "wall_ratios": ratios,
            "sim_ratios": sim_ratios,
        },
        args.json,
    )


if __name__ == "__main__":
    main()
