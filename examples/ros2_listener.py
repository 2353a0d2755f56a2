"""Receive odometry and the colour image in ROS 2 (rclpy) through zenoh-bridge-ros2dds.

Not run by this project's tests: it needs a ROS 2 installation (Humble or Jazzy) and the
zenoh-bridge-ros2dds binary, neither of which is installed here; the test only compiles it.

    droneulator run --scene orchard                       # simulator, Zenoh on tcp/127.0.0.1:7448
    zenoh-bridge-ros2dds -e tcp/127.0.0.1:7448            # ROS 2 side: DDS <-> Zenoh
    source /opt/ros/jazzy/setup.bash
    python3 examples/ros2_listener.py --ros-args -p use_sim_time:=true
    rviz2 -d examples/rviz/droneulator.rviz               # TF, odometry path, image, depth cloud

The bridge creates DDS endpoints for the simulator's topics, so this is an ordinary ROS 2 node:
the topics and types are those of ``ros2 topic list -t`` (README, "The running simulator").
"""

import rclpy
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage


class DroneulatorListener(Node):
    """Logs the vehicle position twice per second and every colour frame's stamp and size."""

    def __init__(self) -> None:
        super().__init__("droneulator_listener")
        ns = self.declare_parameter("namespace", "droneulator").value
        camera = self.declare_parameter("camera", "front").value
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)  # what the simulator offers
        self.create_subscription(Odometry, f"/{ns}/odom", self.on_odometry, qos)
        self.create_subscription(
            CompressedImage, f"/{ns}/{camera}/color/image_raw/compressed", self.on_image, qos
        )
        self.last_log_ns = 0

    def on_odometry(self, msg: Odometry) -> None:
        t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if t - self.last_log_ns < 500_000_000:
            return
        self.last_log_ns = t
        p = msg.pose.pose.position
        self.get_logger().info(
            f"odom {msg.header.frame_id}->{msg.child_frame_id} t={t / 1e9:.2f} s "
            f"position=({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) forward={msg.twist.twist.linear.x:.2f} m/s"
        )

    def on_image(self, msg: CompressedImage) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        self.get_logger().info(f"image {msg.header.frame_id} t={stamp:.2f} s {msg.format} {len(msg.data)} B")


def main() -> None:
    rclpy.init()
    node = DroneulatorListener()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
