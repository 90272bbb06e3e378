"""Synthetic depth data with exact ground truth (no ROS)."""
