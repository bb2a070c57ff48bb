"""A time-of-flight depth sensor: the second sensor model, drawn for a share of the frames.

Structurally unlike the structured-light model of ``noise.py`` (no projector, no disparity),
so a network trained on both cannot lean on either's signature. In this order, on the clean
full-resolution render (docs/rendering.md):

1. **Flying pixels** (mixed pixels, Hansard et al. 2013, *Time-of-Flight Cameras*, ch. 1):
   a pixel whose footprint spans a depth edge integrates both surfaces' returns and reads a
   depth in between. Every pixel whose 3 x 3 neighbourhood spans more than ``edge_jump_m`` is
   mixed with probability ``flying_pixel_rate``, at a uniform point between the nearest and
   farthest depth around it. Its label stays that of its own surface.
2. **Multipath** (Fuchs 2010; Jiménez et al. 2014): light bounced off a neighbouring surface
   arrives late, so concave regions read too far. A pixel deeper than the mean of its
   ``multipath_window_px`` neighbourhood by h reads ``multipath_gain`` x h deeper (h capped
   at 10 cm).
3. **Axial noise**: Gaussian in depth, sd ``sigma_1m`` x z^2 / sqrt(cos incidence) (the
   return's amplitude falls as cos / z^2; shot noise grows as its inverse square root,
   steepened to z^2 for ambient light), plus a per-frame offset N(0, ``depth_bias_m``).
4. **Amplitude dropout**: a pixel whose amplitude cos / z^2 is below ``amplitude_cutoff``
   is invalid; the probability ramps to zero over the next ``amplitude_soft``. Far grazing
   floor disappears first, as on real ToF cameras.
5. **Isolated dropouts** at ``dropout_rate`` per pixel, then the range limits.

Invalid pixels are NaN in depth and :data:`~task_outcome_ros.labels.IGNORE` in labels. Every
random draw comes from the ``rng`` passed in, in a fixed order.
"""

from __future__ import annotations

import cv2
import numpy as np

from task_outcome_ros.labels import IGNORE
from training.config import TofConfig
from training.noise import _standard_normal

MULTIPATH_CAP_M = 0.10    # the hollow depth a corner can add to, at most
MIN_COS = 0.05            # incidence below this counts as this (the amplitude model's floor)


def apply_tof_noise(depth: np.ndarray, labels: np.ndarray, cos_incidence: np.ndarray,
                    cfg: TofConfig, rng: np.random.Generator
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Turn a clean render into a ToF-like frame (see the module docstring).

    depth float32 HxW metres (NaN = no hit), labels uint8 HxW, cos_incidence float32 HxW.
    Returns (noisy depth float32 with NaN = invalid, labels with 255 where invalid)."""
    z = np.array(depth, dtype=np.float32)
    lab = np.array(labels, dtype=np.uint8)
    if z.ndim != 2 or lab.shape != z.shape or np.shape(cos_incidence) != z.shape:
        raise ValueError(f"apply_tof_noise: depth, labels and cos_incidence must share one "
                         f"HxW shape, got {z.shape}, {lab.shape}, {np.shape(cos_incidence)}")
    valid = np.isfinite(z) & (z > 0)
    filled = np.where(valid, z, np.float32(0.0))
    h, w = z.shape

    with np.errstate(invalid="ignore", divide="ignore"):
        # 1. Flying pixels at depth edges (missing returns count as no surface).
        kernel = np.ones((3, 3), np.uint8)
        near = cv2.erode(np.where(valid, z, np.float32(np.inf)), kernel)
        far = cv2.dilate(filled, kernel)
        edge = valid & np.isfinite(near) & (far - near > cfg.edge_jump_m)
        mixed = edge & (rng.random((h, w), dtype=np.float32) < cfg.flying_pixel_rate)
        alpha = rng.random((h, w), dtype=np.float32)
        z = np.where(mixed, near + alpha * (far - near), z)

        # 2. Multipath: concave regions read deeper by a share of their hollow depth.
        if cfg.multipath_gain > 0:
            size = (int(cfg.multipath_window_px), int(cfg.multipath_window_px))
            weight = cv2.blur(valid.astype(np.float32), size)
            mean = cv2.blur(filled, size) / np.maximum(weight, np.float32(1e-6))
            hollow = np.clip(z - mean, 0.0, MULTIPATH_CAP_M)
            z = z + np.float32(cfg.multipath_gain) * np.where(valid, hollow, 0.0)

        # 3. Axial noise from the return's amplitude, and the frame's offset.
        cos = np.where(np.isfinite(cos_incidence), np.abs(cos_incidence), 1.0)
        cos = np.maximum(cos, MIN_COS).astype(np.float32)
        sigma = np.float32(cfg.sigma_1m) * z * z / np.sqrt(cos)
        z = z + _standard_normal(rng, (h, w)) * sigma
        if cfg.depth_bias_m > 0:
            z = z + np.float32(rng.normal(0.0, cfg.depth_bias_m))

        # 4. Amplitude dropout, ramping over amplitude_soft above the cutoff.
        amplitude = cos / (z * z)
        if cfg.amplitude_soft > 0:
            p_drop = np.clip((cfg.amplitude_cutoff + cfg.amplitude_soft - amplitude)
                             / cfg.amplitude_soft, 0.0, 1.0)
        else:
            p_drop = (amplitude < cfg.amplitude_cutoff).astype(np.float32)
        valid &= rng.random((h, w), dtype=np.float32) >= p_drop

        # 5. Isolated dropouts and the range limits.
        if cfg.dropout_rate > 0:
            valid &= rng.random((h, w), dtype=np.float32) >= cfg.dropout_rate
        valid &= (z >= cfg.min_range) & (z <= cfg.max_range)

    z = z.astype(np.float32, copy=False)
    z[~valid] = np.nan
    lab[~valid] = IGNORE
    return z, lab
