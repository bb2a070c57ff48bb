"""How sure a figure is: Wilson intervals, the exact McNemar test, and `training compare`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from training.__main__ import main as training_main
from training.compare import compare_reports, load_result, unpaired_points
from training.stats import exact_mcnemar_p, holm_adjusted, paired_comparison, wilson_interval

pytestmark = pytest.mark.unit


def test_wilson_interval_matches_the_textbook_values_and_stays_inside_0_1():
    # Newcombe (1998), table I: 81 of 263 -> 0.2553-0.3662; 15 of 148 -> 0.0624-0.1605.
    assert wilson_interval(81, 263) == pytest.approx((0.2553, 0.3662), abs=1e-4)
    assert wilson_interval(15, 148) == pytest.approx((0.0624, 0.1605), abs=1e-4)
    low, high = wilson_interval(300, 300)
    assert high == 1.0 and 0.98 < low < 1.0         # all right: still an interval
    assert wilson_interval(0, 10)[0] == 0.0
    # What the robustness suite's docstring quotes: 97 of 100 vs 291 of 300.
    assert wilson_interval(97, 100) == pytest.approx((0.915, 0.990), abs=1e-3)
    assert wilson_interval(291, 300) == pytest.approx((0.944, 0.984), abs=1e-3)
    for bad in ((5, 0), (-1, 10), (11, 10)):
        with pytest.raises(ValueError, match="need 0 <= right <= n"):  # not sqrt's domain
            wilson_interval(*bad)


def test_exact_mcnemar_counts_only_the_discordant_images():
    assert exact_mcnemar_p(0, 0) == 1.0
    assert exact_mcnemar_p(3, 3) == 1.0
    assert exact_mcnemar_p(0, 5) == pytest.approx(2 / 32)       # 5 coin flips all one way
    assert exact_mcnemar_p(1, 4) == pytest.approx(2 * 6 / 32)   # P(<= 1 of 5) twice
    assert exact_mcnemar_p(4, 1) == exact_mcnemar_p(1, 4)
    # 0 vs 10 is significant, 2 vs 8 is not at 5 %.
    assert exact_mcnemar_p(0, 10) < 0.01 and exact_mcnemar_p(2, 8) > 0.05
    with pytest.raises(ValueError, match="counts must be >= 0"):
        exact_mcnemar_p(-1, 2)


def test_paired_comparison_splits_the_mistakes_by_model():
    row = paired_comparison([3, 7, 9], [7, 11, 12, 13], n=100)
    assert row["only_a_wrong"] == [3, 9] and row["only_b_wrong"] == [11, 12, 13]
    assert row["both_wrong"] == 1
    assert row["a"]["all_correct"] == 0.97 and row["b"]["mistakes"] == 4
    assert row["p_value"] == pytest.approx(exact_mcnemar_p(2, 3))
    with pytest.raises(ValueError, match="cannot come from"):
        paired_comparison(range(5), [], n=4)


def test_holm_adjustment_matches_the_textbook_step_down():
    # R: p.adjust(c(0.01, 0.04, 0.03, 0.005), "holm") -> 0.03 0.06 0.06 0.02 (input order; the
    # third-smallest's 0.06 carries over to the largest, whose own 0.04 would undercut it).
    assert holm_adjusted([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjusted([0.049] * 22) == [1.0] * 22       # one point of a suite: not a finding
    assert holm_adjusted([0.2]) == [0.2] and holm_adjusted([]) == []
    with pytest.raises(ValueError, match="must lie in"):
        holm_adjusted([0.5, 1.5])


def _eval(data: str, mistakes: list[int], n: int = 300) -> dict:
    return {"data": data, "split": "val", "n_images": n, "mistakes": mistakes,
            "image_all_correct": 1 - len(mistakes) / n}


def _robustness(mistakes_per_point: list[list[int]] | None, n: int = 100) -> dict:
    entry = {"values": [0.0, 3.0],
             "image_all_correct": [1 - len(m) / n for m in mistakes_per_point or [[], [1, 2]]]}
    if mistakes_per_point is not None:
        entry["mistakes"] = mistakes_per_point
    return {"data": "runs/default", "images": n, "factors": {"support_tilt_deg": entry}}


def test_compare_pairs_evaluations_and_robustness_points_on_the_same_images():
    rows = compare_reports("eval", _eval("runs/x", [1, 2, 3]), "eval", _eval("runs/x", [2]))
    assert len(rows) == 1 and rows[0]["only_a_wrong"] == [1, 3] and rows[0]["both_wrong"] == 1
    rows = compare_reports("robustness", _robustness([[], [4, 5, 6]]),
                           "robustness", _robustness([[4], [4]]))
    assert [r["set"] for r in rows] == ["as trained", "support_tilt_deg 3.0"]
    assert rows[0]["only_b_wrong"] == [4] and rows[1]["only_a_wrong"] == [5, 6]
    # Over several points each row also carries its Holm-adjusted p-value.
    assert [r["p_holm"] for r in rows] == pytest.approx(holm_adjusted([r["p_value"]
                                                                       for r in rows]))
    assert rows[1]["p_value"] == pytest.approx(0.5) and rows[1]["p_holm"] == 1.0  # 2 x 0.5
    # Results from before the suite kept its mistakes: rates and intervals, no paired test.
    old = compare_reports("robustness", _robustness(None), "robustness", _robustness([[], []]))
    assert all(r["p_value"] is None for r in old)
    assert old[1]["a"]["all_correct"] == 0.98
    assert old[1]["a"]["ci95"] == pytest.approx(wilson_interval(98, 100))


def test_compare_names_the_points_only_one_result_holds():
    """A suite made before a point was added pairs the rest; the new point is named unpaired."""
    old, new = _robustness([[], [1]]), _robustness([[], [1]])
    new["factors"]["scene_emptied"] = {"values": [False, True], "image_all_correct": [1.0, 0.0],
                                       "mistakes": [[], [1, 2]]}
    rows = compare_reports("robustness", old, "robustness", new)
    assert [r["set"] for r in rows] == ["as trained", "support_tilt_deg 3.0"]
    assert unpaired_points(old, new) == ([], ["scene_emptied True"])
    assert unpaired_points(new, new) == ([], [])


def test_compare_reports_the_training_condition_once():
    """Every factor's first value is the training condition, the same scenes each time."""
    two = _robustness([[], [1]])
    two["factors"]["camera_roll_deg"] = {"values": [0.0, 10.0], "image_all_correct": [1.0, 0.97],
                                         "mistakes": [[], [7, 8, 9]]}
    rows = compare_reports("robustness", two, "robustness", two)
    assert [r["set"] for r in rows] == ["as trained", "support_tilt_deg 3.0",
                                        "camera_roll_deg 10.0"]


