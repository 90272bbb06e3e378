"""`python -m smpl_depth_ros.offline`: the process_bag command line."""
import sys

from smpl_depth_ros.offline.cli import main

sys.exit(main())
