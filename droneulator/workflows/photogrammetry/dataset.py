"""Stage 4 of a capture: the dataset folder, written view by view so that an interruption leaves a
valid partial dataset and a second run resumes it.

Layout::

    images/NNNN.jpg          JPEG bytes exactly as published
    segmentation/NNNN.png    the segmentation image of the same stamp (class ids, as published)
    truth/depth/NNNN.npz     its depth image (metres, float16): ground truth, for scoring only
    truth/mesh.npz           the true tree and ground around it (:mod:`.truth`), for scoring only
    sparse_known/            COLMAP text model of the known poses (PINHOLE camera, empty points3D.txt)
    poses.json, poses.csv    stamp and pose of the optical frame and of base_link in the world (map)
    metadata.json            settings, intrinsics, tracking errors and timings

Every file is replaced atomically; the images are written before the files that list them.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from droneulator.config import SimConfig
from droneulator.frames import transform_from_pose
from droneulator.ros.topics import MAP_FRAME
from droneulator.workflows.photogrammetry.colmap_model import (
    KnownModel,
    atomic_write,
    colmap_pinhole_params,
    write_text_model,
)
from droneulator.workflows.photogrammetry.record import AuxFrames


def plan_settings(cfg: SimConfig, pitch_deg: float, cam: dict[str, Any]) -> dict[str, Any]:
    """What fixes the dataset's views: a resumed capture must use exactly these."""
    c = cfg.capture
    return {
        "scene": cfg.scene,
        "seed": cfg.seed,
        "views": c.views,
        "radius": c.radius,
        "altitudes": c.ring_altitudes(),
        "arc_deg": c.arc_deg,
        "pitch_deg": round(float(pitch_deg), 6),
        "width": int(cam["width"]),
        "height": int(cam["height"]),
        "hfov_deg": round(float(cam["hfov_deg"]), 6),
    }


class DatasetMismatchError(ValueError):
    """The output folder holds a capture made with other settings."""


