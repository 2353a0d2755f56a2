"""Where the UI tests save their screenshots: ``out/screenshots`` (ignored by git), so a test run leaves
the checkout clean; ``DRONEULATOR_SCREENSHOTS=docs/img`` refreshes the README's figures instead."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHOTS = ROOT / os.environ.get("DRONEULATOR_SCREENSHOTS", "out/screenshots")
SHOTS.mkdir(parents=True, exist_ok=True)
