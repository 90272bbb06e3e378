"""Dense correspondence network (paper III-B, no ROS)."""
