"""User-level workflows built on the running simulator's public interfaces (WebSocket API, ROS 2 topics)."""
