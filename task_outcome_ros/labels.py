"""The one vocabulary: class ids, outcome names, colours, presence rule (docs/interface.md §3).

Training, evaluation, the node and the tools all import these; never copy a constant.
"""

from __future__ import annotations

import numpy as np

BACKGROUND = 0
CONTAINER = 1
SUCCESS = 2
FELL_OUTSIDE = 3
STUCK_ON_RIM = 4
IGNORE = 255

NUM_CLASSES = 5
CLASS_NAMES: tuple[str, ...] = ("background", "container", "success", "fell_outside",
                                "stuck_on_rim")
# The three outcomes, in label-id order; their label id is OUTCOME_IDS[name].
OUTCOME_NAMES: tuple[str, ...] = ("success", "fell_outside", "stuck_on_rim")
OUTCOME_IDS: dict[str, int] = {"success": SUCCESS, "fell_outside": FELL_OUTSIDE,
                               "stuck_on_rim": STUCK_ON_RIM}
FAILURE_OUTCOMES: tuple[str, ...] = ("fell_outside", "stuck_on_rim")

# RGB colours for overlays and figures (paper Fig. 1: green success, yellow/red failures).
CLASS_COLOURS: dict[int, tuple[int, int, int]] = {
    BACKGROUND: (0, 0, 0),
    CONTAINER: (70, 130, 255),
    SUCCESS: (40, 200, 60),
    FELL_OUTSIDE: (255, 210, 0),
    STUCK_ON_RIM: (230, 30, 30),
    IGNORE: (110, 110, 110),
}

# Presence rule: at least PRESENCE_MIN_PIXELS labelled pixels at 640 x 480, scaled with area.
PRESENCE_MIN_PIXELS = 50
REFERENCE_PIXELS = 640 * 480


def label_table() -> dict[str, int]:
    """Class name -> id; stored in checkpoints so a mismatch with this code is caught."""
    return {name: i for i, name in enumerate(CLASS_NAMES)}


def presence_threshold(height: int, width: int,
                       min_pixels: int = PRESENCE_MIN_PIXELS) -> int:
    """Pixel count an outcome needs to be *present* in an image of this size (>= 1)."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height} x {width}")
    if min_pixels < 1:
        raise ValueError(f"presence min_pixels must be >= 1, got {min_pixels}")
    return max(1, scale_pixel_count(min_pixels, height, width))


def scale_pixel_count(pixels: int, height: int, width: int) -> int:
    """A pixel count given at 640 x 480 (REFERENCE_PIXELS), scaled with the image area."""
    return int(round(pixels * height * width / REFERENCE_PIXELS))


def outcome_pixel_counts(labels: np.ndarray) -> dict[str, int]:
    """Number of pixels per outcome in a label image."""
    labels = np.asarray(labels, dtype=np.uint8)
    # Three comparisons beat one bincount here (0.06 vs 0.38 ms at 640 x 480): no widening.
    return {name: int(np.count_nonzero(labels == OUTCOME_IDS[name])) for name in OUTCOME_NAMES}


def outcomes_present(labels: np.ndarray, min_pixels: int = PRESENCE_MIN_PIXELS,
                     ) -> dict[str, bool]:
    """The paper's presence decision for each outcome (threshold scaled to the image size)."""
    h, w = labels.shape[:2]
    return presence_from_counts(outcome_pixel_counts(labels), presence_threshold(h, w, min_pixels))


def presence_from_counts(counts: dict[str, int], threshold: int) -> dict[str, bool]:
    """The presence rule on per-outcome pixel counts already made (``outcome_pixel_counts``)."""
    return {name: counts[name] >= threshold for name in OUTCOME_NAMES}


def colourise(labels: np.ndarray) -> np.ndarray:
    """Label image -> RGB uint8 image using CLASS_COLOURS (unknown ids black)."""
    lut = np.zeros((256, 3), np.uint8)
    for class_id, rgb in CLASS_COLOURS.items():
        lut[class_id] = rgb
    return lut[np.asarray(labels, dtype=np.uint8)]


def presence_scores(truth: np.ndarray, pred: np.ndarray) -> dict:
    """The paper's image-level metric over N images: (N, 3) boolean presence arrays, columns in
    OUTCOME_NAMES order -> all-correct rate, per-outcome counts and presence precision/recall,
    and the two rates again as ``presence_precision`` / ``presence_recall`` {outcome: rate}."""
    truth, pred = np.asarray(truth, bool), np.asarray(pred, bool)
    out: dict = {"image_all_correct": float(np.mean(np.all(truth == pred, axis=1)))
                 if len(truth) else 0.0}
    for k, name in enumerate(OUTCOME_NAMES):
        tp = int(np.sum(truth[:, k] & pred[:, k]))
        fp = int(np.sum(~truth[:, k] & pred[:, k]))
        fn = int(np.sum(truth[:, k] & ~pred[:, k]))
        out[name] = {"presence_precision": tp / (tp + fp) if tp + fp else 1.0,
                     "presence_recall": tp / (tp + fn) if tp + fn else 1.0,
                     "support": int(truth[:, k].sum()), "false_positives": fp,
                     "false_negatives": fn}
    for rate in ("presence_precision", "presence_recall"):
        out[rate] = {name: out[name][rate] for name in OUTCOME_NAMES}
    return out
