"""Fragment absorption (one object, one outcome), the hard-case tags and the size bins of the
evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS, absorb_fragments, fragment_threshold
from task_outcome_ros.labels import DEFAULT_TABLE, FIXTURE
from training.evaluate import hard_case_report
from training.fixture import Table
from training.hard_cases import (
    NEAR_BOUNDARY_M,
    HardCase,
    gap_bin,
    gap_bin_names,
    object_gap,
    object_tags,
)
from training.rest_place import (
    BENEATH_SUPPORT,
    BOTH,
    ON_SUPPORT,
    object_place,
    place_of,
    recall_by_place,
)
from training.size_recall import SIZE_BINS_PX, recall_by_size, size_bin, size_bin_names

pytestmark = pytest.mark.unit

# The default task's outcome ids, for hand-made label images.
SUCCESS_ID, FELL_ID, STUCK_ID = (DEFAULT_TABLE.outcome_ids[name] for name in
                                 ("success", "fell_outside", "stuck_on_rim"))


def _scene() -> np.ndarray:
    labels = np.zeros((60, 80), np.uint8)
    labels[5:25, 5:25] = FELL_ID            # a fell object ...
    labels[5:8, 22:25] = STUCK_ID           # ... with a 9-pixel stuck fringe on its corner
    labels[40:44, 60:64] = SUCCESS_ID       # a 16-pixel object of its own
    labels[30:50, 30:50] = FIXTURE
    labels[35:38, 35:38] = STUCK_ID         # a small stuck object on the container only
    return labels


def test_a_small_fringe_takes_the_outcome_of_the_object_it_sits_on():
    labels = _scene()
    out = absorb_fragments(labels, 10)
    assert (out[5:25, 5:25] == FELL_ID).all()
    changed = out != labels
    assert changed.sum() == 9                  # nothing else moved
    assert (labels == _scene()).all()          # the input is not modified


def test_lone_small_objects_and_large_regions_are_kept():
    labels = _scene()
    assert (absorb_fragments(labels, 9) == labels).all()     # 9 px is not < 9
    assert (absorb_fragments(labels, 0) == labels).all()     # 0 turns it off
    out = absorb_fragments(labels, 1000)
    assert (out[40:44, 60:64] == SUCCESS_ID).all()           # touches no other outcome
    assert (out[35:38, 35:38] == STUCK_ID).all()             # touches only the container


def test_decisions_use_the_input_labels_not_earlier_absorptions():
    """Two touching fragments on a success box each join the box, whatever the class order."""
    labels = np.zeros((30, 30), np.uint8)
    labels[2:28, 2:28] = SUCCESS_ID
    labels[10:12, 10:12] = FELL_ID
    labels[10:12, 12:14] = STUCK_ID
    out = absorb_fragments(labels, 5)
    assert (out[2:28, 2:28] == SUCCESS_ID).all()


def test_the_table_says_which_ids_are_outcomes():
    """Id 5 is no class of the default task but an outcome of the shelf task (``tipped``): a
    fringe of it on a fell_off object is absorbed only under the shelf table."""
    from model_helpers import SHELF_TABLE

    ids = SHELF_TABLE.outcome_ids
    labels = np.zeros((30, 30), np.uint8)
    labels[2:28, 2:28] = ids["fell_off"]
    labels[10:12, 10:12] = ids["tipped"]
    assert (absorb_fragments(labels, 5) == labels).all()
    out = absorb_fragments(labels, 5, SHELF_TABLE)
    assert (out[2:28, 2:28] == ids["fell_off"]).all()


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
    assert object_tags({**inside, "top_above_region": -0.1}) == set()
    assert object_tags({**inside, "top_above_region": NEAR_BOUNDARY_M / 2}) == {"near_boundary"}
    assert object_tags({**inside, "top_above_region": -NEAR_BOUNDARY_M / 2}) == {"near_boundary"}
    fell = {"com_offset": 2.0, "com_beyond_outer": 1.0, "over_fraction": 0.0,
            "inside_fraction": 0.0, "top_above_region": 0.0}
    assert object_tags(fell) == set()                 # beside the container: no boundary
    across = {**fell, "com_offset": 1.02, "com_beyond_outer": 0.0, "over_fraction": 0.6}
    assert object_tags(across) == {"near_boundary", "across_edge"}
    assert object_gap({**inside, "top_above_region": -0.004}) == 0.004
    assert object_gap(fell) is None


def test_gap_bins_cover_every_gap_once():
    names = gap_bin_names()
    assert names[0] == "0-2 mm" and names[-1] == ">= 20 mm"
    assert [gap_bin(g) for g in (0.0, 0.0019, 0.002, 0.0049, 0.007, 0.015, 0.02, 0.5)] \
        == [0, 0, 1, 1, 2, 3, 4, 4]
    assert gap_bin(None) == len(names) - 1     # nothing over the fixture: the open bin


def test_hard_case_report_counts_mistakes_per_tag():
    rows = [{"episode": 0, "correct": True}, {"episode": 1, "correct": False},
            {"episode": 2, "correct": False}, {"episode": 3, "correct": True}]
    cases = {0: HardCase((), None), 1: HardCase(("near_boundary",), 0.001),
             2: HardCase((), 0.3), 3: HardCase(("across_edge", "near_boundary"), 0.003)}
    hard = hard_case_report(rows, cases)["hard_cases"]
    assert hard["images"] == {"near_boundary": 2, "across_edge": 1}
    assert hard["mistakes"] == {"near_boundary": 1, "across_edge": 0, "untagged": 1}
    assert hard["untagged_images"] == 2 and hard["untagged_image_all_correct"] == 0.5
    by_gap = {e["bin"]: e for e in hard["by_boundary_gap"]}
    assert by_gap["0-2 mm"] == {"bin": "0-2 mm", "images": 1, "mistakes": 1,
                                "image_all_correct": 0.0}
    assert by_gap["2-5 mm"]["image_all_correct"] == 1.0
    assert by_gap[">= 20 mm"]["images"] == 2 and by_gap[">= 20 mm"]["mistakes"] == 1
    assert by_gap["5-10 mm"]["images"] == 0 and by_gap["5-10 mm"]["image_all_correct"] is None
    assert hard_case_report(rows, None) == {}


def test_size_bins_scale_with_the_image_area():
    assert size_bin_names()[0] == "50-100" and size_bin_names()[-1] == ">= 1600"
    assert [size_bin(p, 480, 640) for p in (49, 50, 99, 100, 399, 1600, 10**6)] \
        == [None, 0, 0, 1, 2, 5, 5]
    # At 320 x 240 every edge is a quarter (rounded like the presence rule: 50 -> 12): 25
    # pixels there are 100 at 640 x 480.
    assert [size_bin(p, 240, 320) for p in (11, 12, 25, 400)] == [None, 0, 1, 5]


def test_recall_by_size_counts_found_outcomes_per_bin():
    def row(truth_px, found):
        return {"truth": {"fell": truth_px >= 50, "ok": False},
                "pred": {"fell": found, "ok": False},
                "truth_pixels": {"fell": truth_px, "ok": 0}}
    rows = [row(80, False), row(90, True), row(150, False), row(5000, True), row(0, True)]
    report = recall_by_size(rows, ["fell", "ok"], 480, 640)
    fell = {e["bin"]: e for e in report["by_outcome"]["fell"]}
    assert fell["50-100"] == {"bin": "50-100", "images": 2, "found": 1, "recall": 0.5}
    assert fell["100-200"]["recall"] == 0.0 and fell[">= 1600"]["recall"] == 1.0
    assert fell["200-400"] == {"bin": "200-400", "images": 0, "found": 0, "recall": None}
    # An invented outcome (truly absent) is not a recall event.
    assert sum(e["images"] for e in report["by_outcome"]["ok"]) == 0
    assert report["size_bins_px"] == list(SIZE_BINS_PX)


def test_places_split_at_half_the_tables_height_and_recall_is_counted_per_place():
    table = Table(0.9, 0.7, 0.1, -0.05, top_z=0.75, floor_z=0.0)
    assert [object_place((0.0, 0.0, z), table) for z in (0.78, 0.38, 0.37, 0.03)] \
        == [ON_SUPPORT, ON_SUPPORT, BENEATH_SUPPORT, BENEATH_SUPPORT]
    assert place_of({ON_SUPPORT}) == ON_SUPPORT and place_of({ON_SUPPORT, BENEATH_SUPPORT}) == BOTH

    def row(episode, truth_px, found):
        return {"episode": episode, "truth": {"fell": truth_px >= 50},
                "pred": {"fell": found}, "truth_pixels": {"fell": truth_px}}
    rows = [row(0, 300, False), row(1, 300, True), row(2, 300, True), row(3, 5000, True),
            row(4, 0, True)]
    places = {0: {"fell": BENEATH_SUPPORT}, 1: {"fell": BENEATH_SUPPORT}, 2: {"fell": ON_SUPPORT},
              3: {"fell": BOTH}, 4: {"fell": BENEATH_SUPPORT, "ok": ON_SUPPORT}}
    report = recall_by_place(rows, places, ["fell"], 480, 640)["recall_by_place"]
    fell = report["by_outcome"]["fell"]
    found = {place: (sum(e["found"] for e in bins), sum(e["images"] for e in bins))
             for place, bins in fell.items()}
    # Episode 4's fallen object is absent from its truth: no recall event anywhere.
    assert found == {ON_SUPPORT: (1, 1), BENEATH_SUPPORT: (1, 2), BOTH: (1, 1)}
    assert {e["bin"]: e["images"] for e in fell[BENEATH_SUPPORT]}["200-400"] == 2
    assert recall_by_place(rows, None, ["fell"], 480, 640) == {}
