"""Client side of bench/node.py: one process per scenario (Fast DDS reads its XML profile once
per process, so the SHM / no-SHM runs need fresh processes). Feeds depth/image_raw, listens to
outcome/labels and outcome/status, samples the node's RSS and CPU, writes a JSON summary.

Not meant to be run by hand; bench/node.py starts it with the scenario's environment.
"""

from __future__ import annotations

import argparse
import array
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import percentiles  # noqa: E402
from inference import load_frames  # noqa: E402

from task_outcome_ros.topics import CAMERA_INFO_TOPIC, DEPTH_TOPIC, LABELS_TOPIC, STATUS_TOPIC  # noqa: E402

LATENCY_SEC, THROUGHPUT_SEC, PRIME_SEC = 1, 2, 3  # header.stamp.sec tags the phase
PRIME_TRIES, GIVE_UP_AFTER, LATENCY_TIMEOUT_S = 20, 30, 0.5  # p95 is ~20-50 ms


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS / VmHWM (kB) of ``pid``."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(rest.split()[0])
    return out


def proc_cpu_s(pid: int) -> float:
    """user + system CPU seconds of ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


FLOOR_NAMESPACE = "floor"
STATIC_NOISE_M = 0.002  # axial noise sd of a static camera's successive frames


def static_camera(depth: np.ndarray, n: int) -> list[np.ndarray]:
    """``n`` frames of one static camera: ``depth`` with fresh axial noise each (seeded)."""
    rng = np.random.default_rng(0)
    return [(depth + rng.normal(0.0, STATIC_NOISE_M, depth.shape)).astype(np.float32)
            for _ in range(n)]


class Target:
    """One node under test: its input publishers and what came back from it."""

    def __init__(self, node, namespace: str, pub_qos, sub_qos) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import CameraInfo, Image

        prefix = f"{namespace}/" if namespace else ""
        self.pub = node.create_publisher(Image, prefix + DEPTH_TOPIC, pub_qos)
        self.info_pub = node.create_publisher(CameraInfo, prefix + CAMERA_INFO_TOPIC, pub_qos)
        self.labels_at: dict[tuple[int, int], float] = {}
        self.status_of: dict[tuple[int, int], dict[str, str]] = {}
        self.last_status: dict[str, str] = {}
        self.primed: int | None = None
        self.subs = [node.create_subscription(Image, prefix + LABELS_TOPIC, self._on_labels,
                                              sub_qos),
                     node.create_subscription(DiagnosticArray, prefix + STATUS_TOPIC,
                                              self._on_status, sub_qos)]

    def discovered(self) -> bool:
        return (self.pub.get_subscription_count() >= 1
                and all(s.get_publisher_count() >= 1 for s in self.subs))

    def _on_labels(self, msg) -> None:
        self.labels_at.setdefault((msg.header.stamp.sec, msg.header.stamp.nanosec),
                                  time.monotonic())

    def _on_status(self, msg) -> None:
        values = {kv.key: kv.value for s in msg.status for kv in s.values}
        self.status_of[msg.header.stamp.sec, msg.header.stamp.nanosec] = values
        self.last_status.clear()
        self.last_status.update(values)


def windows(published_s: np.ndarray, answered: np.ndarray, lag_ms: np.ndarray,
            window_s: float) -> list[dict]:
    """Per ``window_s`` of publishing: frames published, share answered, lag p50 / p95."""
    out = []
    which = (published_s // window_s).astype(int)
    for w in range(int(which.max()) + 1 if which.size else 0):
        lags = lag_ms[which[answered] == w]       # the answered frames published in w
        sent = int((which == w).sum())
        out.append({"start_s": round(w * window_s, 1), "published": sent,
                    "fraction_answered": round(lags.size / max(1, sent), 4),
                    "lag_p50_ms": round(float(np.percentile(lags, 50)), 2) if lags.size else None,
                    "lag_p95_ms": round(float(np.percentile(lags, 95)), 2) if lags.size else None})
    return out


def measure_latency(nodes: list, frames: int, hz: float, publish, spin_until) -> dict:
    """One frame at a time at ``hz``: publish -> labels (and status) received, per node.

    ``nodes``: (name, Target, pid). With two, every frame goes to both, one after the other,
    the order flipping each frame, so both see the same load and the same images."""
    period = 1.0 / hz
    per = {name: {"lat": [], "node_lat": [], "infer": [], "lost": 0, "answered": 0}
           for name, _, _ in nodes}
    cpu0 = {name: proc_cpu_s(pid) for name, _, pid in nodes}
    in_a_row, sent = 0, 0
    for i in range(frames):
        tick = time.monotonic()
        order = nodes if i % 2 == 0 else nodes[::-1]
        lost_now = 0
        for name, target, _ in order:
            tp = publish(LATENCY_SEC, i, target)
            key = (LATENCY_SEC, i)
            row = per[name]
            if spin_until(lambda key=key, t=target: key in t.labels_at and key in t.status_of,
                          LATENCY_TIMEOUT_S):
                row["lat"].append((target.labels_at[key] - tp) * 1e3)
                row["node_lat"].append(float(target.status_of[key]["latency_ms"]))
                row["infer"].append(float(target.status_of[key].get("inference_ms", "nan")))
                row["answered"] += 1
            else:
                row["lost"] += 1
                lost_now += 1
        sent += 1
        in_a_row = in_a_row + 1 if lost_now == len(nodes) else 0
        if in_a_row >= GIVE_UP_AFTER:
            break  # the transport loses everything: don't wait for 200
        spin_until(lambda tick=tick: time.monotonic() >= tick + period, period)
    out: dict = {"frames": sent, "rate_hz": hz,
                 "gave_up_after_consecutive_unanswered": in_a_row >= GIVE_UP_AFTER}
    for name, _, pid in nodes:
        row = per[name]
        cpu_ms = (proc_cpu_s(pid) - cpu0[name]) * 1e3
        stats = {"unanswered": row["lost"],
                 "end_to_end_ms": percentiles(row["lat"]) if row["lat"] else None,
                 "node_latency_ms": percentiles(row["node_lat"]) if row["node_lat"] else None,
                 "cpu_ms_per_frame": round(cpu_ms / max(1, row["answered"]), 2)}
        if name == "outcome_node":
            stats["node_inference_ms"] = percentiles(row["infer"]) if row["infer"] else None
            out.update(stats)  # the real node's figures stay where they always were
        else:
            out[name] = stats
    if len(nodes) == 2 and out["end_to_end_ms"] and out["floor"]["end_to_end_ms"]:
        real, base = out["end_to_end_ms"], out["floor"]["end_to_end_ms"]
        out["ratio_to_floor"] = {q: round(real[q] / base[q], 2) for q in ("p50", "p95")}
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--node-pid", type=int, required=True)
    p.add_argument("--floor-pid", type=int, default=0,
                   help="a floor node (bench/_floor_node.py) in the 'floor' namespace: "
                        "latency frames alternate between it and outcome_node")
    p.add_argument("--qos", choices=("sensor_data", "reliable"), required=True)
    p.add_argument("--latency-frames", type=int, default=0)
    p.add_argument("--latency-hz", type=float, default=10.0)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--hz", type=float, default=30.0)
    p.add_argument("--images", type=int, default=30)
    p.add_argument("--window-s", type=float, default=60.0,
                   help="throughput: lag p95 and answered share per window of this length")
    p.add_argument("--static-camera", action="store_true",
                   help="one camera: the first frame again and again, fresh noise each time")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    frames, _, cameras, frames_desc = load_frames(args.images)
    if args.static_camera:
        frames, cameras = static_camera(frames[0], args.images), [cameras[0]] * args.images
        frames_desc = (f"one camera: the first of {frames_desc}, {args.images} times with "
                       f"fresh {STATIC_NOISE_M * 1e3:g} mm noise")
    msgs, infos = [], []
    for depth, camera in zip(frames, cameras, strict=True):
        h, w = depth.shape
        msgs.append(Image(height=h, width=w, encoding="32FC1", is_bigendian=0, step=w * 4,
                          data=array.array("B", np.ascontiguousarray(depth, "<f4").tobytes())))
        msgs[-1].header.frame_id = "depth_optical"
        # Each frame's camera_info goes out just before it, as a camera driver sends them.
        infos.append(None if camera is None else CameraInfo(width=w, height=h, k=camera.k()))

    rclpy.init()
    node = rclpy.create_node("outcome_bench_client")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    pub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                         reliability=ReliabilityPolicy.BEST_EFFORT if args.qos == "sensor_data"
                         else ReliabilityPolicy.RELIABLE)
    sub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                         reliability=ReliabilityPolicy.RELIABLE)
    real = Target(node, "", pub_qos, sub_qos)
    floor = Target(node, FLOOR_NAMESPACE, pub_qos, sub_qos) if args.floor_pid else None
    targets = [t for t in (real, floor) if t is not None]
    # The throughput phase talks to the real node only: its old names stay.
    labels_at, status_of, last_status = real.labels_at, real.status_of, real.last_status

    def spin_until(cond, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            executor.spin_once(timeout_sec=min(left, 0.05))
        return True

    def publish(sec: int, index: int, target: Target = real) -> float:
        msg, info = msgs[index % len(msgs)], infos[index % len(msgs)]
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, index
        if info is not None:
            info.header = msg.header
            target.info_pub.publish(info)
        t = time.monotonic()
        target.pub.publish(msg)
        return t

    result: dict = {"qos": args.qos, "frames": frames_desc,
                    "shm_profile": os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "")}
    try:
        t0 = time.monotonic()
        if not spin_until(lambda: all(t.discovered() for t in targets), 90.0):
            raise TimeoutError("outcome_node (or the floor node) not discovered within 90 s")
        result["discovery_s"] = round(time.monotonic() - t0, 2)
        # Prime: first frames after discovery may be lost on best effort; wait for an answer.
        # Not fatal: a transport that loses every frame is a result, measured below.
        for target in targets:
            for i in range(PRIME_TRIES):
                publish(PRIME_SEC, i, target)
                if spin_until(lambda i=i, t=target: (PRIME_SEC, i) in t.labels_at, 1.0):
                    target.primed = i + 1
                    break
        result["priming_frames_until_answer"] = real.primed  # None: none of PRIME_TRIES
        result["rss_kb_ready"] = proc_status(args.node_pid)

        if args.latency_frames:
            pids = {"outcome_node": args.node_pid, "floor": args.floor_pid}
            result["latency"] = measure_latency(
                [(name, t, pids[name]) for name, t in zip(("outcome_node", "floor"), targets)],
                args.latency_frames, args.latency_hz, publish, spin_until)
            result["latency"]["note"] = (
                "end_to_end = client publish -> labels received (same clock); node_latency = "
                "arrival at the node -> status published; cpu_ms_per_frame = the node "
                "process's CPU time over the phase / frames answered (idle spinning "
                "included); with a floor node the frames alternate between the two nodes, "
                "the order flipping every frame")
            spin_until(lambda: False, 0.5)

        if args.seconds > 0:
            dropped_start = int(last_status.get("dropped_frames", 0))
            n = int(round(args.seconds * args.hz))
            period = 1.0 / args.hz
            pub_t = np.zeros(n)
            rss = [(0.0, proc_status(args.node_pid)["VmRSS"])]
            cpu0, start = proc_cpu_s(args.node_pid), time.monotonic()
            next_t, next_rss, late = start, start + 2.0, 0
            i = 0
            while i < n:
                now = time.monotonic()
                if now >= next_t:
                    pub_t[i] = publish(THROUGHPUT_SEC, i)
                    i += 1
                    next_t += period
                    if next_t < now - period:  # fell behind by > 1 frame: don't burst
                        late += 1
                        next_t = now + period
                else:
                    executor.spin_once(timeout_sec=next_t - now)
                if now >= next_rss:
                    rss.append((round(now - start, 1), proc_status(args.node_pid)["VmRSS"]))
                    next_rss += 2.0
            feed_s = time.monotonic() - start
            cpu_s = proc_cpu_s(args.node_pid) - cpu0
            spin_until(lambda: (THROUGHPUT_SEC, n - 1) in status_of, 3.0)  # drain
            spin_until(lambda: False, 0.5)
            end_status = proc_status(args.node_pid)
            rss.append((round(time.monotonic() - start, 1), end_status["VmRSS"]))
            answered = sorted((k[1], t) for k, t in labels_at.items() if k[0] == THROUGHPUT_SEC)
            idx = np.array([a for a, _ in answered], int)
            recv = np.array([t for _, t in answered])
            lag = (recv - pub_t[idx]) * 1e3 if idx.size else np.array([])
            # backlog: frames published after frame i but before its answer arrived
            backlog = (np.searchsorted(pub_t, recv, side="right") - 1 - idx) if idx.size \
                else np.array([0])
            dropped = int(last_status.get("dropped_frames", 0)) - dropped_start
            node_lat = [float(v["latency_ms"]) for k, v in status_of.items()
                        if k[0] == THROUGHPUT_SEC and "latency_ms" in v]
            infer = [float(v["inference_ms"]) for k, v in status_of.items()
                     if k[0] == THROUGHPUT_SEC and "inference_ms" in v]
            errors = sum(1 for k, v in status_of.items()
                         if k[0] == THROUGHPUT_SEC and "inference_ms" not in v)
            kept = [v.get("support_plane") == "kept" for k, v in status_of.items()
                    if k[0] == THROUGHPUT_SEC and "support_plane" in v]
            result["throughput"] = {
                "target_hz": args.hz, "seconds": args.seconds, "published": n,
                "achieved_publish_hz": round(n / feed_s, 2), "late_ticks": late,
                "labels_received": int(idx.size),
                "fraction_answered": round(idx.size / n, 4),
                "answered_hz": round(idx.size / feed_s, 2),
                "dropped_frames_node": dropped,
                "dropped_frames_node_total": int(last_status.get("dropped_frames", 0)),
                "lost_before_node": max(0, n - int(idx.size) - dropped),
                "error_status": errors,
                "windows": windows(pub_t - start, idx, lag, args.window_s),
                "lag_ms": percentiles(lag.tolist()) | {"max": round(float(lag.max()), 1)}
                if lag.size else None,
                "backlog_frames": {"max": int(backlog.max()),
                                   "p50": float(np.percentile(backlog, 50))},
                "node_latency_ms": percentiles(node_lat) if node_lat else None,
                "node_inference_ms": percentiles(infer) if infer else None,
                "node_cpu_percent": round(100 * cpu_s / feed_s, 1),
                "node_cpu_ms_per_answered_frame": round(1e3 * cpu_s / max(1, idx.size), 2),
                "support_plane_kept_share": round(float(np.mean(kept)), 3) if kept else None,
                "node_rss_kb": {"start": rss[0][1], "end": rss[-1][1],
                                "max": max(r for _, r in rss), "peak_VmHWM": end_status["VmHWM"],
                                "samples_t_s_kb": rss},
                "note": "lost_before_node = published - answered - node dropped_frames (lost "
                        "in transport or still queued); lag = publish -> labels received; "
                        "backlog = frames published between a frame and its answer"}
        result["ok"] = True
    except Exception as exc:
        result["ok"], result["error"] = False, f"{type(exc).__name__}: {exc}"
    finally:
        args.out.write_text(json.dumps(result, indent=1))
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
