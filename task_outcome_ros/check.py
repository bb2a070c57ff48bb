"""``outcome/check``: "did the place I just finished work?", answered from a fresh frame.

A manipulation stack asks once, after its place action ends. The answer must describe the
scene *after* the request, never a frame taken before it: the reply comes from the first
frame whose header stamp is later than the request's arrival at the node (both in the node's
ROS clock, so replays need ``use_sim_time``). No frame in time: a reply saying so.

This module is the bookkeeping and the reply's content, with no rclpy, so it is tested alone;
node.py wires it to the service (a coroutine that polls the book) and to its worker thread,
which finishes frames.
"""

from __future__ import annotations

import itertools
import json
import threading
from dataclasses import dataclass
from typing import Any

from task_outcome_ros.outcome_report import ERROR, status_outcomes

SCHEMA = "task_outcome_ros/check/1"


@dataclass
class Answer:
    """What one check request is answered with (the Trigger response's two fields)."""

    success: bool
    message: str  # JSON, see ``frame_answer``


class CheckBook:
    """Pending check requests; thread-safe. A frame finished by the node's worker thread
    answers the requests that arrived before it was taken (``on_frame``); the service
    collects its answer with ``poll``, which never blocks."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: dict[int, int] = {}            # token -> arrival ns
        self._answers: dict[int, Answer] = {}
        self._tokens = itertools.count()

    def ask(self, arrival_ns: int) -> int:
        with self._lock:
            token = next(self._tokens)
            self._pending[token] = arrival_ns
            return token

    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def on_frame(self, stamp_ns: int, answer: Answer) -> list[int]:
        """A processed frame: it answers every request that arrived before it was taken."""
        with self._lock:
            done = [t for t, arrival in self._pending.items() if stamp_ns > arrival]
            for token in done:
                del self._pending[token]
                self._answers[token] = answer
            return done

    def release_all(self, why: str) -> None:
        """Shutting down: every waiting request returns now, saying ``why``."""
        with self._lock:
            for token in list(self._pending):
                del self._pending[token]
                self._answers[token] = no_frame_answer(why)

    def poll(self, token: int, timed_out: bool, timeout_s: float) -> Answer | None:
        """``token``'s answer if it has one; else the timeout answer once ``timed_out``; else
        None (still waiting)."""
        with self._lock:
            answer = self._answers.pop(token, None)
            if answer is None and not timed_out:
                return None
            self._pending.pop(token, None)
            return answer or no_frame_answer(f"no frame within {timeout_s:g} s")


def no_frame_answer(reason: str) -> Answer:
    """A reply no frame answered (a timeout, a shutdown): success false, no stamp."""
    return Answer(False, json.dumps({"schema": SCHEMA, "reason": reason, "stamp": None},
                                    separators=(",", ":")))


def frame_answer(stamp: tuple[int, int], frame_id: str, fields: Any,
                 outside_envelope: list[str] | None, envelope_checked: bool) -> Answer:
    """The reply for one processed frame. ``fields``: its outcome_report.StatusFields.

    ``success`` only when nothing but success-like outcomes are present (or nothing at all)
    and the frame is not outside the trained envelope. Which outcomes there are, and which
    are failure modes, the status itself says (its ``label_table`` value): any task's model.
    """
    values = dict(fields.values)
    if fields.level == ERROR:
        summary = {"schema": SCHEMA, "stamp": _stamp(stamp), "frame_id": frame_id,
                   "reason": f"frame not processed: {fields.message}"}
        return Answer(False, json.dumps(summary, separators=(",", ":")))
    outcomes = status_outcomes(values)
    present = [n for n in outcomes.names if values.get(f"{n}.present") == "true"]
    failures = []
    for name in outcomes.failures:
        for k in range(int(values.get(f"{name}.objects", 0))):
            failures.append({"outcome": name,
                             "centroid_px": _floats(values.get(f"{name}.{k}.centroid_px")),
                             "centroid_m": _floats(values.get(f"{name}.{k}.centroid_m"))})
    envelope = values.get("envelope", "unchecked")
    outside = bool(outside_envelope)
    failed = [n for n in present if n in outcomes.failures]
    reason = ("outside the trained envelope" if outside
              else f"failure: {','.join(failed)}" if failed else "success")
    summary = {"schema": SCHEMA, "stamp": _stamp(stamp), "frame_id": frame_id,
               "outcomes": present, "failures": failures, "envelope": envelope,
               "envelope_checked": envelope_checked, "reason": reason}
    return Answer(not failed and not outside, json.dumps(summary, separators=(",", ":")))


def _stamp(stamp: tuple[int, int]) -> dict:
    return {"sec": int(stamp[0]), "nanosec": int(stamp[1])}


def _floats(text: str | None) -> list[float] | None:
    return None if text is None else [float(v) for v in text.split(",")]
