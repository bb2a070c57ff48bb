"""A scene the sensor-model tests share (test_tof.py, test_stereo.py)."""

from __future__ import annotations

import numpy as np

H, W = 120, 160


def step_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, labels, cos_incidence) of a plane at 2 m with a box face at 1.7 m, label 2, in
    columns 60-99, everything facing the camera."""
    depth = np.full((H, W), 2.0, np.float32)
    labels = np.zeros((H, W), np.uint8)
    depth[:, 60:100] = 1.7
    labels[:, 60:100] = 2
    return depth, labels, np.ones((H, W), np.float32)
