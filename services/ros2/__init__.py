"""The ROS 2 side: a robot to and from ROS 2 nodes over rmw_zenoh (docs/ros2.md)."""
