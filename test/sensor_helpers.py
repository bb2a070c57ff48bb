"""What the sensor-model and augmentation tests share (test_tof.py, test_stereo.py,
test_islands.py, test_range_limit.py)."""

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


AUGMENT_SEED = 6


def augment_with_and_without(depth, valid, labels, **option):
    """``augment.augment`` (holes 0.5, one seed) three ways: without ``option``, with it at
    its off value 0, and with it on: (plain, off, on) batches. An augmentation drawn last
    must leave the first two equal and, labels-honest, the labels of all three."""
    import torch

    from training.augment import augment

    (name, value), = option.items()

    def run(**extra):
        return augment(depth, valid, labels, torch.Generator().manual_seed(AUGMENT_SEED),
                       holes=0.5, **extra)
    return run(), run(**{name: 0.0}), run(**{name: value})
