"""Diagnosing lost depth images: camera_info keeps arriving, the images much less often.

A 640 x 480 ``32FC1`` image (1.2 MB) does not fit Fast DDS's default shared-memory segment, so
a best-effort subscriber loses most of them while the small camera_info messages on the same
path all arrive (bench/node.py: 54.5 % of 1,800 frames without the project's profile, none
lost with it). The ratio of the two is what gives it away.
"""

from __future__ import annotations

# After this many camera_info messages, images below this share of them mean losses.
MIN_INFOS = 30
MIN_IMAGE_SHARE = 0.5

FIX = ("load the shared-memory Fast DDS profile in the camera driver (the publisher) and in "
       "this node: export FASTRTPS_DEFAULT_PROFILES_FILE=<share>/task_outcome_ros/config/"
       "fastdds_shm.xml (README: Large images over DDS)")


class TransportMonitor:
    """Counts both topics; says once when images are going missing."""

    def __init__(self) -> None:
        self.images = 0
        self.infos = 0
        self.warned = False

    def on_image(self) -> None:
        self.images += 1

    def on_camera_info(self) -> str | None:
        """The warning to log, the first time the counts show images being lost."""
        self.infos += 1
        if self.warned or self.infos < MIN_INFOS or self.images >= MIN_IMAGE_SHARE * self.infos:
            return None
        self.warned = True
        return (f"{self.infos} camera_info messages but only {self.images} depth images "
                f"arrived: large images are being lost in DDS. Fix: {FIX}")
