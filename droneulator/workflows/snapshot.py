"""``droneulator snapshot``: every image of every camera (of every vehicle) from a scene's spawn pose."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from droneulator.config import SimConfig
from droneulator.frames import pose_from_transform
from droneulator.imaging import depth_to_rgb, segmentation_to_rgb
from droneulator.world import FrameSet, World


def camera_info(frame: Any, t_ns: int) -> dict[str, Any]:
    """camera_info-like description of one camera image (REP 104 fields, plus the optical pose)."""
    K = frame.K
    h, w = frame.depth.shape
    pos, quat = pose_from_transform(frame.T_world_optical)
    return {
        "stamp_ns": t_ns,
        "frame_id": f"{frame.name}_optical_frame",
        "width": w,
        "height": h,
        "distortion_model": "plumb_bob",
        "D": [0.0] * 5 if frame.D is None else [float(d) for d in frame.D],
        "K": K.ravel().tolist(),
        "R": np.eye(3).ravel().tolist(),
        "P": np.hstack([K, np.zeros((3, 1))]).ravel().tolist(),
        "T_world_optical": frame.T_world_optical.tolist(),
        "optical_position": pos.tolist(),
        "optical_quaternion_xyzw": quat.tolist(),
    }


def save_frames(frames: FrameSet, out: Path, prefix: str = "", vehicle: str | None = None) -> dict[str, Path]:
    """Write RGB, depth (.npy and viewable PNG), segmentation (palette and ids) and camera info of every
    camera of ``vehicle`` (the first vehicle's for None)."""
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    cameras = frames.cameras[vehicle] if vehicle is not None else next(iter(frames.cameras.values()))
    for name, f in cameras.items():
        stem = f"{prefix}{name}"
        paths = {
            "rgb": out / f"{stem}_rgb.png",
            "depth_npy": out / f"{stem}_depth.npy",
            "depth_png": out / f"{stem}_depth.png",
            "seg": out / f"{stem}_seg.png",
            "seg_ids": out / f"{stem}_seg_ids.png",
            "camera_info": out / f"{stem}_camera_info.json",
        }
        Image.fromarray(f.rgb).save(paths["rgb"])
        np.save(paths["depth_npy"], f.depth)
        Image.fromarray(depth_to_rgb(f.depth)).save(paths["depth_png"])
        Image.fromarray(segmentation_to_rgb(f.seg)).save(paths["seg"])
        Image.fromarray(f.seg).save(paths["seg_ids"])
        paths["camera_info"].write_text(json.dumps(camera_info(f, frames.t_ns), indent=2))
        written.update({f"{name}/{k}": v for k, v in paths.items()})
    return written


def snapshot(config: SimConfig, out: Path, altitude: float = 1.5) -> dict[str, Path]:
    """Render the rig at the scene's spawn pose lifted to ``altitude`` (hovering) and save it.

    With several vehicles (config ``vehicles``), each hovers ``altitude`` above its own start and its
    images go to ``out/<vehicle>/``: every vehicle is drawn in the others' cameras."""
    with World(config=config) as world:
        if len(world.vehicles) == 1:
            world.reset(position=world.scene.spawn_position + np.array([0.0, 0.0, altitude]))
            return save_frames(world.render(), out)
        lift = np.array([0.0, 0.0, altitude])
        for v, (pos, yaw) in zip(world.vehicle_list, world.spawns(), strict=True):
            v.place(pos + lift, yaw)
        frames = world.render()
        written: dict[str, Path] = {}
        for name in frames.cameras:
            saved = save_frames(frames, out / name, vehicle=name)
            written.update({f"{name}/{k}": p for k, p in saved.items()})
        return written
