"""artrack core: ROS-free articulated body tracking (numpy / scipy / OpenCV).

Nothing in this package imports rclpy; the ROS 2 node wrappers live in
``artrack_nodes`` and only translate messages, parameters and timing.
See ../shared/ALGORITHMS.md for the papers each module implements.
"""

__version__ = "0.1.0"
