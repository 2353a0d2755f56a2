"""Paper Table III: photogrammetry capture and COLMAP reconstruction at 18, 36 and 54 views.

For each density: ``droneulator capture`` (its own simulator subprocess, commands over WebSocket, data
over Zenoh) into a fresh dataset, then ``droneulator reconstruct`` (pycolmap on the CPU). Prints the
figures beside the paper's and writes ``benchmarks/results/photogrammetry.json``.

    .venv/bin/python benchmarks/photogrammetry.py                      # 18, 36, 54 views at 1024x768
    .venv/bin/python benchmarks/photogrammetry.py --views 18 --width 640 --height 480
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write  # noqa: E402

from droneulator.config import load_config  # noqa: E402
from droneulator.workflows.photogrammetry.capture import capture  # noqa: E402
from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct  # noqa: E402

#: paper Table III (dense stereo included in the time, on the authors' GPU machine)
PAPER = {
    18: {"sparse_points": 149, "mean_track_length": 3.09, "reproj_px": 0.79, "time_min": 3.9},
    36: {"sparse_points": 1156, "mean_track_length": 3.72, "reproj_px": 0.74, "time_min": 8.4},
    54: {"sparse_points": 2760, "mean_track_length": 4.15, "reproj_px": 0.72, "time_min": 11.8},
}


def tree_points(dataset: Path, meta: dict) -> int:
    """Sparse points on the tree itself: within the crown radius (+0.5 m) of the trunk and 0.3 m above
    the ground (the rest is ground and background)."""
    import numpy as np
    import pycolmap

    from droneulator.scenes import get_scene

    scene = get_scene(meta["scene"], meta["seed"])
    trunk = np.asarray(scene.landmarks["tree"], dtype=float)
    reach = float(scene.landmarks["crown_radius"][0]) + 0.5
    rec = pycolmap.Reconstruction(dataset / "sparse")
    X = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    return int(((np.hypot(*(X[:, :2] - trunk[:2]).T) < reach) & (X[:, 2] > 0.3)).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, nargs="+", default=[18, 36, 54])
    ap.add_argument("--width", type=int, default=None, help="default: capture.width (1024)")
    ap.add_argument("--height", type=int, default=None, help="default: capture.height (768)")
    ap.add_argument("--out", default="out/bench_photogrammetry", help="datasets go to OUT/views_N")
    ap.add_argument("--reuse", action="store_true", help="keep complete datasets instead of capturing again")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", default=None, help="output JSON (default: benchmarks/results/)")
    args = ap.parse_args()

    rows = []
    for n in args.views:
        cfg = load_config(None, args.overrides, scene="tree_inspection")
        cfg.capture.views = n
        if args.width:
            cfg.capture.width = args.width
        if args.height:
            cfg.capture.height = args.height
        out = Path(args.out) / f"views_{n}"
        meta_path = out / "metadata.json"
        if args.reuse and meta_path.exists() and json.loads(meta_path.read_text())["complete"]:
            meta = json.loads(meta_path.read_text())
        else:
            shutil.rmtree(out, ignore_errors=True)
            meta = capture(cfg, out, progress=False)
        report = reconstruct(out, ReconstructOptions())
        runs = [r for r in meta["runs"] if r["captured"]]
        rows.append(
            {
                "views": n,
                "sparse_points": report["sparse_points"],
                "mean_track_length": report["mean_track_length"],
                "reproj_px": report["mean_reprojection_error_px"],
                "known_pose_reproj_px": report["known_pose_reprojection"]["mean_px"],
                "sparse_time_s": report["times_s"]["sparse_total"],
                "stage_times_s": report["times_s"],
                "image_pairs": report["image_pairs"],
                "capture_wall_s": sum(r["wall_s"] for r in runs),
                "capture_sim_s": sum(r["sim_s"] for r in runs),
                "max_path_error_m": meta["tracking"]["max_path_error_m"],
                "max_altitude_error_m": meta["tracking"]["max_altitude_error_m"],
                "tree_points": tree_points(out, meta),
                "dense": report["dense"],
                "paper": PAPER.get(n),
            }
        )

    c = cfg.capture
    print(
        f"\ntree_inspection, {c.width}x{c.height}, hfov {c.hfov_deg} deg, radius {c.radius} m, "
        f"altitudes {c.altitudes} m, speed {c.speed} m/s; reconstruction on the CPU (sparse only)"
    )
    head = (
        f"{'views':>5} | {'sparse pts (paper)':>19} | {'track (paper)':>14} | {'reproj px (paper)':>18} | "
        f"{'tree pts':>8} | {'sparse s':>8} | {'paper min':>9} | {'capture s':>9} | "
        f"{'max path/alt err m':>18}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        p = r["paper"] or {}
        print(
            f"{r['views']:>5} | {r['sparse_points']:>8} ({p.get('sparse_points', '-'):>7}) | "
            f"{r['mean_track_length']:>5.2f} ({p.get('mean_track_length', '-'):>5}) | "
            f"{r['reproj_px']:>6.3f} ({p.get('reproj_px', '-'):>6}) | {r['tree_points']:>8} | "
            f"{r['sparse_time_s']:>8.1f} | "
            f"{p.get('time_min', '-'):>9} | {r['capture_wall_s']:>9.1f} | "
            f"{r['max_path_error_m']:.3f} / {r['max_altitude_error_m']:.3f}"
        )
    write(
        "photogrammetry",
        {
            "scene": "tree_inspection",
            "capture": {
                "width": c.width,
                "height": c.height,
                "hfov_deg": c.hfov_deg,
                "radius": c.radius,
                "altitudes": c.altitudes,
                "pitch_deg": c.pitch_deg,
                "speed": c.speed,
                "camera_hz": c.camera_hz,
                "jpeg_quality": c.jpeg_quality,
            },
            "reconstruct": vars(ReconstructOptions()),
            "rows": rows,
        },
        args.json,
    )


if __name__ == "__main__":
    main()
