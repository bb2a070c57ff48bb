"""Fragment absorption (one object, one outcome) and the hard-case tags of the evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS, absorb_fragments, fragment_threshold
from task_outcome_ros.labels import CONTAINER, FELL_OUTSIDE, STUCK_ON_RIM, SUCCESS
from training.evaluate import hard_case_report
from training.hard_cases import (
    NEAR_RIM_M,
    HardCase,
    object_rim_gap,
    object_tags,
    rim_gap_bin,
    rim_gap_bin_names,
)

pytestmark = pytest.mark.unit


def _scene() -> np.ndarray:
    labels = np.zeros((60, 80), np.uint8)
    labels[5:25, 5:25] = FELL_OUTSIDE          # a fell object ...
    labels[5:8, 22:25] = STUCK_ON_RIM          # ... with a 9-pixel stuck fringe on its corner
    labels[40:44, 60:64] = SUCCESS             # a 16-pixel object of its own
    labels[30:50, 30:50] = CONTAINER
    labels[35:38, 35:38] = STUCK_ON_RIM        # a small stuck object on the container only
    return labels


def test_a_small_fringe_takes_the_outcome_of_the_object_it_sits_on():
    labels = _scene()
    out = absorb_fragments(labels, 10)
    assert (out[5:25, 5:25] == FELL_OUTSIDE).all()
    changed = out != labels
    assert changed.sum() == 9                  # nothing else moved
    assert (labels == _scene()).all()          # the input is not modified


def test_lone_small_objects_and_large_regions_are_kept():
    labels = _scene()
    assert (absorb_fragments(labels, 9) == labels).all()     # 9 px is not < 9
    assert (absorb_fragments(labels, 0) == labels).all()     # 0 turns it off
    out = absorb_fragments(labels, 1000)
    assert (out[40:44, 60:64] == SUCCESS).all()              # touches no other outcome
    assert (out[35:38, 35:38] == STUCK_ON_RIM).all()         # touches only the container


def test_decisions_use_the_input_labels_not_earlier_absorptions():
    """Two touching fragments on a success box each join the box, whatever the class order."""
    labels = np.zeros((30, 30), np.uint8)
    labels[2:28, 2:28] = SUCCESS
    labels[10:12, 10:12] = FELL_OUTSIDE
    labels[10:12, 12:14] = STUCK_ON_RIM
    out = absorb_fragments(labels, 5)
    assert (out[2:28, 2:28] == SUCCESS).all()


def test_threshold_scales_with_the_image_area_and_bad_input_is_refused():
    assert fragment_threshold(480, 640) == FRAGMENT_MAX_PIXELS
    assert fragment_threshold(120, 160) == FRAGMENT_MAX_PIXELS // 16
    assert fragment_threshold(120, 160, 0) == 0
    with pytest.raises(ValueError, match=">= 0"):
        fragment_threshold(120, 160, -1)
    with pytest.raises(ValueError, match="uint8"):
        absorb_fragments(np.zeros((4, 4), np.int64), 5)
    with pytest.raises(ValueError, match="2-D"):
        absorb_fragments(np.zeros((2, 4, 4), np.uint8), 5)


def test_hard_case_tags_follow_the_geometry():
    inside = {"com_offset": 0.5, "com_beyond_outer": 0.0, "over_fraction": 1.0,
              "inside_fraction": 1.0}
    assert object_tags({**inside, "top_above_rim": -0.1}) == set()
    assert object_tags({**inside, "top_above_rim": NEAR_RIM_M / 2}) == {"near_rim"}
    assert object_tags({**inside, "top_above_rim": -NEAR_RIM_M / 2}) == {"near_rim"}
    fell = {"com_offset": 2.0, "com_beyond_outer": 1.0, "over_fraction": 0.0,
            "inside_fraction": 0.0, "top_above_rim": 0.0}
    assert object_tags(fell) == set()                 # beside the container: no rim
    across = {**fell, "com_offset": 1.02, "com_beyond_outer": 0.0, "over_fraction": 0.6}
    assert object_tags(across) == {"near_rim", "across_wall"}
    assert object_rim_gap({**inside, "top_above_rim": -0.004}) == 0.004
    assert object_rim_gap(fell) is None


def test_rim_gap_bins_cover_every_gap_once():
    names = rim_gap_bin_names()
    assert names[0] == "0-2 mm" and names[-1] == ">= 20 mm"
    assert [rim_gap_bin(g) for g in (0.0, 0.0019, 0.002, 0.0049, 0.007, 0.015, 0.02, 0.5)] \
        == [0, 0, 1, 1, 2, 3, 4, 4]
    assert rim_gap_bin(None) == len(names) - 1     # nothing over the container: the open bin


def test_hard_case_report_counts_mistakes_per_tag():
    rows = [{"episode": 0, "correct": True}, {"episode": 1, "correct": False},
            {"episode": 2, "correct": False}, {"episode": 3, "correct": True}]
    cases = {0: HardCase((), None), 1: HardCase(("near_rim",), 0.001),
             2: HardCase((), 0.3), 3: HardCase(("across_wall", "near_rim"), 0.003)}
    hard = hard_case_report(rows, cases)["hard_cases"]
    assert hard["images"] == {"near_rim": 2, "across_wall": 1}
    assert hard["mistakes"] == {"near_rim": 1, "across_wall": 0, "untagged": 1}
    assert hard["untagged_images"] == 2 and hard["untagged_image_all_correct"] == 0.5
    by_gap = {e["bin"]: e for e in hard["by_rim_gap"]}
    assert by_gap["0-2 mm"] == {"bin": "0-2 mm", "images": 1, "mistakes": 1,
                                "image_all_correct": 0.0}
    assert by_gap["2-5 mm"]["image_all_correct"] == 1.0
    assert by_gap[">= 20 mm"]["images"] == 2 and by_gap[">= 20 mm"]["mistakes"] == 1
    assert by_gap["5-10 mm"]["images"] == 0 and by_gap["5-10 mm"]["image_all_correct"] is None
    assert hard_case_report(rows, None) == {}
