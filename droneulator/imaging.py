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


def _depth_colours(x: np.ndarray) -> np.ndarray:
    """Colour of nearness ``x`` in [0, 1] (1: at the camera): bright yellow to dark purple, uint8 RGB."""
    rgb = np.stack(
        [
            np.clip(1.6 * x - 0.2, 0, 1),
            np.clip(1.4 * x * x, 0, 1),
            np.clip(0.6 - 0.6 * x, 0, 1) * x + 0.15 * x,
        ],
        axis=-1,
    )
    return (rgb * 255).astype(np.uint8)


#: the depth colour map on 1024 levels (finer than the 8-bit colours it produces), indexed by depth
_DEPTH_LEVELS = 1024
_DEPTH_LUT = _depth_colours(1.0 - np.linspace(0.0, 1.0, _DEPTH_LEVELS))


def depth_to_rgb(depth: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """Viewable depth: near is bright yellow, far (``max_range`` and beyond) dark purple, misses (NaN)
    black. A table lookup: this runs on every image the UI shows."""
    finite = np.isfinite(depth)
    scaled = np.where(finite, depth, max_range) * ((_DEPTH_LEVELS - 1) / max_range)
    rgb = _DEPTH_LUT[np.clip(scaled, 0, _DEPTH_LEVELS - 1).astype(np.intp)]
    rgb[~finite] = 0
    return rgb


def encode_png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def encode_jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()
