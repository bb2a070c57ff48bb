"""Sensor noise and dropout re-drawn on training images, for whole images (``augment.augment``)
and for crops (``crops.crop_batch``) alike: one formula, so both train on the same noise.

Each helper takes the generator and draws exactly what it always drew, in the same order,
so that a run's random stream does not depend on which module calls it.
"""

from __future__ import annotations

import math

import torch

from task_outcome_ros.labels import REFERENCE_PIXELS

# The sensor's axial noise per 640 x 480 pixel, as sd / z^2 (robust sd of noisy - clean depth
# over 15 validation renders: 5.3 / 8.1 / 12.0 / 16.1 mm at 1.75 / 2.25 / 2.75 / 3.25 m).
# Area-averaging k pixels into one working pixel divides it by sqrt(k): 0.0004 z^2 at
# 160 x 120, which the same renders confirm (1.3-4.0 mm). Re-drawn augmentation noise is
# scaled from this, so training inputs stay as noisy as the ones the network will see.
SENSOR_NOISE_PER_Z2 = 0.0016
# Extra dropout: each image loses up to this share of its pixels' depth.
MAX_DROPOUT_SHARE = 0.03


def noise_levels(n: int, size: tuple[int, int], noise_level: float,
                 gen: torch.Generator) -> torch.Tensor:
    """(n, 1, 1) sd / z^2 per image: U(0, ``noise_level``) times the sensor's noise per pixel
    of a working ``size`` (h, w) image (area-averaged from 640 x 480)."""
    per_pixel = SENSOR_NOISE_PER_Z2 * math.sqrt(size[0] * size[1] / REFERENCE_PIXELS)
    return per_pixel * noise_level * torch.rand(n, 1, 1, generator=gen)


def axial_noise(depth: torch.Tensor, level: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Noise to add to ``depth`` (N, h, w): normal, sd ``level`` (N, 1, 1) times z^2."""
    return torch.randn(depth.shape, generator=gen) * level * depth ** 2


def drop_pixels(valid: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """``valid`` (N, h, w) with U(0, ``MAX_DROPOUT_SHARE``) of each image's pixels set to 0
    (labels are kept: the network must infer what lies there)."""
    n = valid.shape[0]
    drop = (torch.rand(valid.shape, generator=gen)
            < MAX_DROPOUT_SHARE * torch.rand(n, 1, 1, generator=gen))
    return torch.where(drop, torch.zeros_like(valid), valid)