def test_compare_refuses_different_images_or_kinds():
    with pytest.raises(ValueError, match="not the same images"):
        compare_reports("eval", _eval("runs/x", []), "eval", _eval("runs/y", []))
    with pytest.raises(ValueError, match="not the same images"):
        compare_reports("eval", _eval("runs/x", [], 300), "eval", _eval("runs/x", [], 200))
    with pytest.raises(ValueError, match="cannot compare"):
        compare_reports("eval", _eval("runs/x", []), "robustness", _robustness(None))


def test_two_runs_with_the_same_manifest_hold_the_same_images(tmp_path, monkeypatch):
    """A second recipe trained on a linked (or copied) dataset is compared on its images."""
    monkeypatch.chdir(tmp_path)
    for run, manifest in (("first", '{"images": [1, 2]}'), ("linked", None),
                          ("copy", '{"images": [1, 2]}'), ("other", '{"images": [3]}')):
        Path(run).mkdir()
        if manifest is None:
            (Path(run) / "manifest.json").symlink_to(tmp_path / "first" / "manifest.json")
        else:
            (Path(run) / "manifest.json").write_text(manifest)
    for same in ("linked", "copy"):
        rows = compare_reports("eval", _eval("first", [1, 2]), "eval", _eval(same, [2]))
        assert rows[0]["only_a_wrong"] == [1]
    for different in ("other", "missing"):
        with pytest.raises(ValueError, match="not the same images"):
            compare_reports("eval", _eval("first", []), "eval", _eval(different, []))


def test_training_compare_reads_result_folders(tmp_path, capsys):
    for name, mistakes in (("a", [1, 2, 3, 4, 5, 6]), ("b", [6])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "eval.json").write_text(json.dumps(_eval("runs/x", mistakes)))
    assert load_result(tmp_path / "a")[0] == "eval"
    assert training_main(["compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    out = capsys.readouterr().out
    p = exact_mcnemar_p(5, 0)
    assert "only A wrong 5, only B wrong 0, both 1" in out and f"p = {p:.3g}" in out
    assert "Holm" not in out                                # one set: nothing to adjust
    assert math.isclose(p, 2 / 32)
    (tmp_path / "empty").mkdir()
    assert training_main(["compare", str(tmp_path / "a"), str(tmp_path / "empty")]) == 2
    assert "expected one of eval.json, robustness.json" in capsys.readouterr().err
