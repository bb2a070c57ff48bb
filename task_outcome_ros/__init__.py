"""task_outcome_ros: tell from one depth image whether a place task succeeded.

Only ``node`` (and the bag replay tool) import rclpy; everything else is plain Python so the
training pipeline and tests can use it without ROS.
"""

__version__ = "0.1.0"
