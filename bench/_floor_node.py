"""The latency floor of bench/node.py: a node that does nothing but answer.

It subscribes depth/image_raw with outcome_node's input QoS and, in the subscription
callback, publishes at once what outcome_node publishes first: a mono8 image of the input's
size and header on outcome/labels (zeros: no decoding, no inference) and a one-status
DiagnosticArray on outcome/status. What it costs is DDS plus rclpy for the same messages, so
outcome_node's latency over this node's is what our own work adds.

Not meant to be run by hand; bench/node.py starts it in the ``floor`` namespace beside the
real node, with the same environment (DDS profile, domain).
"""

from __future__ import annotations

import argparse
import array
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Image

from task_outcome_ros.node import (
    OUTPUT_QOS,
    QOS_CHOICES,
    STATUS_NAME,
    interrupt_on_signals,
    subscription_qos,
)
from task_outcome_ros.topics import DEPTH_TOPIC, LABELS_TOPIC, STATUS_TOPIC


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--qos", choices=QOS_CHOICES, default=QOS_CHOICES[0])
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=[sys.argv[0], *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    interrupt_on_signals()
    node = rclpy.create_node("outcome_floor_node")
    labels = node.create_publisher(Image, LABELS_TOPIC, OUTPUT_QOS)
    status = node.create_publisher(DiagnosticArray, STATUS_TOPIC, OUTPUT_QOS)
    zeros: dict[tuple[int, int], array.array] = {}

    def on_image(msg: Image) -> None:
        t0 = time.monotonic()
        size = (int(msg.height), int(msg.width))
        if size not in zeros:
            zeros[size] = array.array("B", bytes(size[0] * size[1]))
        labels.publish(Image(header=msg.header, height=size[0], width=size[1],
                             encoding="mono8", is_bigendian=0, step=size[1],
                             data=zeros[size]))
        latency = KeyValue(key="latency_ms", value=f"{(time.monotonic() - t0) * 1e3:.2f}")
        status.publish(DiagnosticArray(header=msg.header, status=[DiagnosticStatus(
            level=DiagnosticStatus.OK, name=STATUS_NAME, message="", values=[latency])]))

    node.create_subscription(Image, DEPTH_TOPIC, on_image, subscription_qos(args.qos))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.get_logger().info("ready: floor node")
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
