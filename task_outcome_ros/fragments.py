"""One object, one outcome: small outcome fragments on another outcome's object are absorbed.

Why: an object has exactly one outcome, but the network sometimes paints a thin fringe of a
second outcome on it (a few stuck_on_rim pixels along the edge of a box that fell against the
outer wall, say). A fringe of 50+ pixels at 640 x 480 is enough to make the presence rule
report an outcome that is not there; such fringes were 4 of the 22 validation mistakes of model
0.1.1. A fragment is an 8-connected component of one outcome class with fewer than
``max_pixels`` pixels that *touches* pixels of another outcome; it takes the outcome most
common in its one-pixel ring. Fragments touching no other outcome (a small object of its own,
e.g. one cut by the image border) are left alone.

The threshold (at 640 x 480) follows the model. It is chosen on the validation split
(runs/default, 500 images) and the first 1,000 training images, then checked on the
independent set (runs/seed1, 1,000 images); docs/experiments.md keeps each model's sweep. For
model 0.2.0, without / 512 / 1024 / 1536 px make 18 / **19** / 24 / 32 mistakes on the two
together and 12 / **9** / 11 / 13 on seed-1, so 512 px stays, as for the four models before.
Models trained on cross-entropy alone needed absorption more (model 0.1.5: 0.974 without, 0.982
at 512 on validation), because that loss charged a fringe by its pixels. Larger is not free: a
success box half hidden behind a stuck one shows a small visible part that touches the stuck
box, and it gets absorbed (that is what 1536 px loses). Merging whole connected objects to
their majority outcome instead *lost* 1-8 points: touching boxes with different outcomes merge.
"""

from __future__ import annotations

import cv2
import numpy as np

from task_outcome_ros.labels import DEFAULT_TABLE, LabelTable, scale_pixel_count

# Largest fragment absorbed, in pixels of a 640 x 480 image (scaled with the area like the
# presence rule's 50): 32 pixels at the 160 x 120 working size.
FRAGMENT_MAX_PIXELS = 512

_RING = np.ones((3, 3), np.uint8)


def fragment_threshold(height: int, width: int, max_pixels: int = FRAGMENT_MAX_PIXELS) -> int:
    """``max_pixels`` (at 640 x 480) scaled to an image of this size; 0 turns absorption off."""
    if max_pixels < 0:
        raise ValueError(f"fragment max_pixels must be >= 0, got {max_pixels}")
    return scale_pixel_count(max_pixels, height, width)


def absorb_fragments(labels: np.ndarray, max_pixels: int,
                     table: LabelTable = DEFAULT_TABLE) -> np.ndarray:
    """A copy of ``labels`` (uint8 class ids) with outcome fragments < ``max_pixels`` absorbed.

    ``max_pixels`` is in pixels of *this* image (see ``fragment_threshold``); ``table`` says
    which ids are outcomes (the fixture and background are never absorbed nor absorb).
    Decisions are taken on the input labels, so the result does not depend on the order of
    the classes.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or labels.dtype != np.uint8:
        raise ValueError(f"labels must be a 2-D uint8 image, got {labels.dtype} {labels.shape}")
    out = labels.copy()
    if max_pixels <= 1:
        return out
    h, w = labels.shape
    outcome_ids = np.array(sorted(table.outcome_ids.values()), np.uint8)
    outcome_lut = np.zeros(256, bool)   # a lookup by id: a tenth of np.isin's time
    outcome_lut[outcome_ids] = True
    is_outcome = outcome_lut[labels]
    for outcome in outcome_ids:
        mask = (labels == outcome).view(np.uint8)   # bool is one byte of 0 / 1: no copy
        if not mask.any():   # most frames show one or two outcomes: no labelling for the rest
            continue
        n, cc, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        for k in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < max_pixels) + 1:
            # Work inside the component's bounding box grown by the one-pixel ring.
            x0 = max(stats[k, cv2.CC_STAT_LEFT] - 1, 0)
            y0 = max(stats[k, cv2.CC_STAT_TOP] - 1, 0)
            x1 = min(stats[k, cv2.CC_STAT_LEFT] + stats[k, cv2.CC_STAT_WIDTH] + 1, w)
            y1 = min(stats[k, cv2.CC_STAT_TOP] + stats[k, cv2.CC_STAT_HEIGHT] + 1, h)
            part = (cc[y0:y1, x0:x1] == k).astype(np.uint8)
            ring = cv2.dilate(part, _RING).astype(bool) & ~part.astype(bool)
            neighbours = labels[y0:y1, x0:x1][ring & is_outcome[y0:y1, x0:x1]]
            if neighbours.size:
                votes = np.bincount(neighbours, minlength=int(outcome_ids.max()) + 1)
                out[y0:y1, x0:x1][part.astype(bool)] = np.uint8(votes.argmax())
    return out
