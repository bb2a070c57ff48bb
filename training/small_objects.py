"""Loss boost for small visible objects: the metric counts objects, cross-entropy counts pixels.

Why: the presence rule (CONTRACTS §3) calls an outcome present from 50 pixels at 640 x 480, so
a box cut by the image border that shows 100 pixels counts as much as one that fills a
quarter of the view. Per-pixel cross-entropy weighs them by area, and the stop-10 model
missed about half of the outcomes whose visible area is under 400 pixels (3 of its 10
validation mistakes, 9 of 24 on the first 1,000 training images, 6 of 24 on the seed-1 set),
nearly all of them fell_outside boxes cut by the border.

``small_object_boost`` gives every pixel of an outcome object (an 8-connected component of one
outcome class in the working-size labels) the factor ``min(max_boost, ref / area)``, at least
1: objects of ``ref`` pixels or more keep their loss, smaller ones weigh up to ``max_boost``
times as much per pixel. Background, container and ignored pixels keep 1.
"""

from __future__ import annotations

import cv2
import numpy as np

from task_outcome_ros.labels import OUTCOME_IDS, scale_pixel_count

# Objects smaller than this (pixels at 640 x 480, scaled with the area like the presence
# rule's 50) get a boost: 1,024 px is 64 pixels at the 160 x 120 working size.
SMALL_OBJECT_PIXELS = 1024

_OUTCOME_IDS = tuple(sorted(OUTCOME_IDS.values()))


def small_object_boost(labels: np.ndarray, max_boost: float,
                       ref_pixels: int = SMALL_OBJECT_PIXELS) -> np.ndarray:
    """(N, h, w) uint8 working-size labels -> (N, h, w) float16 per-pixel loss factors >= 1.

    ``ref_pixels`` is at 640 x 480 and scaled to the labels' size; ``max_boost`` = 1 gives all
    ones (no boost).
    """
    labels = np.asarray(labels)
    if labels.ndim != 3 or labels.dtype != np.uint8:
        raise ValueError(f"labels must be (N, h, w) uint8, got {labels.dtype} {labels.shape}")
    if max_boost < 1.0:
        raise ValueError(f"max_boost must be >= 1, got {max_boost}")
    boost = np.ones(labels.shape, np.float16)
    if max_boost == 1.0:
        return boost
    ref = scale_pixel_count(ref_pixels, *labels.shape[1:])
    for image, out in zip(labels, boost):
        for outcome in _OUTCOME_IDS:
            mask = image == outcome
            if not mask.any():
                continue
            n, cc, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8),
                                                               connectivity=8)
            area = stats[:, cv2.CC_STAT_AREA].astype(np.float32)
            factor = np.clip(ref / np.maximum(area, 1.0), 1.0, max_boost)
            factor[0] = 1.0  # component 0 is everything that is not this outcome
            out[mask] = factor[cc[mask]]
    return boost
