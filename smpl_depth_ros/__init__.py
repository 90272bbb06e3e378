"""smpl_depth_ros: 3D human body reconstruction from a single depth image.

Core (no ROS import): body, synth, net, fit; pipeline with refine, segmentation, tracking;
config (every parameter declared once) and params (the schema derived from it);
sensor_noise, depth_codec, stamps, bagio; offline (process_bag, on a process pool or Ray).
ROS adapters and nodes live in smpl_depth_ros.ros.
"""
__version__ = '0.1.0'
