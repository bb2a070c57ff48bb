"""Play a bag to a live ``outcome_node`` over DDS, record what it publishes, and score it.

What a camera plus a manifest of ground truth would give: the node runs as its own process
with the shipped model (or ``--ros-args`` of the caller's choosing), ``outcome_replay`` plays
the bag in real time, and an in-process rclpy subscriber keeps every labels, status and
overlay message by input stamp. With the bag's ``ground_truth.json`` the answers get the
paper's image-level scores. ``python -m training demo`` is this on a freshly simulated bag.

A DDS tool like node.py and replay.py: it imports rclpy only when it runs.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from task_outcome_ros import bag_io as B
from task_outcome_ros import outcome_report as R
from task_outcome_ros.ground_truth import load_ground_truth, score
from task_outcome_ros.topics import LABELS_TOPIC, OVERLAY_TOPIC, STATUS_TOPIC

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
OUTPUT_TOPICS = {LABELS_TOPIC: B.IMAGE, STATUS_TOPIC: B.DIAGNOSTIC_ARRAY,
                 OVERLAY_TOPIC: B.IMAGE}


def _fastdds_profile() -> Path | None:
    """The SHM profile: in the source tree, or in share/ of a colcon install."""
    candidates = [CONFIG_DIR / "fastdds_shm.xml"]
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("task_outcome_ros")) / "config"
                          / "fastdds_shm.xml")
    except Exception:  # not a ROS install: the source-tree copy is the one
        pass
    return next((p for p in candidates if p.is_file()), None)


def ros_env(domain_id: int) -> dict[str, str]:
    """Environment for every DDS process of the demo: own domain, localhost, SHM profile."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    profile = _fastdds_profile()
    if profile is not None:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
        env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)
    return env


def _script(name: str) -> list[str]:
    """A console script of this package: beside the interpreter, else via ``python -m``."""
    exe = Path(sys.executable).parent / name
    if exe.exists():
        return [str(exe)]
    module = {"outcome_node": "task_outcome_ros.node",
              "outcome_replay": "task_outcome_ros.replay"}[name]
    return [sys.executable, "-m", module]


class Recorder:
    """Subscribes to the node's outputs and keeps them by input stamp (rclpy, in-process)."""

    def __init__(self, env: dict[str, str]):
        os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                               "FASTRTPS_DEFAULT_PROFILES_FILE",
                                               "FASTDDS_DEFAULT_PROFILES_FILE") if k in env})
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("outcome_demo_recorder", context=self.context)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.received: dict[str, dict[int, tuple[float, object]]] = {
            topic: {} for topic in OUTPUT_TOPICS}
        for topic, msgtype in ((LABELS_TOPIC, Image), (STATUS_TOPIC, DiagnosticArray),
                               (OVERLAY_TOPIC, Image)):
            self.node.create_subscription(msgtype, topic, self._keeper(topic), qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _keeper(self, topic: str):
        def keep(msg) -> None:
            stamp = B.stamp_to_ns(msg.header.stamp)
            self.received[topic][stamp] = (time.monotonic(), msg)
        return keep

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def publishers_seen(self, topic: str) -> int:
        return self.node.count_publishers(topic)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def write_output_bag(path: Path, received: dict, storage: str = "mcap") -> None:
    """The node's answers as a bag (raw CDR from rclpy, log time = input stamp)."""
    from rclpy.serialization import serialize_message

    types = OUTPUT_TOPICS
    if path.exists():
        shutil.rmtree(path)
    writer = B.open_writer(path, storage=storage)
    try:
        conns = {t: writer.add_connection(t, types[t], typestore=B.typestore()) for t in types}
        for topic, by_stamp in received.items():
            for stamp, (_, msg) in sorted(by_stamp.items()):
                writer.write(conns[topic], stamp, serialize_message(msg))
    finally:
        writer.close()


def status_present(msg) -> dict[str, bool] | None:
    """Outcomes present according to a DiagnosticArray from the node; None for ERROR. The
    outcomes are the ones the status names (its model's label table), whatever the task."""
    status = msg.status[0]
    # rclpy gives the byte field as bytes (b'\x02'), rosbags as an int.
    level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
    if level == R.ERROR:
        return None
    values = {kv.key: kv.value for kv in status.values}
    return {name: values.get(f"{name}.present", "false") == "true"
            for name in R.status_outcomes(values).names}


@dataclass
class LiveRun:
    """What the node said about a bag: its messages by input stamp, and their scores."""

    received: dict[str, dict[int, tuple[float, Any]]]
    ground_truth: dict
    scores: dict
    frames_sent: int

    def latencies_ms(self) -> list[float]:
        values = [{kv.key: kv.value for kv in msg.status[0].values}
                  for _, msg in self.received[STATUS_TOPIC].values()]
        return [float(v["latency_ms"]) for v in values if "latency_ms" in v]


def run_live(bag: Path, out: Path, *, rate_hz_note: str = "", timeout_s: float = 60.0,
             node_args: list[str] | None = None, log=print,
             then: Callable[[dict[str, str]], None] | None = None) -> LiveRun:
    """Start outcome_node, replay ``bag`` to it, record and score; the node log goes to
    ``out/outcome_node.log`` and the answers to ``out/output_bag``. ``then(env)`` runs while
    the node is still up (with the DDS environment of the run), e.g. a client of it."""
    ground_truth = load_ground_truth(bag)
    if ground_truth is None:
        raise B.BagToolError(f"{bag} has no ground_truth.json to score against")
    n_frames = len(ground_truth["frames"])
    env = ros_env(random.randint(1, 200))
    out.mkdir(parents=True, exist_ok=True)
    log(f"starting outcome_node{' ' + ' '.join(node_args) if node_args else ''}")
    command = _script("outcome_node") + (["--ros-args", *node_args] if node_args else [])
    with open(out / "outcome_node.log", "w") as node_log:
        node = subprocess.Popen(command, env=env, stdout=node_log, stderr=subprocess.STDOUT)
        recorder = None
        try:
            recorder = Recorder(env)
            _wait_for_node(recorder, node, out, timeout_s)
            log(f"replaying {n_frames} frames{rate_hz_note} over DDS with outcome_replay")
            subprocess.run([*_script("outcome_replay"), str(bag), "--qos", "sensor_data",
                            "--wait", str(timeout_s)], env=env, check=True)
            deadline = time.monotonic() + 10.0
            while len(recorder.received[STATUS_TOPIC]) < n_frames \
                    and time.monotonic() < deadline:
                time.sleep(0.1)
            received = {topic: dict(by_stamp) for topic, by_stamp in recorder.received.items()}
            if then is not None:
                then(env)
        finally:
            if recorder is not None:
                recorder.close()
            node.terminate()
            try:
                node.wait(timeout=10)
            except subprocess.TimeoutExpired:
                node.kill()
    predicted = {stamp: status_present(msg) for stamp, (_, msg)
                 in received[STATUS_TOPIC].items()}
    write_output_bag(out / "output_bag", received)
    return LiveRun(received, ground_truth, score(ground_truth, predicted), n_frames)


def _wait_for_node(recorder: Recorder, node: subprocess.Popen, out: Path,
                   timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while recorder.publishers_seen(LABELS_TOPIC) == 0:
        if node.poll() is not None:
            raise RuntimeError(f"outcome_node exited with {node.returncode}; see "
                               f"{out / 'outcome_node.log'}")
        if time.monotonic() > deadline:
            raise RuntimeError("outcome_node did not come up within the timeout")
        time.sleep(0.1)
