"""``outcome_replay``: a bag's depth image and camera_info topics over DDS, in real time.

What a camera would do for outcome_node, from a recorded (or ``training export-bag``) bag:
waits (with a timeout) for a subscriber on the image topic, then publishes every message at its
original relative log time (scaled by ``--rate-factor``), optionally in a loop, and reports how
many it published. Messages are published as the bag's serialized CDR bytes (rclpy's
``Publisher.publish`` takes ``bytes``), so there is no conversion cost and the headers are the
recorded ones (a ``--loop`` repeats the same stamps).

One of the modules that use rclpy (with node.py, live_bag.py and client.py); it imports it inside
``main`` so the package (and this module) still imports where ROS is not installed.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from task_outcome_ros import bag_io as B
from task_outcome_ros.cli_args import positive_float, positive_int

NODE_NAME = "outcome_replay"
# Seconds to stay up after the last image when nothing acknowledges it (a best-effort QoS such
# as sensor_data): a sample still unread when its writer goes away is lost, so a subscriber
# on a loaded machine missed the bag's last frame in 1 of 5 demo runs without this.
BEST_EFFORT_LINGER_S = 1.0


def build_parser(qos_choices: tuple[str, ...]) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=NODE_NAME, description="Publish a bag's depth/image_raw and depth/camera_info "
        "over DDS with the recorded timing (for outcome_node). ROS arguments go after "
        "--ros-args.")
    p.add_argument("bag", type=Path, help="bag folder (mcap or sqlite3)")
    p.add_argument("--rate-factor", type=positive_float, default=1.0,
                   help="playback speed, 2 = twice as fast (default %(default)s)")
    p.add_argument("--loop", action="store_true", help="play again and again (Ctrl-C stops)")
    p.add_argument("--qos", choices=qos_choices, default="reliable",
                   help="publisher QoS; reliable (default) also serves best-effort subscribers")
    p.add_argument("--namespace", default="",
                   help="publish under this namespace, e.g. /cam1 (default: /)")
    p.add_argument("--topic", default=B.DEPTH_TOPIC, help="depth image topic (relative)")
    p.add_argument("--camera-info-topic", default=B.CAMERA_INFO_TOPIC,
                   help="camera_info topic (relative); skipped if the bag has none")
    p.add_argument("--wait", type=float, default=10.0,
                   help="seconds to wait for a subscriber before starting; 0 = do not wait "
                        "(default %(default)s)")
    p.add_argument("--delay", type=float, default=0.5,
                   help="seconds between the subscriber appearing and the first message, so "
                        "its side of discovery completes (default %(default)s)")
    p.add_argument("--limit", type=positive_int, default=None,
                   help="at most N images per pass")
    return p


def _msg_type(msgtype: str) -> type:
    """'sensor_msgs/msg/Image' -> the rclpy message class."""
    import importlib

    package, _, name = msgtype.rpartition("/")
    return getattr(importlib.import_module(package.replace("/", ".")), name)


class Replayer:
    """Publishers for the bag's image (and camera_info) connections on ``node``."""

    def __init__(self, node: Any, reader: Any, args: argparse.Namespace, qos: Any) -> None:
        self.node, self.reader, self.args = node, reader, args
        self.image_conn = B.require_connection(reader, args.topic, args.namespace, B.IMAGE,
                                               args.bag)
        self.info_conn = B.bag_connection(reader, args.camera_info_topic, args.namespace,
                                          B.CAMERA_INFO)
        self.image_pub = node.create_publisher(_msg_type(B.IMAGE), args.topic, qos)
        self.pubs = {self.image_conn.id: self.image_pub}
        if self.info_conn is not None:
            self.pubs[self.info_conn.id] = node.create_publisher(
                _msg_type(B.CAMERA_INFO), args.camera_info_topic, qos)
        self.published = dict.fromkeys(self.pubs, 0)
        self.late = 0

    def wait_for_subscriber(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while self.image_pub.get_subscription_count() < 1:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def loop_period_ns(self) -> int:
        """Gap between the last message of one pass and the first of the next (--loop)."""
        stamps = [t for c, t, _ in self.reader.messages(connections=[self.image_conn])]
        gaps = [b - a for a, b in zip(stamps, stamps[1:]) if b > a]
        return int(statistics.median(gaps)) if gaps else 1_000_000_000

    def play_once(self, start_wall: float, offset_ns: int, limit: int | None) -> tuple[int, int]:
        """One pass; returns (first, last) log time. Message at log time t goes out at
        start_wall + (t - first + offset_ns) / rate_factor (or at once when behind)."""
        first = last = None
        conns = list(filter(None, (self.image_conn, self.info_conn)))
        images = 0
        for conn, log_time, raw in self.reader.messages(connections=conns):
            if limit is not None and images >= limit:
                break
            first = log_time if first is None else first
            last = log_time
            due = start_wall + (log_time - first + offset_ns) * 1e-9 / self.args.rate_factor
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -0.05:
                self.late += 1
            self.pubs[conn.id].publish(bytes(raw))
            self.published[conn.id] += 1
            images += conn.id == self.image_conn.id
        return (first or 0), (last or 0)

    def n_images(self) -> int:
        return self.published[self.image_conn.id]

    def n_infos(self) -> int:
        return 0 if self.info_conn is None else self.published[self.info_conn.id]


def main(argv: list[str] | None = None) -> int:
    """Console script ``outcome_replay``; returns the process exit code."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import remove_ros_args

    from task_outcome_ros.node import QOS_CHOICES, interrupt_on_signals, subscription_qos

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(QOS_CHOICES).parse_args(remove_ros_args([NODE_NAME, *argv])[1:])
    try:
        B.resolve_topic(args.topic, args.namespace)
        B.resolve_topic(args.camera_info_topic, args.namespace)
        reader = B.open_reader(args.bag)
    except B.BagToolError as exc:
        print(f"{NODE_NAME}: error: {exc}", file=sys.stderr)
        return 2
    try:
        # Python's own SIGINT handling: Ctrl-C raises KeyboardInterrupt between two messages
        # (rclpy's handler would invalidate the context under a publish in progress).
        rclpy.init(args=[NODE_NAME, *argv], signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # malformed --ros-args
        print(f"{NODE_NAME}: error: cannot start: {exc}", file=sys.stderr)
        reader.close()
        return 2
    interrupt_on_signals()
    node = rclpy.create_node(NODE_NAME, namespace=args.namespace or None)
    log = node.get_logger()
    code = 0
    replayer = None
    t0 = time.monotonic()
    try:
        replayer = Replayer(node, reader, args, subscription_qos(args.qos))
        topic = replayer.image_pub.topic_name
        if args.wait > 0:
            if replayer.wait_for_subscriber(args.wait):
                time.sleep(max(0.0, args.delay))
            else:
                log.warning(f"no subscriber on {topic} after {args.wait:g} s; playing anyway")
        log.info(f"playing {args.bag} ({replayer.image_conn.topic} -> {topic}) at "
                 f"{args.rate_factor:g}x{' in a loop' if args.loop else ''}")
        t0 = time.monotonic()
        start, offset, period = t0, 0, None
        while True:
            first, last = replayer.play_once(start, offset, args.limit)
            if not args.loop or replayer.n_images() == 0:
                break
            period = replayer.loop_period_ns() if period is None else period
            offset += last - first + period
    except B.BagToolError as exc:
        print(f"{NODE_NAME}: error: {exc}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        pass  # Ctrl-C is how a --loop ends
    finally:
        if replayer is not None:
            seconds = time.monotonic() - t0
            # Reliable subscribers should have the last image before the process exits.
            # (Not camera_info: small samples are acknowledged only at the writer's next
            # periodic heartbeat, seconds later, although they arrived.)
            try:
                acked = replayer.image_pub.wait_for_all_acked(Duration(seconds=3))
                best_effort = (replayer.image_pub.qos_profile.reliability
                               == ReliabilityPolicy.BEST_EFFORT)
                if best_effort and replayer.n_images():
                    time.sleep(BEST_EFFORT_LINGER_S)
            except Exception:  # context already shut down (Ctrl-C)
                acked = False
            print(f"{NODE_NAME}: published {replayer.n_images()} images and "
                  f"{replayer.n_infos()} camera_info on {replayer.image_pub.topic_name} in "
                  f"{seconds:.1f} s ({replayer.late} late"
                  f"{'' if acked else '; last images not acknowledged'})", flush=True)
        reader.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
