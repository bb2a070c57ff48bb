"""Helpers for tests that run the real outcome_node as a subprocess and talk to it over DDS.

The test side is an rclpy node in its own Context; nothing here sleeps blindly: every wait
polls a condition (discovery counts, a reply with a given header) against a deadline.
"""

from __future__ import annotations

import array
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from model_helpers import make_checkpoint, make_depth_band_checkpoint  # noqa: F401 (re-export)
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

REPO = Path(__file__).resolve().parents[1]
SHM_PROFILE = REPO / "config" / "fastdds_shm.xml"
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE)


def node_command() -> list[str]:
    """The installed console script if there is one, else the same entry point via -m."""
    return script_command("outcome_node", "task_outcome_ros.node")


def script_command(name: str, module: str) -> list[str]:
    """Console script ``name`` (on PATH or beside this Python), else ``python -m module``."""
    script = shutil.which(name) or shutil.which(name, path=str(Path(sys.prefix) / "bin"))
    return [script] if script else [sys.executable, "-m", module]


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for an isolated, localhost-only ROS graph using the SHM profile."""
    env = dict(os.environ)
    env.update({
        "ROS_DOMAIN_ID": str(domain_id if domain_id is not None else random.randint(1, 200)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(SHM_PROFILE),
        "FASTDDS_DEFAULT_PROFILES_FILE": str(SHM_PROFILE),
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "OMP_NUM_THREADS": "1",
    })
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return env


def run_node_expect_exit(args: list[str], timeout: float = 30.0,
                         ) -> subprocess.CompletedProcess:
    """Run the node with --ros-args ``args``; it must exit by itself within ``timeout``."""
    return subprocess.run(node_command() + ["--ros-args", *args], env=ros_env(),
                          capture_output=True, text=True, timeout=timeout)


class NodeProcess:
    """outcome_node in a subprocess; stderr goes to a file so a chatty node never blocks."""

    def __init__(self, args: list[str], domain_id: int, log_path: Path,
                 command: list[str] | None = None) -> None:
        self.log_path = log_path
        self._log = open(log_path, "w")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen((command or node_command()) + ["--ros-args", *args],
                                     env=ros_env(domain_id), stdout=self._log,
                                     stderr=subprocess.STDOUT)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int:
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self._log.close()
        return self.proc.returncode


def depth_msg(depth_m: np.ndarray, encoding: str = "32FC1", *, stamp: tuple[int, int] = (0, 0),
              frame_id: str = "depth_optical", bigendian: bool = False, pad: int = 0) -> Image:
    """float metres -> Image in the given encoding/endianness, rows padded by ``pad`` bytes."""
    if encoding == "32FC1":
        arr = np.asarray(depth_m, np.float32)
    elif encoding == "16UC1":
        with np.errstate(invalid="ignore"):
            mm = np.where(np.isfinite(depth_m) & (depth_m > 0), np.rint(depth_m * 1000), 0)
        arr = np.clip(mm, 0, 65535).astype(np.uint16)
    else:
        raise ValueError(encoding)
    arr = arr.astype(arr.dtype.newbyteorder(">" if bigendian else "<"))
    h, w = arr.shape
    rows = arr.view(np.uint8).reshape(h, w * arr.itemsize)
    if pad:
        rows = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return raw_image(encoding, h, w, rows.shape[1], rows.tobytes(), stamp=stamp,
                     frame_id=frame_id, bigendian=bigendian)


def raw_image(encoding: str, height: int, width: int, step: int, data: bytes, *,
              stamp: tuple[int, int] = (0, 0), frame_id: str = "depth_optical",
              bigendian: bool = False) -> Image:
    msg = Image(encoding=encoding, height=height, width=width, step=step,
                is_bigendian=int(bigendian), data=array.array("B", data))
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame_id
    return msg


def camera_info(width: int, height: int, fx: float, cx: float, cy: float,
                frame_id: str = "depth_optical") -> CameraInfo:
    msg = CameraInfo(width=width, height=height, distortion_model="plumb_bob")
    msg.header.frame_id = frame_id
    msg.k = [fx, 0.0, cx, 0.0, fx, cy, 0.0, 0.0, 1.0]
    msg.p = [fx, 0.0, cx, 0.0, 0.0, fx, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    msg.d = [0.0] * 5
    return msg


def header_key(header) -> tuple[int, int, str]:
    return header.stamp.sec, header.stamp.nanosec, header.frame_id


class Reply:
    """What the node published for one input header."""

    def __init__(self) -> None:
        self.labels: Image | None = None
        self.status: DiagnosticArray | None = None
        self.overlay: Image | None = None
        self.markers: MarkerArray | None = None
        self.status_arrived: float | None = None  # time.monotonic() when the status came


class OutcomeClient:
    """A test-side rclpy node (own Context) that feeds outcome_node and collects its replies."""

    def __init__(self, domain_id: int, namespace: str = "") -> None:
        # Join the node's graph; the variables are read while the participant is created,
        # then restored so other tests in this process see their own environment.
        wanted = {k: v for k, v in ros_env(domain_id).items()
                  if k.startswith(("ROS_", "FASTRTPS_", "FASTDDS_"))}
        saved = {k: os.environ.get(k) for k in wanted}
        os.environ.update(wanted)
        try:
            self.context = Context()
            rclpy.init(context=self.context, domain_id=domain_id)
            self.node = Node("outcome_test_client", namespace=namespace, context=self.context)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.image_pub = self.node.create_publisher(Image, "depth/image_raw", RELIABLE)
        self.info_pub = self.node.create_publisher(CameraInfo, "depth/camera_info", RELIABLE)
        self.replies: dict[tuple[int, int, str], Reply] = {}
        self.subs = [
            self.node.create_subscription(Image, "outcome/labels",
                                          self._store("labels"), RELIABLE),
            self.node.create_subscription(DiagnosticArray, "outcome/status",
                                          self._store("status"), RELIABLE),
            self.node.create_subscription(Image, "outcome/overlay",
                                          self._store("overlay"), RELIABLE),
            self.node.create_subscription(MarkerArray, "outcome/markers",
                                          self._store("markers"), RELIABLE),
        ]
        self._stamp = 1000

    def _store(self, field: str) -> Callable:
        def callback(msg) -> None:
            header = msg.markers[0].header if field == "markers" else msg.header
            reply = self.replies.setdefault(header_key(header), Reply())
            if getattr(reply, field) is None:  # keep the first answer to a header
                setattr(reply, field, msg)
                if field == "status":
                    reply.status_arrived = time.monotonic()
        return callback

    def next_stamp(self) -> tuple[int, int]:
        """A fresh, unique stamp so every request's reply can be told apart."""
        self._stamp += 1
        return self._stamp, 123_456_789

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return condition()

    def wait_for_node(self, proc: NodeProcess, timeout: float = 45.0) -> None:
        """Discovery in both directions, checked by counts (or fail with the node's log)."""
        def matched() -> bool:
            if not proc.alive():
                raise RuntimeError(f"outcome_node exited ({proc.proc.returncode}):\n{proc.log()}")
            return (self.image_pub.get_subscription_count() >= 1
                    and self.info_pub.get_subscription_count() >= 1
                    and all(s.get_publisher_count() >= 1 for s in self.subs))
        if not self.spin_until(matched, timeout):
            raise TimeoutError(f"outcome_node not discovered within {timeout} s:\n{proc.log()}")

    def request(self, msg: Image, fields: tuple[str, ...] = ("status",), timeout: float = 20.0,
                resend_every: float = 3.0) -> Reply:
        """Publish ``msg`` and wait for the replies to its header (resend if none came)."""
        key = header_key(msg.header)

        def done() -> bool:
            reply = self.replies.get(key)
            return reply is not None and all(getattr(reply, f) is not None for f in fields)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.image_pub.publish(msg)
            if self.spin_until(done, min(resend_every, deadline - time.monotonic())):
                return self.replies[key]
        raise TimeoutError(f"no {fields} for header {key} within {timeout} s")

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def status_values(array_msg: DiagnosticArray) -> dict[str, str]:
    (status,) = array_msg.status
    return {kv.key: kv.value for kv in status.values}
