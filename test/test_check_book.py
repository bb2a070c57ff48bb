"""outcome/check without DDS: the book of waiting requests and the reply's content."""

from __future__ import annotations

import json

import pytest

from task_outcome_ros.check import Answer, CheckBook, frame_answer
from task_outcome_ros.client import CheckError, parse
from task_outcome_ros.outcome_report import ERROR, OK, WARN, StatusFields

pytestmark = pytest.mark.unit


def _fields(level: int, message: str, **values: str) -> StatusFields:
    return StatusFields(level, message, list(values.items()))


def test_success_only_for_success_inside_the_envelope():
    ok = _fields(OK, "success", **{"success.present": "true", "fell_outside.objects": "0",
                                   "envelope": "ok"})
    assert frame_answer((1, 2), "cam", ok, [], True).success
    assert not frame_answer((1, 2), "cam", ok, ["fixture not seen"], True).success
    fell = _fields(WARN, "fell_outside", **{"fell_outside.present": "true",
                                            "fell_outside.objects": "1",
                                            "fell_outside.0.centroid_px": "3.0,4.0",
                                            "fell_outside.0.centroid_m": "0.1,0.2,1.5"})
    answer = frame_answer((1, 2), "cam", fell, [], True)
    assert not answer.success
    result = parse(answer.success, answer.message)
    assert result.failures[0].centroid_m == (0.1, 0.2, 1.5)
    assert result.stamp_ns == 1_000_000_002
    error = frame_answer((1, 2), "cam", _fields(ERROR, "bad depth image: x"), None, False)
    assert not error.success and "frame not processed" in json.loads(error.message)["reason"]


def test_the_book_answers_only_requests_older_than_the_frame_and_times_out_the_rest():
    book = CheckBook()
    early, late = book.ask(100), book.ask(200)
    answer = Answer(True, "{}")
    assert book.on_frame(150, answer) == [early]
    assert book.poll(early, False, 5.0) is answer  # answered already: no waiting
    assert book.on_frame(200, answer) == []   # stamped at the request: not after it
    assert book.poll(late, False, 0.05) is None and book.pending() == 1  # still waiting
    assert "no frame within 0.05 s" in book.poll(late, True, 0.05).message
    assert book.pending() == 0
    waiting = book.ask(300)
    book.release_all("shutting down")
    assert "shutting down" in book.poll(waiting, False, 5.0).message


def test_a_reply_that_is_not_the_nodes_json_is_a_clear_error():
    with pytest.raises(CheckError, match="JSON"):
        parse(True, "yes")
    with pytest.raises(CheckError, match="schema"):
        parse(True, json.dumps({"schema": "other/9"}))


MALFORMED = ["null", "42", json.dumps({"schema": "task_outcome_ros/check/1", "stamp": {"sec": 1}})]


@pytest.mark.parametrize("message", MALFORMED)
def test_malformed_replies_are_check_errors_not_crashes(message):
    with pytest.raises(CheckError):
        parse(True, message)


def _shelf_result(present: dict[str, bool]):
    """An OutcomeResult of a shelf model: each present outcome one 100-pixel object."""
    import numpy as np

    from task_outcome_ros.inference import DetectedObject, OutcomeResult

    objects = {name: [DetectedObject(name, 100, (3.0, 4.0), 1.5)] if there else []
               for name, there in present.items()}
    return OutcomeResult(labels=np.zeros((48, 64), np.uint8), present=present,
                         pixel_counts={n: 100 * p for n, p in present.items()},
                         objects=objects, inference_ms=1.0)


def test_another_tasks_status_and_reply_use_its_outcomes():
    """A shelf model's status names its outcomes and carries its table; the reply reads both
    from the status: a failure mode of that table is a failure, its success-like one is not."""
    from model_helpers import SHELF_TABLE

    from task_outcome_ros.outcome_report import label_table_value, status_fields

    none = dict.fromkeys(SHELF_TABLE.outcome_names, False)
    hanging = status_fields(_shelf_result({**none, "hanging_over_edge": True}),
                            table=SHELF_TABLE)
    values = dict(hanging.values)
    assert hanging.level == WARN and hanging.message == "hanging_over_edge"
    assert values["label_table"] == label_table_value(SHELF_TABLE)
    assert json.loads(values["label_table"]) == SHELF_TABLE.to_dict()["classes"]
    assert values["hanging_over_edge.0.centroid_px"] == "3.0,4.0"
    assert not any(key.startswith(("success.", "fell_outside.")) for key in values)
    answer = frame_answer((1, 2), "cam", hanging, [], False)
    result = parse(answer.success, answer.message)
    assert not result.success and result.outcomes == ("hanging_over_edge",)
    assert [f.outcome for f in result.failures] == ["hanging_over_edge"]
    assert json.loads(answer.message)["reason"] == "failure: hanging_over_edge"

    on_shelf = status_fields(_shelf_result({**none, "on_shelf": True}), table=SHELF_TABLE)
    assert on_shelf.level == OK
    assert frame_answer((1, 2), "cam", on_shelf, [], False).success


def test_status_outcomes_fall_back_to_the_keys_then_the_default_task():
    from model_helpers import SHELF_TABLE

    from task_outcome_ros.labels import DEFAULT_TABLE
    from task_outcome_ros.outcome_report import label_table_value, status_outcomes

    shelf = status_outcomes({"label_table": label_table_value(SHELF_TABLE)})
    assert shelf == (SHELF_TABLE.outcome_names, SHELF_TABLE.failures)
    # A status of an older node (no label_table value), or an unreadable one: the keys.
    for extra in ({}, {"label_table": "[{not json"}):
        older = status_outcomes({**extra, "success.present": "true",
                                 "fell_outside.present": "false", "envelope": "ok"})
        assert older == (("success", "fell_outside"), ("fell_outside",))
    assert status_outcomes({}) == (DEFAULT_TABLE.outcome_names, DEFAULT_TABLE.failures)
    # Another task's keys without a readable table: none of them can be judged a success.
    unknown = status_outcomes({"label_table": "[{not json", "on_shelf.present": "true"})
    assert unknown == (("on_shelf",), ("on_shelf",))
