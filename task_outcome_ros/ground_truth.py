"""Ground truth beside a bag (``ground_truth.json``, written by ``python -m training
export-bag``) and the paper's image-level scores of a run's answers against it.

Used by ``outcome_bag`` (offline) and by ``live_bag`` (a live node over DDS), so both score
with the same presence rule as ``python -m training evaluate``. The outcomes scored are the
truth's: a label table given by the caller, else the file's own (``label_table``), else the
outcomes its frames count pixels of; the answers must cover them.
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


def truth_outcomes(ground_truth: dict, table: L.LabelTable | None = None) -> tuple[str, ...]:
    """The outcomes ``ground_truth`` is scored on: those of ``table`` (the task the truth was
    made for, when the caller knows it); else of the file's ``label_table``
    (``LabelTable.to_dict()``); else the keys of its frames' pixel counts; for a file without
    frames, the default task's."""
    if table is not None:
        return table.outcome_names
    if "label_table" in ground_truth:
        try:
            return L.LabelTable.from_dict(ground_truth["label_table"]).outcome_names
        except L.LabelTableError as exc:
            raise BagToolError(f"{ground_truth.get('path', 'ground truth')}: {exc}") from None
    frames = ground_truth["frames"]
    return tuple(frames[0]["pixel_counts"]) if frames else L.DEFAULT_TABLE.outcome_names


def require_outcomes(ground_truth: dict, names: tuple[str, ...]) -> None:
    """BagToolError unless a model with the outcomes ``names`` can answer for every outcome of
    ``ground_truth``. (A model may know more: a small run may not have discovered them all;
    such an outcome is absent from every truth frame, and the score counts the model's
    answers for it too.)"""
    unknown = [name for name in truth_outcomes(ground_truth) if name not in names]
    if unknown:
        raise BagToolError(f"{ground_truth.get('path', 'the ground truth')} is about the "
                           f"outcomes {list(truth_outcomes(ground_truth))}, the model knows "
                           f"{list(names)} and not {unknown}: a model of another task")


def score(ground_truth: dict, predicted: dict[int, dict[str, bool] | None],
          presence_min_pixels: int = L.PRESENCE_MIN_PIXELS,
          table: L.LabelTable | None = None) -> dict:
    """Image-level presence scores of ``predicted`` (stamp ns -> present, None = ERROR frame).

    The truth is the presence rule applied to the ground-truth pixel counts with the same
    ``presence_min_pixels``, for the outcomes ``truth_outcomes(ground_truth, table)`` and
    any further outcome the answers know (the truth's run did not find it: absent in every
    frame, so a model that reports it is wrong). A frame with no prediction (ERROR status, or
    missing from the bag) counts as not all-correct and as 'nothing present' for precision
    and recall.
    """
    known = truth_outcomes(ground_truth, table)
    answered = next((p for p in predicted.values() if p is not None), {})
    names = known + tuple(name for name in answered if name not in known)
    n = len(ground_truth["frames"])
    truth = np.zeros((n, len(names)), bool)
    pred = np.zeros_like(truth)
    correct = np.zeros(n, bool)
    mistakes, n_errors, n_missing = [], 0, 0
    for i, frame in enumerate(ground_truth["frames"]):
        threshold = L.presence_threshold(frame["height"], frame["width"], presence_min_pixels)
        counts = {**dict.fromkeys(names[len(known):], 0), **frame["pixel_counts"]}
        truth[i] = [count >= threshold for count in _values(counts, names,
                                                             f"frame {i}'s pixel counts")]
        stamp = int(frame["stamp_ns"])
        if stamp not in predicted:
            n_missing += 1
        elif predicted[stamp] is None:
            n_errors += 1
        else:
            pred[i] = [bool(p) for p in _values(predicted[stamp], names,
                                                 f"the answer for stamp {stamp}")]
            correct[i] = bool(np.all(truth[i] == pred[i]))
        if not correct[i]:
            mistakes.append({"index": frame.get("index", i), "episode": frame.get("episode"),
                             "stamp_ns": stamp})
    # Missing and ERROR frames predict nothing present, and are never all-correct.
    report: dict[str, Any] = {
        "n_images": n,
        **L.presence_scores(truth, pred, names),
        "image_all_correct": float(correct.mean()) if n else 0.0,
        "n_errors": n_errors,
        "n_missing": n_missing,
        "presence_min_pixels": presence_min_pixels,
    }
    report["mistakes"] = mistakes
    return report


def _values(by_outcome: dict, names: tuple[str, ...], what: str) -> list:
    """``by_outcome``'s values for ``names``; BagToolError naming what lacks which outcome."""
    missing = [name for name in names if name not in by_outcome]
    if missing:
        raise BagToolError(f"{what} has no {missing} (it has {sorted(by_outcome)}): the "
                           "ground truth and the answers are about different outcomes")
    return [by_outcome[name] for name in names]