@dataclass
class CaptureDataset:
    """A capture folder: views are added one at a time and every file is rewritten atomically."""

    root: Path
    plan_settings: dict[str, Any]
    views: dict[int, dict[str, Any]] = field(default_factory=dict)
    camera: dict[str, Any] | None = None
    runs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @classmethod
    def open(cls, root: Path, plan_settings: dict[str, Any]) -> CaptureDataset:
        """Open ``root`` for ``plan_settings``: a new folder, or one to resume with the same settings."""
        root = Path(root)
        ds = cls(root, plan_settings)
        meta_path, poses_path = root / "metadata.json", root / "poses.json"
        if meta_path.exists():
            meta = json.loads(meta_path.read_text())
            if meta.get("plan") != plan_settings:
                diff = {
                    k: (meta.get("plan", {}).get(k), v)
                    for k, v in plan_settings.items()
                    if meta.get("plan", {}).get(k) != v
                }
                raise DatasetMismatchError(
                    f"{root} holds a capture with other settings ({diff}, as (stored, requested)); "
                    "use another --out or the stored settings"
                )
            ds.runs = list(meta.get("runs", []))
        if poses_path.exists():
            poses = json.loads(poses_path.read_text())
            ds.camera = poses.get("camera")
            for v in poses.get("views", []):
                if (ds.images_dir / v["name"]).is_file():
                    ds.views[int(v["index"])] = v
        return ds

    def set_camera(self, info: dict[str, Any]) -> None:
        if self.camera is not None and (
            self.camera["width"] != info["width"]
            or self.camera["height"] != info["height"]
            or not np.allclose(self.camera["K"], info["K"], atol=1e-9)
        ):
            raise DatasetMismatchError(
                f"{self.root}: the camera publishes {info['width']}x{info['height']} K={info['K']}, "
                f"the stored views used {self.camera['width']}x{self.camera['height']} K={self.camera['K']}"
            )
        self.camera = info

    def add(
        self, view: dict[str, Any], jpeg: bytes, run: dict[str, Any], aux: AuxFrames | None = None
    ) -> None:
        """Store one captured view: its segmentation and depth and its image first, then the files that
        list it."""
        self.store(view, jpeg, aux)
        self.write(run)

    def store(self, view: dict[str, Any], jpeg: bytes, aux: AuxFrames | None = None) -> None:
        """A view's files (segmentation, depth, image) and its entry; the lists that name it come with the
        next :meth:`write` (a view whose image is there and whose entry is not is captured again)."""
        if aux is not None:
            stem = Path(view["name"]).stem
            atomic_write(self.root / "segmentation" / f"{stem}.png", aux.segmentation_png)
            buf = io.BytesIO()
            np.savez_compressed(buf, depth=aux.depth.astype(np.float16))
            atomic_write(self.root / "truth" / "depth" / f"{stem}.npz", buf.getvalue())
        atomic_write(self.images_dir / view["name"], jpeg)
        self.views[int(view["index"])] = view

    def write(self, run: dict[str, Any] | None = None) -> None:
        views = [self.views[i] for i in sorted(self.views)]
        if self.camera is None:
            return
        poses = {
            "world_frame": MAP_FRAME,
            "camera_frame": self.camera["frame_id"],
            "conventions": "positions in metres in the world frame (ENU, z up); quaternions [x, y, z, w] "
            "rotating the frame's axes into the world; K in the OpenCV/ROS pixel convention",
            "camera": self.camera,
            "views": views,
        }
        atomic_write(self.root / "poses.json", json.dumps(poses, indent=1))
        atomic_write(self.root / "poses.csv", _poses_csv(views))
        model = KnownModel.from_views(
            np.array(self.camera["K"]),
            self.camera["width"],
            self.camera["height"],
            [(v["image_id"], v["name"], _T_world_optical(v)) for v in views],
        )
        write_text_model(self.root / "sparse_known", model)
        atomic_write(self.root / "metadata.json", json.dumps(self.metadata(run), indent=1))

    def metadata(self, run: dict[str, Any] | None) -> dict[str, Any]:
        runs = [*self.runs, run] if run is not None else self.runs
        views = [self.views[i] for i in sorted(self.views)]
        legs = [v["leg"] for v in views if v["leg"]["kind"] == "capture"]
        K = np.array(self.camera["K"]) if self.camera else None
        s = self.plan_settings
        return {
            "scene": s["scene"],
            "seed": s["seed"],
            "views": s["views"],
            "views_captured": len(views),
            "complete": len(views) == s["views"],
            "radius": s["radius"],
            "altitudes": s["altitudes"],
            "pitch_deg": s["pitch_deg"],
            "resolution": [s["width"], s["height"]],
            "hfov_deg": s["hfov_deg"],
            "K": K.tolist() if K is not None else None,
            "colmap_pinhole": colmap_pinhole_params(K).tolist() if K is not None else None,
            "pixel_convention": "K: OpenCV/ROS (pixel centres at integers); COLMAP PINHOLE: cx, cy + 0.5",
            "tracking": {
                "per_view": {
                    v["name"]: {
                        "kind": v["leg"]["kind"],
                        "max_path_error_m": v["leg"]["max_path_error_m"],
                        "max_altitude_error_m": v["leg"]["max_altitude_error_m"],
                    }
                    for v in views
                },
                "max_path_error_m": max((g["max_path_error_m"] for g in legs), default=None),
                "max_altitude_error_m": max((g["max_altitude_error_m"] for g in legs), default=None),
                "capture_legs": len(legs),
                # gotos that ended within the acceptance radius without settling (wind; accept_after_s)
                "unsettled_gotos": sum(v["leg"].get("unsettled", 0) for v in views),
            },
            "plan": s,
            "runs": runs,
            "timings": {
                "capture_wall_s": sum(r.get("wall_s", 0.0) for r in runs),
                "sim_s": sum(r.get("sim_s", 0.0) for r in runs),
            },
        }

    def finish_run(self, run: dict[str, Any]) -> None:
        self.runs.append(run)
        self.write()


def _T_world_optical(view: dict[str, Any]) -> np.ndarray:
    o = view["optical"]
    return transform_from_pose(np.array(o["position"]), np.array(o["quaternion_xyzw"]))


def _poses_csv(views: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    cols = ["x", "y", "z", "qx", "qy", "qz", "qw"]
    w.writerow(["index", "name", "stamp_ns", *(f"optical_{c}" for c in cols), *(f"base_{c}" for c in cols)])
    for v in views:
        o, b = v["optical"], v["base_link"]
        w.writerow(
            [
                v["index"],
                v["name"],
                v["stamp_ns"],
                *(repr(float(x)) for x in [*o["position"], *o["quaternion_xyzw"]]),
                *(repr(float(x)) for x in [*b["position"], *b["quaternion_xyzw"]]),
            ]
        )
    return buf.getvalue()
