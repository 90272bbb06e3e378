"""ROS 2 layer: message <-> array adapters (`adapters`: images, camera info, diagnostics;
`markers`; `body_msgs`: JointState and TF), the OAK camera's depthai side (`oak`,
`oak_device`) and the nodes that drive the core.

The adapters import no rclpy at module level: the same functions serve rclpy messages and
rosbags dataclasses (see `adapters.MsgFactory`).
"""
