"""``outcome/check`` on the real node over DDS, and its bookkeeping alone.

The node runs the depth-band model (test/model_helpers.py): a frame whose near part is a box
says fell_outside, a frame of far floor only says success, so every reply can be told apart.
Stamps are the client's ROS clock: "old" frames are stamped seconds before the request.
"""

from __future__ import annotations

import json
import random
import time

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 rclpy is not installed")

import node_helpers as nh  # noqa: E402

from task_outcome_ros.check import SCHEMA  # noqa: E402
from task_outcome_ros.client import OutcomeCheckClient, parse  # noqa: E402

pytestmark = pytest.mark.ros

TIMEOUT_S = 1.0
FLOOR = np.full((60, 80), 2.2, np.float32)   # success everywhere (beyond the band's 2 m)
WITH_BOX = FLOOR.copy()
WITH_BOX[15:35, 20:45] = 1.9                  # a near box: fell_outside


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("check")
    domain = random.randint(1, 200)
    ckpt = nh.make_depth_band_checkpoint(tmp / "band.pt")
    proc = nh.NodeProcess(["-p", f"model_path:={ckpt}", "-p", "qos:=reliable", "-p",
                           f"check_timeout_s:={TIMEOUT_S}", "-p", "publish_overlay:=false"],
                          domain, tmp / "node.log")
    client = nh.OutcomeClient(domain)
    try:
        client.wait_for_node(proc)
        checker = OutcomeCheckClient(client.node)
        assert checker.wait_for_service(20.0), proc.log()
        yield client, checker, proc
    finally:
        client.close()
        proc.stop()


def _now(client, offset_s: float = 0.0) -> tuple[int, int]:
    ns = client.node.get_clock().now().nanoseconds + int(offset_s * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


def _publish(client, depth, stamp) -> None:
    client.image_pub.publish(nh.depth_msg(depth, stamp=stamp))


def _wait(client, future, timeout=5.0):
    assert client.spin_until(future.done, timeout), "no reply"
    response = future.result()
    return parse(response.success, response.message)


def _answer_with_fresh_frames(client, future, depth, timeout=8.0):
    """Publish a fresh frame every 0.1 s until the call is answered (however late the
    request reaches the node); returns the reply and the first fresh frame's stamp (ns)."""
    first = None
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        stamp = _now(client)
        first = first or stamp[0] * 1_000_000_000 + stamp[1]
        _publish(client, depth, stamp)
        client.spin_until(future.done, 0.1)
    return _wait(client, future, 0.1), first


def test_the_reply_never_describes_a_frame_older_than_the_request(node):
    """Old frame, request, old frame, new frame: the reply is the new frame, every time."""
    client, checker, _ = node
    for trial in range(5):
        _publish(client, FLOOR, _now(client, -5.0))
        client.spin_until(lambda: False, 0.05)
        future = checker.call_async()
        client.spin_until(lambda: False, 0.1)  # the request reaches the node
        _publish(client, FLOOR, _now(client, -3.0))
        client.spin_until(lambda: False, 0.1)
        assert not future.done(), "answered from a frame stamped before the request"
        depth = WITH_BOX if trial % 2 else FLOOR
        result, first_fresh = _answer_with_fresh_frames(client, future, depth)
        assert result.stamp_ns >= first_fresh  # never the old frames around the request
        assert result.success == (depth is FLOOR)
        assert result.outcomes == (("success", "fell_outside") if depth is WITH_BOX
                                   else ("success",))


def test_no_frame_in_time_is_a_reply_saying_so_and_the_node_keeps_working(node):
    client, checker, _ = node
    started = time.monotonic()
    future = checker.call_async()
    # Meanwhile the node still answers frames (stamped before the request, so they do not
    # answer it): the waiting call does not block its executor.
    client.spin_until(lambda: False, 0.1)
    old = nh.depth_msg(FLOOR, stamp=_now(client, -1.0))
    reply = client.request(old, ("status",), resend_every=0.5)
    assert reply.status.status[0].message == "success"
    result = _wait(client, future, timeout=5.0)
    elapsed = time.monotonic() - started
    assert not result.success and result.reason == f"no frame within {TIMEOUT_S:g} s"
    assert result.stamp_ns is None
    # Not before its timeout; the bound above is _wait's (a node that never gave up fails it),
    # not a wall-clock figure a shared machine can break.
    assert elapsed >= TIMEOUT_S * 0.9


def test_the_reply_is_the_documented_json(node):
    client, checker, _ = node
    future = checker.call_async()
    _answer_with_fresh_frames(client, future, WITH_BOX)
    response = future.result()
    data = json.loads(response.message)
    assert set(data) == {"schema", "stamp", "frame_id", "outcomes", "failures", "envelope",
                         "envelope_checked", "reason"}
    assert data["schema"] == SCHEMA and set(data["stamp"]) == {"sec", "nanosec"}
    assert data["frame_id"] == "depth_optical" and data["reason"] == "failure: fell_outside"
    (failure,) = data["failures"]
    assert failure["outcome"] == "fell_outside" and failure["centroid_m"] is None
    u, v = failure["centroid_px"]
    assert 20 <= u <= 45 and 15 <= v <= 35  # the box's pixels
    assert data["envelope"].startswith("unchecked") and data["envelope_checked"] is False
    assert response.success is False


def test_concurrent_calls_are_all_answered_by_the_next_frame(node):
    client, checker, _ = node
    called = client.node.get_clock().now().nanoseconds
    futures = [checker.call_async() for _ in range(4)]
    _answer_with_fresh_frames(client, futures[0], FLOOR)
    for future in futures[1:]:  # the others by the same frame, or by the next ones
        _answer_with_fresh_frames(client, future, FLOOR)
    results = [_wait(client, f, 0.1) for f in futures]
    assert all(r.success and r.stamp_ns > called for r in results)


def test_a_call_during_a_burst_gets_a_frame_from_after_it(node):
    client, checker, _ = node
    for _ in range(10):
        _publish(client, WITH_BOX, _now(client, -2.0))
    called = client.node.get_clock().now().nanoseconds
    future = checker.call_async()
    for _ in range(10):  # a burst of fresh frames, back to back
        _publish(client, FLOOR, _now(client))
    result, _ = _answer_with_fresh_frames(client, future, FLOOR)
    assert result.success and result.stamp_ns > called  # one of the fresh ones


def test_the_client_checks_from_a_script(node):
    """OutcomeCheckClient.check spins the caller's node until the reply: a frame the camera
    takes while the call waits (published from another thread, as a driver would)."""
    import threading

    client, checker, _ = node
    called = client.node.get_clock().now().nanoseconds
    camera = threading.Timer(0.3, lambda: _publish(client, FLOOR, _now(client)))
    camera.start()
    try:
        result = checker.check(timeout_s=5.0)
    finally:
        camera.join()
    assert result.success and result.reason == "success" and result.stamp_ns > called
