"""perception_config: a ROS 2 perception service for robotic picking that configures itself."""

__version__ = "0.1.0"

import os as _os

# Our numpy work is many small products (Nx3 @ 3x3): OpenBLAS threads only add contention on
# the 2-core machines this runs on (measured up to 50x slower under load). A user's setting wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
