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
#: the same with one black row after the last level, for pixels with no depth
_DEPTH_LUT_MISS = np.vstack([_DEPTH_LUT, np.zeros((1, 3), np.uint8)])


def depth_to_rgb(depth: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """Viewable depth: near is bright yellow, far (``max_range`` and beyond) dark purple, misses (NaN,
    infinities) black. A table lookup in float32 with ``np.take`` (the UI runs it on every depth image it
    shows: 0.3 ms at 320x240, against 1.7 ms with float64 and fancy indexing)."""
    scaled = np.multiply(depth, np.float32((_DEPTH_LEVELS - 1) / max_range), dtype=np.float32)
    np.clip(scaled, 0, _DEPTH_LEVELS - 1, out=scaled)
    scaled[~np.isfinite(depth)] = _DEPTH_LEVELS  # the table's last row: black
    return np.take(_DEPTH_LUT_MISS, scaled.astype(np.intp), axis=0)


def encode_png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def encode_jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()
