"""``outcome/check`` round trip with frames streaming at 30 Hz, and its freshness guarantee.

outcome_node runs as its own process (the shipped model, shared-memory Fast DDS profile); this
process streams 640 x 480 ``32FC1`` depth frames with camera_info at 30 Hz, stamped with the
current time, and in between frames stamped one second in the past (a lagging camera or a
stale bag). It sends ``--trials`` requests one after another and measures, per request, the
time from the call to the reply, and whether the reply's frame was stamped after the call
was sent (it must be, in every trial: the node answers from the first frame stamped after the
request's arrival, which is later still).

    python bench/check.py [--trials 100]

Writes the ``check`` section of bench/results.json.
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import threading
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parents[0]))
from common import percentiles, record  # noqa: E402

from task_outcome_ros.topics import DEPTH_TOPIC, STATUS_TOPIC  # noqa: E402

FRAME_HZ = 30.0


def frames(n: int = 20) -> list[tuple[np.ndarray, object]]:
    """Depth frames of the default run if there is one, else a rendered-like synthetic one."""
    from task_outcome_ros.camera import Intrinsics

    runs = [BENCH.parent / "runs" / name for name in ("default", "bench_dataset")]
    run = next((r for r in runs if (r / "manifest.json").is_file()), None)
    if run is not None:
        from training.dataset import load_manifest
        from training.render import read_pair, reported_camera

        images = load_manifest(run)["images"][:n]
        return [(read_pair(run, im["episode"])[0], Intrinsics.from_record(reported_camera(im)))
                for im in images]
    depth = np.full((480, 640), 2.3, np.float32)
    depth[150:330, 200:440] = 2.0
    return [(depth, Intrinsics(640, 480, 557.5, 557.5, 319.5, 239.5))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--quick", action="store_true", help="10 trials (a smoke run)")
    args = parser.parse_args()
    trials = 10 if args.quick else args.trials

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    sys.path.insert(0, str(BENCH.parent / "test"))
    import node_helpers as nh

    from task_outcome_ros.client import OutcomeCheckClient, parse

    domain = random.randint(1, 200)
    env = nh.ros_env(domain)
    os.environ.update({k: v for k, v in env.items()
                       if k.startswith(("ROS_", "FASTRTPS_", "FASTDDS_"))})
    log = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_check_node_{domain}.log"
    proc = nh.NodeProcess(["-p", "threads:=1"], domain, log)
    rclpy.init()
    node = rclpy.create_node("bench_check")
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    image_pub = node.create_publisher(Image, DEPTH_TOPIC, qos)
    info_pub = node.create_publisher(CameraInfo, "depth/camera_info", qos)
    checker = OutcomeCheckClient(node)
    inference_ms: list[float] = []  # the node's own time per frame, from its status

    def on_status(msg) -> None:
        values = {kv.key: kv.value for kv in msg.status[0].values}
        if "inference_ms" in values:
            inference_ms.append(float(values["inference_ms"]))

    from diagnostic_msgs.msg import DiagnosticArray

    node.create_subscription(DiagnosticArray, STATUS_TOPIC, on_status, qos)
    msgs = [(nh.depth_msg(d), nh.camera_info(k.width, k.height, k.fx, k.cx, k.cy))
            for d, k in frames()]
    tick = [0]
    interleave = [False]  # scenario switch, read by the publishing timer

    def publish() -> None:
        """Fresh frames at 30 Hz; in the stress scenario an old one between each two."""
        old = interleave[0] and tick[0] % 2 == 1
        if not interleave[0] and tick[0] % 2 == 1:
            tick[0] += 1
            return  # the timer runs at 60 Hz; plain streaming uses every other tick
        image, info = msgs[tick[0] // 2 % len(msgs)]
        ns = node.get_clock().now().nanoseconds - (1_000_000_000 if old else 0)
        for msg in (info, image):
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        info_pub.publish(info)
        image_pub.publish(image)
        tick[0] += 1

    node.create_timer(1.0 / (2 * FRAME_HZ), publish)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    scenarios = {}
    try:
        if not checker.wait_for_service(60.0):
            raise SystemExit(f"outcome/check not available; node log: {log}")
        for name, with_old in (("streaming", False), ("old_frames_interleaved", True)):
            interleave[0] = with_old
            inference_ms.clear()
            time.sleep(2.0)  # discovery settles, the node is streaming
            scenarios[name] = _trials(node, checker, parse, trials, log)
            scenarios[name]["node_inference_ms"] = percentiles(inference_ms)
    finally:
        executor.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        rclpy.try_shutdown()
        proc.stop()
    record("check", {
        "trials_per_scenario": trials, "frame_hz": FRAME_HZ,
        "frame_period_ms": round(1e3 / FRAME_HZ, 2), "scenarios": scenarios,
        "note": "old_frames_interleaved: between each two fresh frames one stamped 1 s in the "
                "past; round trip = call to reply in this process",
        "model": "shipped default model, threads 1, shared-memory Fast DDS profile",
        "frames": f"{len(msgs)} 640 x 480 32FC1 frames with camera_info",
    }, command="python bench/check.py " + " ".join(sys.argv[1:]))


def _trials(node, checker, parse, trials: int, log: Path) -> dict:
    """``trials`` requests one after another (after 3 untimed): round trip and freshness."""
    round_trip, fresh, timeouts = [], 0, 0
    for k in range(trials + 3):
        sent_ns = node.get_clock().now().nanoseconds
        replied = threading.Event()
        t0 = time.perf_counter()
        future = checker.call_async()
        future.add_done_callback(lambda _, done=replied: done.set())
        if not replied.wait(30.0):
            raise SystemExit(f"outcome/check did not answer; node log: {log}")
        elapsed = (time.perf_counter() - t0) * 1e3
        result = parse(future.result().success, future.result().message)
        if k < 3:
            continue  # warm-up
        round_trip.append(elapsed)
        timeouts += result.stamp_ns is None
        fresh += int(result.stamp_ns is not None and result.stamp_ns > sent_ns)
    return {"round_trip_ms": percentiles(round_trip), "timeouts": timeouts,
            "replies_from_frames_stamped_after_the_request": fresh, "trials": trials}


if __name__ == "__main__":
    main()
