"""Pinhole intrinsics of a depth image (CameraInfo.K), in the forms the package needs.

Two users: the status report back-projects object centroids to 3-D (outcome_report.py), and
the network's height channel back-projects every working-size pixel (floor.py). The second
needs the intrinsics independent of resolution, because the network runs at its working size
whatever the input size: ``normalised()`` divides the focal lengths by the image size and
measures the principal point from the image centre, in image widths and heights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the raw image (CameraInfo.K) for one image size."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_k(cls, width: int, height: int, k: Any) -> Intrinsics:
        """From CameraInfo's width, height and row-major 3 x 3 K; ValueError says what is off."""
        k = [float(v) for v in k]
        if len(k) != 9:
            raise ValueError(f"camera_info K must have 9 values, got {len(k)}")
        if not all(math.isfinite(v) for v in k) or k[0] <= 0 or k[4] <= 0:
            raise ValueError(f"camera_info K has no valid focal length (fx={k[0]}, fy={k[4]})")
        if width <= 0 or height <= 0:
            raise ValueError(f"camera_info has size {width} x {height}")
        return cls(int(width), int(height), k[0], k[4], k[2], k[5])

    @classmethod
    def from_record(cls, camera: dict[str, Any]) -> Intrinsics:
        """From a dataset manifest's per-image camera record (training/render.py)."""
        return cls(int(camera["width"]), int(camera["height"]), float(camera["fx"]),
                   float(camera["fy"]), float(camera["cx"]), float(camera["cy"]))

    def k(self) -> list[float]:
        """Row-major 3 x 3 K, as CameraInfo carries it (``from_k`` reads it back)."""
        return [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]

    def back_project(self, u: float, v: float, z: float) -> tuple[float, float, float]:
        """Pixel (u, v) at depth z (m, along the optical axis) -> optical-frame x, y, z."""
        return (u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z

    def normalised(self) -> np.ndarray:
        """(4,) float32: fx / W, fy / H, (cx - (W - 1) / 2) / W, (cy - (H - 1) / 2) / H.

        Any resize of the image (pixel centres kept aligned, as OpenCV's and torch's area
        resizes do) leaves these four numbers unchanged, so they hold at the working size."""
        w, h = self.width, self.height
        return np.array([self.fx / w, self.fy / h, (self.cx - (w - 1) / 2) / w,
                         (self.cy - (h - 1) / 2) / h], np.float32)


def intrinsics_for_image(width: int, height: int, k: Any, image_width: int, image_height: int,
                         ) -> Intrinsics:
    """Intrinsics from camera_info fields, checked against the image they are used for."""
    cand = Intrinsics.from_k(width, height, k)
    if (cand.width, cand.height) != (image_width, image_height):
        raise ValueError(f"camera_info size {cand.width} x {cand.height} does not match the "
                         f"image {image_width} x {image_height}")
    return cand
