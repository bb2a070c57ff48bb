"""``make demo``: the whole story on a small simulated bag, in a few minutes on 2 CPU cores.

1. simulate a few episodes (new seed) and render them with ground truth (training pipeline);
2. export them as a rosbag2 bag (depth/image_raw 32FC1 + depth/camera_info, 5 Hz);
3. start ``outcome_node`` as its own process (shipped checkpoint, default parameters);
4. replay the bag to it over DDS with ``outcome_replay``, and record what it publishes
   (outcome/labels, outcome/status, outcome/overlay) into a bag of its own;
5. score the node's answers against the ground truth with the paper's image-level metric,
   write a contact sheet of overlays and ``summary.json``.

This is a ROS edge tool (it subscribes over DDS), like ``node.py`` and ``replay.py``; the
inference core never imports rclpy.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from task_outcome_ros import bag_tools as B
from task_outcome_ros import outcome_report as R
from task_outcome_ros.labels import OUTCOME_NAMES

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


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


def make_data(out: Path, episodes: int, seed: int) -> Path:
    """Steps 1-2: a small dataset run and its bag (reused if already there)."""
    from training.export_bag import export_bag

    data = out / "data"
    if not (data / "manifest.json").exists():
        cmd = [sys.executable, "-m", "training", "dataset", "--out", str(data), "--episodes",
               str(episodes), "--seed", str(seed), "--chunk-size", "10"]
        subprocess.run(cmd, check=True)
    bag = out / "input_bag"
    export_bag(data, bag, split="all", rate_hz=5.0, encoding="32FC1", overwrite=True)
    return bag


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
            "outcome/labels": {}, "outcome/status": {}, "outcome/overlay": {}}
        for topic, msgtype in (("outcome/labels", Image), ("outcome/status", DiagnosticArray),
                               ("outcome/overlay", Image)):
            self.node.create_subscription(msgtype, topic, self._keeper(topic), qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _keeper(self, topic: str):
        def keep(msg) -> None:
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
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

    types = {"outcome/labels": "sensor_msgs/msg/Image",
             "outcome/overlay": "sensor_msgs/msg/Image",
             "outcome/status": "diagnostic_msgs/msg/DiagnosticArray"}
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
    """Outcomes present according to a DiagnosticArray from the node; None for ERROR."""
    status = msg.status[0]
    if status.level == R.ERROR:
        return None
    values = {kv.key: kv.value for kv in status.values}
    return {name: values.get(f"{name}.present", "false") == "true" for name in OUTCOME_NAMES}


def contact_sheet(path: Path, received: dict, ground_truth: dict, scores: dict,
                  n: int = 12) -> None:
    """Overlays as the node published them, titled with its answer and the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = ground_truth["frames"]
    wrong = {m["stamp_ns"] for m in scores["mistakes"]}
    order = [f for f in frames if f["stamp_ns"] in wrong] + \
        [f for f in frames if f["stamp_ns"] not in wrong]
    order = [f for f in order if f["stamp_ns"] in received["outcome/overlay"]][:n]
    cols = 4
    rows = max(1, (len(order) + cols - 1) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), dpi=80,
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, frame in zip(axes.ravel(), order):
        msg = received["outcome/overlay"][frame["stamp_ns"]][1]
        rgb = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
        ax.imshow(rgb)
        status = received["outcome/status"].get(frame["stamp_ns"])
        said = status[1].status[0].message if status else "(no status)"
        truth = ",".join(k for k in OUTCOME_NAMES if frame["present"][k]) or "none"
        ok = frame["stamp_ns"] not in wrong
        ax.set_title(f"ep {frame['episode']}: node says {said}\ntruth {truth}", fontsize=8,
                     color="black" if ok else "red")
    fig.suptitle(f"outcome_node on a replayed bag: {scores['image_all_correct']:.1%} of "
                 f"{scores['n_images']} images all-correct (mistakes first, in red)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_demo(out: Path, episodes: int = 40, seed: int = 2026, timeout_s: float = 60.0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print(f"[demo] 1-2/5 simulating {episodes} episodes (seed {seed}) and exporting a bag")
    bag = make_data(out, episodes, seed)
    ground_truth = B.load_ground_truth(bag)
    n_frames = len(ground_truth["frames"])
    env = ros_env(random.randint(1, 200))
    print("[demo] 3/5 starting outcome_node (shipped model)")
    node_log = open(out / "outcome_node.log", "w")
    node = subprocess.Popen(_script("outcome_node"), env=env, stdout=node_log,
                            stderr=subprocess.STDOUT)
    recorder = Recorder(env)
    try:
        deadline = time.monotonic() + timeout_s
        while recorder.publishers_seen("outcome/labels") == 0:
            if node.poll() is not None:
                raise RuntimeError(f"outcome_node exited with {node.returncode}; see "
                                   f"{out / 'outcome_node.log'}")
            if time.monotonic() > deadline:
                raise RuntimeError("outcome_node did not come up within the timeout")
            time.sleep(0.1)
        print(f"[demo] 4/5 replaying {n_frames} frames at 5 Hz over DDS with outcome_replay")
        subprocess.run([*_script("outcome_replay"), str(bag), "--qos", "sensor_data",
                        "--wait", str(timeout_s)], env=env, check=True)
        deadline = time.monotonic() + 10.0
        while len(recorder.received["outcome/status"]) < n_frames \
                and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        recorder.close()
        node.terminate()
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node.kill()
        node_log.close()
    received = recorder.received
    predicted = {stamp: status_present(msg) for stamp, (_, msg)
                 in received["outcome/status"].items()}
    scores = B.score(ground_truth, predicted)
    write_output_bag(out / "output_bag", received)
    contact_sheet(out / "contact_sheet.png", received, ground_truth, scores)
    values = [{kv.key: kv.value for kv in msg.status[0].values}
              for _, msg in received["outcome/status"].values()]
    latency = [float(v["latency_ms"]) for v in values if "latency_ms" in v]
    summary = {
        "frames_sent": n_frames,
        "frames_answered": len(received["outcome/status"]),
        "image_all_correct": scores["image_all_correct"],
        "presence_recall": scores["presence_recall"],
        "presence_precision": scores["presence_precision"],
        "node_latency_ms_p50": float(np.median(latency)) if latency else None,
        "wall_s": round(time.monotonic() - started, 1),
        "outputs": {"contact_sheet": str(out / "contact_sheet.png"),
                    "output_bag": str(out / "output_bag"), "input_bag": str(bag)},
    }
    (out / "summary.json").write_text(json.dumps({**summary, "scores": scores}, indent=1))
    p50 = summary["node_latency_ms_p50"]
    print(f"[demo] 5/5 {summary['frames_answered']}/{n_frames} frames answered, "
          f"{summary['image_all_correct']:.1%} all-correct, node latency p50 "
          f"{'n/a' if p50 is None else f'{p50:.1f}'} ms; contact sheet: "
          f"{out / 'contact_sheet.png'}")
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/demo"))
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args(argv)
    try:
        run_demo(args.out, args.episodes, args.seed)
    except (RuntimeError, subprocess.CalledProcessError, B.BagToolError) as exc:
        print(f"[demo] failed: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
