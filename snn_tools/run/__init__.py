"""Running the pipeline: the closed-loop demo over ROS 2 (separate processes or one), and filling
numba's cache at install."""
