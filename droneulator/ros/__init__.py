"""ROS 2 over Zenoh: message builders/decoders (:mod:`.messages`) and the Zenoh node (:mod:`.zenoh_node`).

Speaks zenoh-bridge-ros2dds keys or rmw_zenoh keys, attachments and liveliness tokens without any ROS 2
installation; messages are rosbags objects serialised to standard CDR.
"""

from droneulator.ros.zenoh_node import (
    RMW_ZENOH_ROUTER,
    QosProfile,
    RosPublisher,
    RosSubscription,
    RosZenohNode,
    ZenohNodeConfig,
    rmw_gid,
)

__all__ = [
    "RMW_ZENOH_ROUTER",
    "QosProfile",
    "RosPublisher",
    "RosSubscription",
    "RosZenohNode",
    "ZenohNodeConfig",
    "rmw_gid",
]
