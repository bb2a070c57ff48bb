"""An active-stereo depth sensor (RealSense-D400-like): the third sensor model, drawn for a
share of the frames (``stereo`` in a scene spec).

Two infrared cameras ``baseline`` m apart, the depth image aligned with the left one; a
projector only adds texture. Depth comes from matching blocks of ``window_px`` pixels along
each row, which shapes its errors unlike the structured-light model of ``noise.py`` (one
camera and a projector, errors per pixel) or the ToF model of ``tof.py`` (no disparity). In
this order, on the clean full-resolution render (docs/rendering.md):

1. **Occlusion** (the left-right check; Scharstein & Szeliski 2002): what the right camera
   cannot see has no match. The right camera sits where the structured-light model's
   projector does (+x), so the same geometry, ``noise.projector_shadow``, finds it: bands on
   the left edges of foreground objects.
2. **Foreground fattening** (Hirschmüller & Scharstein 2009; Scharstein & Szeliski 2002): a
   block straddling a depth edge is matched by the nearer surface's texture, so the
   foreground bleeds ``fattening_px`` pixels over the background. A pixel takes the largest
   disparity (and that pixel's label: the depth it reads is the foreground's) within the
   square of ``fattening_px`` around it when that disparity exceeds its own by more than
   ``EDGE_STEP_PX``; slopes, which change by less from pixel to pixel, keep theirs.
3. **Grazing dropout**, as in the structured-light model (``noise.drop_grazing``).
4. **Disparity noise correlated over a block**: white noise averaged over the
   ``window_px`` block and rescaled to ``sigma_disparity_px``, so neighbouring pixels err
   together (a block's cost aggregation), plus calibration drift as in ``noise.py``; then
   quantised to 1 / ``disparity_subpixel`` px.
5. **Mismatched islands** (``islands.disparity_islands``): seeds at ``mismatch_rate`` per
   pixel grown to discs of radius 0..``mismatch_max_radius_px``, each island's disparity
   off by U(-1, 1) x ``mismatch_disparity_px``: small patches of wrong depth, nearer or
   farther, that pass the checks. Labels stay the truth of what lies there.
6. **Holes where nothing matched** (``noise.speckle_holes`` at ``speckle_rate``), then the
   range limits.

Invalid pixels are NaN in depth and :data:`~task_outcome_ros.labels.IGNORE` in labels. Every
random draw comes from the ``rng`` passed in, in a fixed order.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from task_outcome_ros.labels import IGNORE
from training.config import StereoConfig
from training.islands import disparity_islands
from training.noise import (
    _check_inputs,
    _standard_normal,
    calibration_drift,
    drop_grazing,
    incidence_angle,
    projector_shadow,
    quantised_depth,
    speckle_holes,
)

STEREO_MODEL = "active_stereo"   # its name in a frame's sensor record and the suite

# A neighbour's disparity must exceed a pixel's by this much for the block to be matched by
# the neighbour's surface: a depth edge, not a slope (a floor seen at 60 degrees changes by
# about 0.05 px from one pixel to the next at 2 m).
EDGE_STEP_PX = 1.0


def apply_stereo_noise(depth: np.ndarray, labels: np.ndarray, cos_incidence: np.ndarray,
                       fx: float, cfg: StereoConfig, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Turn a clean render into an active-stereo-like frame (see the module docstring).

    depth float32 HxW metres (NaN = no hit), labels uint8 HxW, cos_incidence float32 HxW,
    fx the camera's focal length in pixels. Returns (noisy depth float32 with NaN = invalid,
    labels with 255 where invalid). Inputs are not modified."""
    depth, labels, cos = _check_inputs(depth, labels, cos_incidence, fx, "apply_stereo_noise")
    h, w = depth.shape
    fb = np.float32(fx * cfg.baseline)
    with np.errstate(invalid="ignore", divide="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
        disparity = np.where(valid, fb / depth, np.float32(np.nan)).astype(np.float32)

        # 1. Occlusion: no match for what the right camera cannot see.
        valid &= ~projector_shadow(disparity)

        # 2. Foreground fattening at depth edges.
        disparity, lab = fatten_foreground(disparity, labels, valid, int(cfg.fattening_px))

        # 3. Grazing dropout.
        theta = incidence_angle(cos.copy())      # cos may be the caller's array
        drop_grazing(valid, theta, np.float32(math.radians(cfg.grazing_start_deg)),
                     np.float32(math.radians(cfg.grazing_full_deg)), rng)

        # 4. Disparity noise correlated over a block, drift, quantisation.
        noisy = disparity + block_noise((h, w), int(cfg.window_px), rng) * np.float32(
            cfg.sigma_disparity_px)
        noisy += calibration_drift((h, w), cfg, rng)

        # 5. Mismatched islands.
        noisy += disparity_islands((h, w), cfg.mismatch_rate, cfg.mismatch_max_radius_px,
                                   cfg.mismatch_disparity_px, rng)
        z, matched = quantised_depth(noisy, fb, cfg.disparity_subpixel)
        valid &= matched

        # 6. Holes where nothing matched, and the range limits.
        valid &= ~speckle_holes((h, w), cfg.speckle_rate, cfg.speckle_max_radius_px, rng)
        valid &= (z >= cfg.min_range) & (z <= cfg.max_range)

    z = z.astype(np.float32, copy=False)
    z[~valid] = np.nan
    lab[~valid] = IGNORE
    return z, lab


def fatten_foreground(disparity: np.ndarray, labels: np.ndarray, valid: np.ndarray,
                      radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(disparity, labels) with each valid pixel taking the largest valid disparity within
    ``radius`` pixels (a square) and its label, where that exceeds its own by more than
    ``EDGE_STEP_PX``. Separable: the maximum along rows, then along columns, each carrying the
    winner's label, is the maximum over the square. Draws nothing."""
    if radius <= 0:
        return disparity.copy(), labels.copy()
    best = np.where(valid, disparity, -np.inf).astype(np.float32)
    best_label = labels.copy()
    for axis in (1, 0):
        source, source_label = best.copy(), best_label.copy()
        for shift in range(-radius, radius + 1):
            if shift == 0:
                continue
            moved = _shifted(source, shift, axis, -np.inf)
            better = moved > best
            best = np.where(better, moved, best)
            best_label = np.where(better, _shifted(source_label, shift, axis, 0), best_label)
    fattened = valid & (best > disparity + np.float32(EDGE_STEP_PX))
    return (np.where(fattened, best, disparity).astype(np.float32),
            np.where(fattened, best_label, labels).astype(np.uint8))


def _shifted(a: np.ndarray, shift: int, axis: int, fill) -> np.ndarray:
    """``a`` moved by ``shift`` pixels along ``axis`` (a pixel reads its neighbour ``shift``
    away), ``fill`` where the neighbour lies beyond the frame."""
    out = np.full_like(a, fill)
    n = a.shape[axis]
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    if shift > 0:
        src[axis], dst[axis] = slice(shift, n), slice(0, n - shift)
    else:
        src[axis], dst[axis] = slice(0, n + shift), slice(-shift, n)
    out[tuple(dst)] = a[tuple(src)]
    return out


def block_noise(shape: tuple[int, int], window: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w) float32 noise of unit standard deviation, correlated over ``window`` pixels:
    white normals averaged over the window's square (an even window counts as the next odd
    size) and rescaled by its side, as i.i.d. values' mean has 1 / side their deviation."""
    white = _standard_normal(rng, shape)
    side = int(window) | 1
    if side == 1:
        return white
    return cv2.blur(white, (side, side), borderType=cv2.BORDER_REFLECT) * np.float32(side)
