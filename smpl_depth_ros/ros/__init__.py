"""ROS 2 layer: message <-> array adapters (`adapters`) and the nodes that drive the core.

`adapters` imports no rclpy at module level: the same functions serve rclpy messages and
rosbags dataclasses (see `adapters.MsgFactory`).
"""
