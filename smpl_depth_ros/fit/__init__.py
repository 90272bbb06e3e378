"""Model fitting (paper III-C, no ROS): objective, solvers, tracking."""
from smpl_depth_ros.fit.fitter import FitResult, Fitter  # noqa: F401
from smpl_depth_ros.fit.targets import backproject  # noqa: F401
