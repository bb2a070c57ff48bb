"""Ask outcome_node whether the place that just ended worked: ``outcome/check`` from Python.

What a behaviour-tree action or a MoveIt task script calls after its place action::

    from task_outcome_ros.client import OutcomeCheckClient

    checker = OutcomeCheckClient(node)           # any rclpy node of the caller
    result = checker.check(timeout_s=3.0)        # spins ``node`` until the reply
    if not result.success:
        for failure in result.failures:          # e.g. fell_outside at (x, y, z)
            print(failure.outcome, failure.centroid_m)

The reply describes a frame stamped after the request reached the node, never an older one.
``call_async`` and ``parse`` serve callers that spin their own executor.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from task_outcome_ros.check import SCHEMA
from task_outcome_ros.topics import CHECK_SERVICE

SERVICE = CHECK_SERVICE


@dataclass(frozen=True)
class FailureObject:
    """One object of a failure outcome: its pixel centroid and, with camera_info, its
    position in the camera's optical frame (metres)."""

    outcome: str
    centroid_px: tuple[float, float] | None
    centroid_m: tuple[float, float, float] | None


@dataclass(frozen=True)
class CheckResult:
    success: bool                       # only success-like outcomes, inside the envelope
    reason: str                         # "success", "failure: fell_outside", a timeout, ...
    stamp_ns: int | None                # the frame's header stamp; None when no frame came
    frame_id: str = ""
    outcomes: tuple[str, ...] = ()      # present in that frame
    failures: tuple[FailureObject, ...] = ()
    envelope: str = ""                  # "ok", "outside: <why>" or "unchecked: ..."
    raw: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)


class CheckError(RuntimeError):
    """The service could not be reached or did not answer; the text says which."""


def parse(success: bool, message: str) -> CheckResult:
    """A Trigger response's fields -> CheckResult (CheckError if it is not the node's JSON)."""
    try:
        data = json.loads(message)
    except json.JSONDecodeError as exc:
        raise CheckError(f"{SERVICE} replied with something other than its JSON: "
                         f"{message[:80]!r} ({exc})") from None
    schema = data.get("schema") if isinstance(data, dict) else None
    if schema != SCHEMA:
        raise CheckError(f"{SERVICE} replied with schema {schema!r}, expected {SCHEMA!r}: is "
                         "this outcome_node of another version?")
    try:
        stamp = data.get("stamp")
        stamp_ns = None if stamp is None else stamp["sec"] * 1_000_000_000 + stamp["nanosec"]
        failures = tuple(FailureObject(f["outcome"], _tuple(f.get("centroid_px")),
                                       _tuple(f.get("centroid_m")))
                         for f in data.get("failures", []))
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckError(f"{SERVICE} replied with a malformed {SCHEMA} message: "
                         f"{type(exc).__name__}: {exc}") from None
    return CheckResult(bool(success), str(data.get("reason", "")), stamp_ns,
                       str(data.get("frame_id", "")), tuple(data.get("outcomes", [])),
                       failures, str(data.get("envelope", "")), data)


class OutcomeCheckClient:
    """A client of ``outcome/check`` (relative: follows the node's namespace) on ``node``."""

    def __init__(self, node: Any, service: str = SERVICE) -> None:
        from std_srvs.srv import Trigger

        self._node = node
        self._trigger = Trigger
        self._client = node.create_client(Trigger, service)

    def wait_for_service(self, timeout_s: float = 5.0) -> bool:
        return self._client.wait_for_service(timeout_sec=timeout_s)

    def call_async(self) -> Any:
        """The rclpy Future of one request (for callers that spin their own executor)."""
        return self._client.call_async(self._trigger.Request())

    def check(self, timeout_s: float = 5.0) -> CheckResult:
        """Call and spin ``node`` until the reply (CheckError after ``timeout_s``). Use it from
        code that is not itself running in ``node``'s executor."""
        import rclpy

        if not self._client.service_is_ready() and not self.wait_for_service(timeout_s):
            raise CheckError(f"{self._client.srv_name} is not available: is outcome_node "
                             "running in this namespace?")
        future = self.call_async()
        # The node's own executor if it has one (it must not be spinning in another thread),
        # else one in the node's context (not the global one: the node may live in its own).
        executor = self._node.executor
        if executor is None:
            from rclpy.executors import SingleThreadedExecutor

            executor = SingleThreadedExecutor(context=self._node.context)
        rclpy.spin_until_future_complete(self._node, future, executor=executor,
                                         timeout_sec=timeout_s)
        if not future.done():
            raise CheckError(f"{self._client.srv_name} did not answer within {timeout_s:g} s")
        response = future.result()
        return parse(response.success, response.message)


def _tuple(values: list[float] | None) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)
