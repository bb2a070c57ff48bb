"""Ground truth beside a bag (``ground_truth.json``, written by ``python -m training
export-bag``) and the paper's image-level scores of a run's answers against it.

Used by ``outcome_bag`` (offline) and by ``live_bag`` (a live node over DDS), so both score
with the same presence rule as ``python -m training evaluate``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from task_outcome_ros import labels as L
from task_outcome_ros.bag_io import BagToolError

GROUND_TRUTH_FILE = "ground_truth.json"


def load_ground_truth(bag: Path) -> dict | None:
    """``ground_truth.json`` inside the bag folder (or beside a bag file), if there is one."""
    bag = Path(bag)
    path = (bag if bag.is_dir() else bag.parent) / GROUND_TRUTH_FILE
    if not path.is_file():
        return None
    try:
        gt = json.loads(path.read_text())
        for frame in gt["frames"]:
            for field in ("stamp_ns", "pixel_counts", "width", "height"):
                if field not in frame:
                    raise KeyError(f"a frame has no '{field}'")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BagToolError(f"{path}: not a ground-truth file of `python -m training "
                           f"export-bag` ({type(exc).__name__}: {exc})") from None
    gt["path"] = str(path)
    return gt


def score(ground_truth: dict, predicted: dict[int, dict[str, bool] | None],
          presence_min_pixels: int = L.PRESENCE_MIN_PIXELS) -> dict:
    """Image-level presence scores of ``predicted`` (stamp ns -> present, None = ERROR frame).

    The truth is the presence rule applied to the ground-truth pixel counts with the same
    ``presence_min_pixels``. A frame with no prediction (ERROR status, or missing from the bag)
    counts as not all-correct and as 'nothing present' for precision and recall.
    """
    n = len(ground_truth["frames"])
    truth = np.zeros((n, len(L.OUTCOME_NAMES)), bool)
    pred = np.zeros_like(truth)
    correct = np.zeros(n, bool)
    mistakes, n_errors, n_missing = [], 0, 0
    for i, frame in enumerate(ground_truth["frames"]):
        threshold = L.presence_threshold(frame["height"], frame["width"], presence_min_pixels)
        truth[i] = [frame["pixel_counts"][name] >= threshold for name in L.OUTCOME_NAMES]
        stamp = int(frame["stamp_ns"])
        if stamp not in predicted:
            n_missing += 1
        elif predicted[stamp] is None:
            n_errors += 1
        else:
            pred[i] = [bool(predicted[stamp][name]) for name in L.OUTCOME_NAMES]
            correct[i] = bool(np.all(truth[i] == pred[i]))
        if not correct[i]:
            mistakes.append({"index": frame.get("index", i), "episode": frame.get("episode"),
                             "stamp_ns": stamp})
    # Missing and ERROR frames predict nothing present, and are never all-correct.
    report: dict[str, Any] = {
        "n_images": n,
        **L.presence_scores(truth, pred),
        "image_all_correct": float(correct.mean()) if n else 0.0,
        "n_errors": n_errors,
        "n_missing": n_missing,
        "presence_min_pixels": presence_min_pixels,
    }
    report["mistakes"] = mistakes
    return report
