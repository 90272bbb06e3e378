"""smpl_depth_ros: 3D human body reconstruction from a single depth image.

Core modules (no ROS import): body, synth, net, fit, pipeline, offline helpers.
ROS adapters and nodes live in smpl_depth_ros.ros.
"""
__version__ = '0.1.0'
