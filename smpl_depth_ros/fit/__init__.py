"""Model fitting (paper III-C, no ROS): objective, solvers, tracking."""
from smpl_depth_ros.fit.fitter import FitResult, Fitter, backproject  # noqa: F401
