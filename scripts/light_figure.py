"""The figure of docs/light.md: one vineyard view at 08:00, 12:00, 18:00 and 20:00 (midsummer, the PX4
home), then overcast at noon and in fog, side by side in ``docs/img/light_strip.png``.

Usage: ``python scripts/light_figure.py [--out DIR]`` (a few seconds on llvmpipe).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from droneulator import frames
from droneulator.config import CameraConfig, LightConfig, SimConfig
from droneulator.render import Renderer
from droneulator.render.renderer import config_lighting
from droneulator.scenes import get_scene

#: the light settings drawn, and their captions
VIEWS = [
    (LightConfig(time_of_day_h=8.0), "08:00"),
    (LightConfig(time_of_day_h=12.0), "12:00"),
    (LightConfig(time_of_day_h=18.0), "18:00"),
    (LightConfig(time_of_day_h=20.0), "20:00"),
    (LightConfig(time_of_day_h=12.0, cloud_cover=1.0), "12:00, overcast"),
    (LightConfig(time_of_day_h=12.0, cloud_cover=0.5, visibility_m=60.0), "12:00, fog (V = 60 m)"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "img")
    args = ap.parse_args()
    scene = get_scene("vineyard", 0)
    cam = CameraConfig(name="view", width=400, height=266, hfov_deg=80.0, rpy_deg=(0.0, 18.0, 0.0))
    yaw = 0.35  # looking along the rows, a little across them
    pose = frames.make_transform(
        frames.quat_to_matrix(frames.quat_from_yaw(yaw)), scene.spawn_position + np.array([0.0, -1.2, 3.5])
    )
    config = SimConfig()
    images = []
    with Renderer(scene, [cam], shadow_map_size=4096) as r:
        for light, caption in VIEWS:
            config.light = light
            lighting = config_lighting(scene, config)
            r.set_light(lighting)
            img = Image.fromarray(r.render(pose)["view"].rgb.copy())
            sun = f"sun {lighting.elevation_deg:.0f} deg up, azimuth {lighting.azimuth_deg:.0f} deg"
            ImageDraw.Draw(img).text((8, 6), f"{caption}: {sun}", fill=(255, 255, 255))
            images.append(img)
    w, h = images[0].size
    strip = Image.new("RGB", (3 * w, 2 * h))
    for i, img in enumerate(images):
        strip.paste(img, ((i % 3) * w, (i // 3) * h))
    strip.save(args.out / "light_strip.png", optimize=True)
    print(f"wrote {args.out / 'light_strip.png'}")


if __name__ == "__main__":
    main()
