"""Settings of ``droneulator capture`` (the ``capture`` section of a config file and of ``--set``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CaptureConfig:
    """Photogrammetry capture (``droneulator capture``): rings of viewpoints around the scene's tree."""

    #: views in all, shared out between the rings
    views: int = 18
    #: orbit radius around the trunk, metres: close enough that tree_inspection's crown (about 5 m across,
    #: 4 m tall) fills most of a 70 deg frame, and about 3 m clear of its leaf clusters
    radius: float = 6.0
    #: one ring per altitude (m above the ground); the views are shared out between the rings. None: one
    #: ring per 18 views (at most 3, see :meth:`ring_altitudes`), so that neighbouring views stay about
    #: 20 degrees apart, close enough for SIFT to match them, and extra views add height rather than
    #: crowding one ring
    altitudes: list[float] | None = None
    #: each ring's views span this arc, degrees from azimuth 0 (360: a full circle, else both ends included)
    arc_deg: float = 360.0
    #: camera mount pitch, degrees (positive looks down); None aims at the crown centre from the mean altitude
    pitch_deg: float | None = None
    camera: str = "front"
    width: int = 1024
    height: int = 768
    hfov_deg: float = 70.0
    #: the simulator a capture starts triggers its camera at each view (``render.camera_trigger=command``):
    #: nothing is rendered between views, so the flight runs as fast as the physics; False: the camera
    #: shoots at ``camera_hz`` throughout (a video camera), and every frame is rendered and published
    trigger: bool = True
    #: with ``trigger``: the odometry and TF rate of the simulator a capture starts (sim Hz; each triggered
    #: frame also brings the states of its stamp). Enough to see the vehicle settle, and at this rate
    #: publishing the states leaves most of the CPU to the flight; None: ``runtime.state_hz``
    state_hz: float | None = 25.0
    #: camera rate while capturing (sim time) when not triggered: frames are only used once the vehicle
    #: has settled
    camera_hz: float = 10.0
    jpeg_quality: int = 95
    #: peak speed of each leg's min-snap goto, m/s
    speed: float = 1.0
    #: arcs wider than this are flown as several gotos so the path stays close to the circle, degrees
    max_leg_deg: float = 25.0
    #: settled once odometry stays this close to the viewpoint for settle_time_s of sim time
    settle_position_m: float = 0.05
    settle_speed_mps: float = 0.05
    settle_yaw_deg: float = 1.0
    settle_rate_dps: float = 3.0
    settle_time_s: float = 0.3
    #: a viewpoint not settled that way this long (sim s) after its leg's reference ended is taken once
    #: the vehicle is within acceptance_m of it and acceptance_deg of its heading (in wind the simulator's
    #: controller keeps an offset and gusts keep it moving; the recorded pose is exact either way)
    accept_after_s: float = 3.0
    acceptance_m: float = 0.5
    acceptance_deg: float = 10.0
    #: wall-clock limit for one leg (flight and settling), seconds
    leg_timeout_s: float = 120.0
    #: vehicles flying the capture at once (``--vehicles``), each its own contiguous arc of every ring
    #: (two: opposite halves, from where they stand outwards); the dataset is the same views whatever the
    #: number
    vehicles: int = 1

    def __post_init__(self) -> None:
        if self.views < 1:
            raise ValueError("capture.views must be at least 1")
        if not 1 <= self.vehicles <= self.views:
            raise ValueError(
                f"capture.vehicles must lie in [1, capture.views = {self.views}] (one view at least per "
                f"vehicle), got {self.vehicles}"
            )
        if self.altitudes is not None and (not self.altitudes or min(self.altitudes) <= 0):
            raise ValueError("capture.altitudes must hold at least one altitude above the ground")
        if self.views < len(self.ring_altitudes()):
            raise ValueError("capture.views must be at least the number of rings (capture.altitudes)")
        if not self.radius > 0 or not self.speed > 0 or not self.camera_hz > 0:
            raise ValueError("capture.radius, capture.speed and capture.camera_hz must be positive")
        if self.state_hz is not None and not self.state_hz >= 5:
            raise ValueError(
                f"capture.state_hz must be at least 5 Hz (the settle check needs odometry), "
                f"got {self.state_hz}"
            )
        if not 0 < self.arc_deg <= 360:
            raise ValueError("capture.arc_deg must lie in (0, 360]")
        if not 0 < self.max_leg_deg <= 180:
            raise ValueError("capture.max_leg_deg must lie in (0, 180]")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError("capture.jpeg_quality must lie in [1, 100]")
        if not (self.accept_after_s > 0 and self.acceptance_m > 0 and 0 < self.acceptance_deg <= 180):
            raise ValueError(
                "capture.accept_after_s and capture.acceptance_m must be positive, capture.acceptance_deg "
                "in (0, 180]"
            )

    def ring_altitudes(self) -> list[float]:
        """The rings' altitudes: ``altitudes`` when given, else ``round(views / 18)`` rings (1 to 3)
        spread over 3.5 to 5.5 m (a single ring at 4.5 m): from 6 m out the 70 deg camera aimed at the
        crown centre (3.8 m on tree_inspection) sees the whole crown from each of them."""
        if self.altitudes is not None:
            return [float(a) for a in self.altitudes]
        rings = min(3, max(1, round(self.views / 18)))
        return [4.5] if rings == 1 else [float(a) for a in np.linspace(3.5, 5.5, rings)]
