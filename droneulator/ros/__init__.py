"""ROS 2 over Zenoh without a ROS 2 installation.

* :mod:`.messages`: messages as rosbags objects and their standard CDR bytes (plus a fast packer for the
  per-step state messages);
* :mod:`.zenoh_node`: a Zenoh session acting as a ROS 2 node, with zenoh-bridge-ros2dds keys or
  rmw_zenoh keys, attachments and liveliness tokens;
* :mod:`.publishers`: what the simulator publishes and takes (state, camera frames, commands);
* :mod:`.topics`: topic names, stamps and image decoding for subscribers.

The package itself imports nothing, so ``droneulator.ros.topics`` stays light for clients and no
submodule imports the package back.
"""
