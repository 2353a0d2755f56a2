"""Image encodings shared by the snapshot, the demo and the bridge."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from droneulator.scenes.base import palette_lut

_LUT = palette_lut()


def segmentation_to_rgb(seg: np.ndarray) -> np.ndarray:
    """Class-id image (H, W) uint8 -> palette colours (H, W, 3) uint8."""
    return _LUT[seg]


def depth_to_rgb(depth: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """Viewable depth: near is bright yellow, far dark purple, misses (NaN) black."""
    d = np.clip(np.nan_to_num(depth, nan=max_range) / max_range, 0.0, 1.0)
    x = 1.0 - d
    rgb = np.stack(
        [
            np.clip(1.6 * x - 0.2, 0, 1),
            np.clip(1.4 * x * x, 0, 1),
            np.clip(0.6 - 0.6 * x, 0, 1) * x + 0.15 * x,
        ],
        axis=-1,
    )
    rgb[~np.isfinite(depth)] = 0.0
    return (rgb * 255).astype(np.uint8)


def encode_png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def encode_jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()
