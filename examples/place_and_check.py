"""A manipulation stack's side of outcome_node: place, then ask whether it worked.

A fake "place" node stands in for the robot and its depth camera. For each place it streams
the depth frames of one recorded scene (from a bag, restamped with the current time, as a
camera would), "finishes" the place, calls ``outcome/check`` and reacts:

    only success-like outcomes   -> next place
    a failure mode               -> "retry", with the object's 3-D position in the camera frame

The outcomes are the model's (its label table: success, fell_outside and stuck_on_rim for
the default task); the node's reply names them, so nothing here assumes a task.

    python examples/place_and_check.py runs/demo/input_bag --places 5

Start outcome_node first (``ros2 run task_outcome_ros outcome_node``); ``make demo`` runs this
at its end. The bag's ``ground_truth.json``, when there is one, is printed beside each answer.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy

from task_outcome_ros import bag_io
from task_outcome_ros.client import CheckError, OutcomeCheckClient, parse
from task_outcome_ros.ground_truth import load_ground_truth

CAMERA_HZ = 15.0


def load_scenes(bag: Path, limit: int) -> list[tuple[bytes, bytes | None, int]]:
    """(raw depth Image, raw CameraInfo or None, recorded stamp ns) per scene of the bag."""
    reader = bag_io.open_reader(bag)
    try:
        image = bag_io.require_connection(reader, bag_io.DEPTH_TOPIC, "", bag_io.IMAGE, bag)
        info = bag_io.bag_connection(reader, bag_io.CAMERA_INFO_TOPIC, "", bag_io.CAMERA_INFO)
        scenes, last_info = [], None
        for conn, _, raw in reader.messages(connections=[c for c in (image, info) if c]):
            if info is not None and conn.id == info.id:
                last_info = bytes(raw)
            elif len(scenes) < limit:
                stamp = bag_io.stamp_to_ns(bag_io.deserialize(raw, bag_io.IMAGE).header.stamp)
                scenes.append((bytes(raw), last_info, stamp))
        return scenes
    finally:
        reader.close()


class FakeCamera:
    """Publishes one scene's depth (and camera_info) at CAMERA_HZ, stamped now."""

    def __init__(self, node) -> None:
        from sensor_msgs.msg import CameraInfo, Image

        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.node = node
        self.image_pub = node.create_publisher(Image, "depth/image_raw", qos)
        self.info_pub = node.create_publisher(CameraInfo, "depth/camera_info", qos)
        self.scene = None
        node.create_timer(1.0 / CAMERA_HZ, self._tick)

    def show(self, scene: tuple[bytes, bytes | None, int]) -> None:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import CameraInfo, Image

        image = deserialize_message(scene[0], Image)
        info = deserialize_message(scene[1], CameraInfo) if scene[1] else None
        self.scene = (image, info)

    def _tick(self) -> None:
        if self.scene is None:
            return
        stamp = self.node.get_clock().now().to_msg()
        image, info = self.scene
        for msg in (info, image):  # camera_info first, as drivers do
            if msg is not None:
                msg.header.stamp = stamp
        if info is not None:
            self.info_pub.publish(info)
        self.image_pub.publish(image)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bag", type=Path, help="a bag of depth frames (one scene per frame)")
    parser.add_argument("--places", type=int, default=5, help="how many places to check")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds per check")
    args = parser.parse_args(argv)
    scenes = load_scenes(args.bag, args.places)
    truth = {f["stamp_ns"]: f for f in (load_ground_truth(args.bag) or {"frames": []})["frames"]}

    rclpy.init()
    node = rclpy.create_node("place_and_check")
    camera = FakeCamera(node)
    checker = OutcomeCheckClient(node)
    # The camera streams in the background, as a real one would; the check is sent from here.
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    code = 0
    try:
        if not checker.wait_for_service(30.0):
            print("place_and_check: outcome/check not available: start outcome_node first",
                  file=sys.stderr)
            return 2
        for k, scene in enumerate(scenes):
            camera.show(scene)          # the arm moves, the object is released ...
            time.sleep(0.3)             # ... and the place action ends here
            future = checker.call_async()
            deadline = time.monotonic() + args.timeout
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            if not future.done():
                raise CheckError(f"outcome/check did not answer within {args.timeout:g} s")
            result = parse(future.result().success, future.result().message)
            expected = truth.get(scene[2])
            said = ",".join(result.outcomes) or "nothing"
            verdict = "ok, next place" if result.success else "retry"
            line = f"place {k + 1}: {said} -> {verdict}"
            for failure in result.failures:
                where = failure.centroid_m or failure.centroid_px
                line += f"; {failure.outcome} at {tuple(round(v, 3) for v in where)}"
            if result.envelope.startswith("outside"):
                line += f" ({result.envelope})"
            if expected is not None:
                present = [name for name, there in expected["present"].items() if there]
                line += f"   [truth: {','.join(present) or 'nothing'}]"
            print(line, flush=True)
    except CheckError as exc:
        print(f"place_and_check: {exc}", file=sys.stderr)
        code = 1
    finally:
        camera.scene = None             # stop streaming, then the spinner, then the node
        executor.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
