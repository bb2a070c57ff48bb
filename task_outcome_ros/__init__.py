"""task_outcome_ros: tell from one depth image whether a place task succeeded.

Only ``node`` and the DDS tools (``replay``, ``live_bag``, ``client``) import rclpy; everything
else is plain Python so the training pipeline and tests can use it without ROS. Nothing here
imports ``training``: a robot installs this package without the simulator or the clustering.
"""

__version__ = "0.21.0"
