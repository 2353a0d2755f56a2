"""ROS 2 bags (MCAP) of the simulator's topics: record them off Zenoh, replay them onto Zenoh.

:class:`~droneulator.recording.recorder.Recorder` (``droneulator record`` and ``droneulator run
--record``) writes what the simulator publishes with :class:`~droneulator.recording.bag.BagWriter`
in the format of ``ros2 bag record`` (Jazzy, MCAP storage); :func:`~droneulator.recording.replay.replay`
(``droneulator replay``) republishes it. See docs/recording.md.
"""

from droneulator.recording.bag import BagWriter
from droneulator.recording.recorder import Recorder, RecorderConfig, RecordingStats
from droneulator.recording.replay import ReplayConfig, replay

__all__ = ["BagWriter", "Recorder", "RecorderConfig", "RecordingStats", "ReplayConfig", "replay"]
