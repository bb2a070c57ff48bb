"""Bag tools: ``outcome_bag`` (a rosbag2 bag in -> the node's outputs in a new bag) and the
entry point of ``outcome_replay`` (a bag's depth topics over DDS, in replay.py).

The offline path uses rosbags only: no rclpy, no DDS, no ROS installation. Each depth image
goes through the node's own steps (``depth.decode_depth`` -> ``OutcomeSegmenter.segment`` ->
``outcome_report``), so the labels, status and overlay written here are what the node would
publish for the same message (the timing values aside). A ``ground_truth.json`` beside the input
bag (``python -m training export-bag`` writes one) is scored with the presence rule.

Topic names are resolved like the node's relative names: ``depth/image_raw`` with namespace
``/cam1`` is ``/cam1/depth/image_raw``; the outputs go to ``<namespace>/outcome/...``. A bag
without that topic but with exactly one ``.../depth/image_raw`` uses that one, so a bag recorded
under another namespace can be processed (or replayed) into ``--namespace``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from task_outcome_ros import labels as L
from task_outcome_ros import outcome_report as R
from task_outcome_ros.cli_args import non_negative_int, positive_int
from task_outcome_ros.depth import DepthDecodeError, decode_depth, encode_depth
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
STORAGES = ("mcap", "sqlite3")
DEPTH_TOPIC = "depth/image_raw"
CAMERA_INFO_TOPIC = "depth/camera_info"
LABELS_TOPIC = "outcome/labels"
STATUS_TOPIC = "outcome/status"
OVERLAY_TOPIC = "outcome/overlay"
GROUND_TRUTH_FILE = "ground_truth.json"
SCORE_FILE = "score.json"
SUMMARY_FILE = "summary.json"


class BagToolError(Exception):
    """A problem with the user's input (bag, topic, paths); the text says what to fix."""


# --- rosbags plumbing --------------------------------------------------------------------------

_TYPESTORE = None


def typestore() -> Any:
    """The ROS 2 Jazzy message definitions of rosbags (built once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def msg_class(msgtype: str) -> Any:
    return typestore().types[msgtype]


def resolve_topic(name: str, namespace: str = "") -> str:
    """A relative name under ``namespace`` -> absolute topic name; absolute names stay."""
    if not name or name.endswith("/") or "//" in name:
        raise BagToolError(f"invalid topic name {name!r}")
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


def stamp_to_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def make_header(stamp_ns: int, frame_id: str) -> Any:
    t = msg_class("builtin_interfaces/msg/Time")(sec=int(stamp_ns // 1_000_000_000),
                                                  nanosec=int(stamp_ns % 1_000_000_000))
    return msg_class("std_msgs/msg/Header")(stamp=t, frame_id=frame_id)


def image_message(header: Any, pixels: np.ndarray, encoding: str) -> Any:
    """uint8 H x W (mono8) or H x W x 3 (rgb8) array -> rosbags Image with ``header``."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    data = np.ascontiguousarray(pixels, dtype=np.uint8).reshape(-1)
    return msg_class(IMAGE)(header=header, height=height, width=width, encoding=encoding,
                            is_bigendian=0, step=width * channels, data=data)


def depth_image_message(header: Any, depth_m: np.ndarray, encoding: str) -> Any:
    """float metres (NaN invalid) -> rosbags depth Image, little-endian, per REP 118."""
    data, step = encode_depth(depth_m, encoding)
    height, width = depth_m.shape
    return msg_class(IMAGE)(header=header, height=height, width=width, encoding=encoding,
                            is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))


def camera_info_message(header: Any, width: int, height: int, k: Iterable[float]) -> Any:
    """Pinhole CameraInfo of an undistorted image: K, P = [K | 0], plumb_bob with zero D."""
    k = np.asarray(list(k), np.float64)
    if k.shape != (9,):
        raise ValueError(f"K must have 9 values, got {k.size}")
    p = np.zeros(12, np.float64)
    p[[0, 1, 2, 4, 5, 6, 10]] = k[[0, 1, 2, 3, 4, 5, 8]]
    roi = msg_class("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0,
                                                         width=0, do_rectify=False)
    return msg_class(CAMERA_INFO)(header=header, height=height, width=width,
                                  distortion_model="plumb_bob", d=np.zeros(5, np.float64),
                                  k=k, r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0,
                                  roi=roi)


def status_message(header: Any, fields: R.StatusFields) -> Any:
    """outcome_report.StatusFields -> rosbags DiagnosticArray (as the node publishes it)."""
    kv = msg_class("diagnostic_msgs/msg/KeyValue")
    status = msg_class("diagnostic_msgs/msg/DiagnosticStatus")(
        level=int(fields.level), name=R.STATUS_NAME, message=fields.message,
        hardware_id=header.frame_id, values=[kv(key=k, value=v) for k, v in fields.values])
    return msg_class(DIAGNOSTIC_ARRAY)(header=header, status=[status])


def serialize(msg: Any, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(raw: bytes | memoryview, msgtype: str) -> Any:
    return typestore().deserialize_cdr(raw, msgtype)


def open_writer(path: Path, storage: str = "mcap", overwrite: bool = False) -> Any:
    """An open rosbags Writer (rosbag2 format 9, as Jazzy's) for a new bag folder."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if storage not in STORAGES:
        raise BagToolError(f"storage must be one of {STORAGES}, got {storage!r}")
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise BagToolError(f"{path} exists; pass --overwrite or choose another path")
        if not (path / "metadata.yaml").is_file():
            raise BagToolError(f"{path} exists and is not a rosbag2 bag (no metadata.yaml); "
                               "refusing to delete it")
        shutil.rmtree(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = Writer(path, version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin[storage.upper()])
    writer.open()
    return writer


def open_reader(path: Path) -> Any:
    """An open rosbags Reader, or BagToolError naming the path."""
    from rosbags.rosbag2 import Reader

    try:
        reader = Reader(Path(path))
        reader.open()
    except FileNotFoundError:
        raise BagToolError(f"no bag at {path}") from None
    except Exception as exc:  # ReaderError and yaml errors: not a readable rosbag2 bag
        raise BagToolError(f"cannot read bag {path}: {exc}") from None
    return reader


def bag_storage(path: Path) -> str:
    """'mcap' or 'sqlite3': how the bag at ``path`` is stored."""
    path = Path(path)
    files = [path] if path.is_file() else list(path.iterdir())
    return "mcap" if any(f.suffix == ".mcap" for f in files) else "sqlite3"


def find_connection(reader: Any, topic: str, msgtype: str) -> Any | None:
    """The bag's connection of ``topic`` (BagToolError if it has another type)."""
    for conn in reader.connections:
        if conn.topic == topic:
            if conn.msgtype != msgtype:
                raise BagToolError(f"topic {topic} in the bag is {conn.msgtype}, expected "
                                   f"{msgtype}")
            return conn
    return None


def bag_connection(reader: Any, name: str, namespace: str, msgtype: str) -> Any | None:
    """The bag's topic for the relative ``name``: ``<namespace>/<name>`` if the bag has it,
    else the only ``msgtype`` topic ending in ``/<name>`` (a bag recorded under another
    namespace); None if there is neither. Absolute names must match exactly."""
    conn = find_connection(reader, resolve_topic(name, namespace), msgtype)
    if conn is not None or name.startswith("/"):
        return conn
    tail = [c for c in reader.connections
            if c.msgtype == msgtype and c.topic.endswith("/" + name)]
    return tail[0] if len({c.topic for c in tail}) == 1 else None


def require_connection(reader: Any, name: str, namespace: str, msgtype: str,
                       path: Path) -> Any:
    conn = bag_connection(reader, name, namespace, msgtype)
    if conn is None:
        same_type = sorted({c.topic for c in reader.connections if c.msgtype == msgtype})
        tail = "" if name.startswith("/") else f" nor exactly one '.../{name}'"
        raise BagToolError(f"bag {path} has no topic {resolve_topic(name, namespace)}{tail}; "
                           f"its {msgtype} topics: {same_type or 'none'} (use --topic / "
                           "--namespace)")
    return conn


def copy_connection(writer: Any, conn: Any) -> Any:
    """The same topic, type, definition and offered QoS in ``writer``."""
    ext = conn.ext
    qos = list(getattr(ext, "offered_qos_profiles", []) or [])
    fmt = getattr(ext, "serialization_format", "cdr")
    if conn.msgdef.data and conn.digest and conn.digest.startswith("RIHS01_"):
        return writer.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data,
                                     rihs01=conn.digest, serialization_format=fmt,
                                     offered_qos_profiles=qos)
    return writer.add_connection(conn.topic, conn.msgtype, typestore=typestore(),
                                 serialization_format=fmt, offered_qos_profiles=qos)


# --- one frame -----------------------------------------------------------------------------------

@dataclass
class FrameOutputs:
    """What the node publishes for one depth image (labels/overlay None on an ERROR frame)."""

    header: Any
    fields: R.StatusFields
    labels: np.ndarray | None = None
    overlay: np.ndarray | None = None
    present: dict[str, bool] | None = None
    inference_ms: float | None = None


def process_frame(segmenter: Any, msg: Any, camera_info: Any | None,
                  overlay_alpha: float | None, t_start: float) -> FrameOutputs:
    """The node's ``_process`` on a deserialized Image (any object with Image's fields).

    ``overlay_alpha`` None: no overlay. ``t_start`` (time.monotonic) is when the message was
    read, for latency_ms.
    """
    header = msg.header

    def latency() -> float:
        return (time.monotonic() - t_start) * 1e3

    try:
        depth = decode_depth(msg.encoding, int(msg.height), int(msg.width), int(msg.step),
                             bool(msg.is_bigendian), msg.data)
    except DepthDecodeError as exc:
        return FrameOutputs(header, R.error_fields(f"bad depth image: {exc}",
                                                   latency_ms=latency()))
    height, width = depth.shape
    intrinsics, note = None, None
    if camera_info is not None:
        try:
            intrinsics = R.intrinsics_for_image(camera_info.width, camera_info.height,
                                                camera_info.k, width, height)
        except ValueError as exc:
            note = f"ignored: {exc}"
    try:
        res = segmenter.segment(depth, intrinsics)  # as the node: heights use camera_info
    except Exception as exc:  # like the node: one bad frame never stops the run
        return FrameOutputs(header, R.error_fields(f"inference failed: {exc}",
                                                   latency_ms=latency()))
    labels = np.ascontiguousarray(res.labels, dtype=np.uint8)
    overlay = None if overlay_alpha is None else R.overlay_rgb(depth, labels, overlay_alpha)
    fields = R.status_fields(res, intrinsics, camera_note=note, latency_ms=latency())
    return FrameOutputs(header, fields, labels, overlay, dict(res.present), res.inference_ms)


# --- scoring against ground truth ----------------------------------------------------------------

def load_ground_truth(bag: Path) -> dict | None:
    """``ground_truth.json`` inside the bag folder (or beside a bag file), if there is one."""
    bag = Path(bag)
    path = (bag if bag.is_dir() else bag.parent) / GROUND_TRUTH_FILE
    if not path.is_file():
        return None
    try:
        gt = json.loads(path.read_text())
        for frame in gt["frames"]:
            for field in ("stamp_ns", "pixel_counts", "width", "height"):
                if field not in frame:
                    raise KeyError(f"a frame has no '{field}'")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BagToolError(f"{path}: not a ground-truth file of `python -m training "
                           f"export-bag` ({type(exc).__name__}: {exc})") from None
    gt["path"] = str(path)
    return gt


def score(ground_truth: dict, predicted: dict[int, dict[str, bool] | None],
          presence_min_pixels: int = L.PRESENCE_MIN_PIXELS) -> dict:
    """Image-level presence scores of ``predicted`` (stamp ns -> present, None = ERROR frame).

    The truth is the presence rule applied to the ground-truth pixel counts with the same
    ``presence_min_pixels``. A frame with no prediction (ERROR status, or missing from the bag)
    counts as not all-correct and as 'nothing present' for precision and recall.
    """
    n = len(ground_truth["frames"])
    truth = np.zeros((n, len(L.OUTCOME_NAMES)), bool)
    pred = np.zeros_like(truth)
    correct = np.zeros(n, bool)
    mistakes, n_errors, n_missing = [], 0, 0
    for i, frame in enumerate(ground_truth["frames"]):
        threshold = L.presence_threshold(frame["height"], frame["width"], presence_min_pixels)
        truth[i] = [frame["pixel_counts"][name] >= threshold for name in L.OUTCOME_NAMES]
        stamp = int(frame["stamp_ns"])
        if stamp not in predicted:
            n_missing += 1
        elif predicted[stamp] is None:
            n_errors += 1
        else:
            pred[i] = [bool(predicted[stamp][name]) for name in L.OUTCOME_NAMES]
            correct[i] = bool(np.all(truth[i] == pred[i]))
        if not correct[i]:
            mistakes.append({"index": frame.get("index", i), "episode": frame.get("episode"),
                             "stamp_ns": stamp})
    # Missing and ERROR frames predict nothing present, and are never all-correct.
    report: dict[str, Any] = {
        "n_images": n,
        **L.presence_scores(truth, pred),
        "image_all_correct": float(correct.mean()) if n else 0.0,
        "n_errors": n_errors,
        "n_missing": n_missing,
        "presence_min_pixels": presence_min_pixels,
    }
    report["mistakes"] = mistakes
    return report


# --- the offline run -----------------------------------------------------------------------------

def process_bag(in_bag: Path, out_bag: Path | None = None, *, model: str | None = None,
                device: str = "cpu", backend: str = "auto",
                presence_min_pixels: int = L.PRESENCE_MIN_PIXELS,
                fragment_max_pixels: int = FRAGMENT_MAX_PIXELS,
                topic: str = DEPTH_TOPIC, camera_info_topic: str = CAMERA_INFO_TOPIC,
                namespace: str = "", overlay: bool = True,
                overlay_alpha: float = R.DEFAULT_OVERLAY_ALPHA, copy_input: bool = True,
                storage: str | None = None, overwrite: bool = False,
                num_threads: int | None = None, progress: bool = True) -> dict:
    """Run the segmenter on every depth image of ``in_bag``; write ``out_bag``; return the
    summary (also written to ``<out_bag>/summary.json``, the score to ``score.json``)."""
    from tqdm import tqdm

    in_bag = Path(in_bag)
    out_bag = Path(out_bag) if out_bag else in_bag.with_name(in_bag.name + "_outcome")
    if out_bag.resolve() == in_bag.resolve():
        raise BagToolError("the output bag must differ from the input bag")
    if out_bag.exists() and not overwrite:  # before loading the model: fail fast
        raise BagToolError(f"{out_bag} exists; pass --overwrite or choose another --out")
    if not 0.0 <= overlay_alpha <= 1.0:
        raise BagToolError(f"overlay alpha must be in [0, 1], got {overlay_alpha}")
    ground_truth = load_ground_truth(in_bag)

    reader = open_reader(in_bag)
    try:  # topics first: a wrong name fails before the model loads
        image_conn = require_connection(reader, topic, namespace, IMAGE, in_bag)
        info_conn = bag_connection(reader, camera_info_topic, namespace, CAMERA_INFO)
        out_topics = {name: resolve_topic(name, namespace)
                      for name in (LABELS_TOPIC, STATUS_TOPIC, OVERLAY_TOPIC)
                      if overlay or name != OVERLAY_TOPIC}
        clash = sorted(set(out_topics.values()) & {c.topic for c in reader.connections})
        if copy_input and clash:
            raise BagToolError(f"bag {in_bag} already has {clash}: pass --no-copy-input or "
                               "another --namespace")
        segmenter = _segmenter(model, device, backend, presence_min_pixels, num_threads,
                               fragment_max_pixels)
        writer = open_writer(out_bag, storage or bag_storage(in_bag), overwrite)
        try:
            copied = {c.id: copy_connection(writer, c) for c in reader.connections} \
                if copy_input else {}
            types = {LABELS_TOPIC: IMAGE, STATUS_TOPIC: DIAGNOSTIC_ARRAY, OVERLAY_TOPIC: IMAGE}
            out = {name: writer.add_connection(name_, types[name], typestore=typestore())
                   for name, name_ in out_topics.items()}
            wanted = reader.connections if copy_input else \
                [c for c in (image_conn, info_conn) if c is not None]
            t0 = time.perf_counter()
            stats = _Stats()
            camera_info = None
            bar = tqdm(total=image_conn.msgcount, desc="outcome_bag", unit="frame",
                       disable=not progress)
            for conn, log_time, raw in reader.messages(connections=wanted):
                if conn.id in copied:
                    writer.write(copied[conn.id], log_time, raw)
                if info_conn is not None and conn.id == info_conn.id:
                    try:  # the newest camera_info, as the node keeps it
                        camera_info = deserialize(raw, CAMERA_INFO)
                    except Exception:  # a corrupt camera_info only costs the 3-D positions
                        camera_info = None
                elif conn.id == image_conn.id:
                    frame = _process_raw(segmenter, raw, log_time, camera_info,
                                         overlay_alpha if overlay else None)
                    _write_frame(writer, out, frame, log_time)
                    stats.add(frame)
                    bar.update()
            bar.close()
        finally:
            writer.close()
    finally:
        reader.close()

    summary = stats.summary(in_bag, out_bag, time.perf_counter() - t0, segmenter)
    if ground_truth is not None:
        report = score(ground_truth, stats.predicted, presence_min_pixels)
        report.update(bag=str(in_bag), ground_truth=ground_truth["path"],
                      model=str(segmenter.model_path))
        (out_bag / SCORE_FILE).write_text(json.dumps(report, indent=2) + "\n")
        summary["score"] = {k: report[k] for k in ("n_images", "image_all_correct",
                                                   "presence_precision", "presence_recall")}
    (out_bag / SUMMARY_FILE).write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _segmenter(model: str | None, device: str, backend: str, presence_min_pixels: int,
               num_threads: int | None, fragment_max_pixels: int) -> Any:
    # Imported here so the rosbags helpers (used by `training export-bag`) do not load torch.
    from task_outcome_ros.checkpoint import CheckpointError
    from task_outcome_ros.inference import OutcomeSegmenter

    try:
        segmenter = OutcomeSegmenter(model or None, device=device,
                                     presence_min_pixels=presence_min_pixels, backend=backend,
                                     num_threads=num_threads,
                                     fragment_max_pixels=fragment_max_pixels)
        segmenter.warmup()  # as the node does, so the first inference_ms is not inflated
        return segmenter
    except (CheckpointError, ValueError, RuntimeError, OSError, ImportError) as exc:
        raise BagToolError(f"cannot use model '{model or 'shipped'}': {exc}") from None


def _process_raw(segmenter: Any, raw: bytes, log_time: int, camera_info: Any,
                 overlay_alpha: float | None) -> FrameOutputs:
    t_start = time.monotonic()
    try:
        msg = deserialize(raw, IMAGE)
    except Exception as exc:  # SerdeError and friends: no header to copy, use the log time
        return FrameOutputs(make_header(log_time, ""),
                            R.error_fields(f"bad depth image: cannot deserialize: {exc}"))
    return process_frame(segmenter, msg, camera_info, overlay_alpha, t_start)


def _write_frame(writer: Any, out: dict, frame: FrameOutputs, log_time: int) -> None:
    if frame.labels is not None:
        writer.write(out[LABELS_TOPIC], log_time,
                     serialize(image_message(frame.header, frame.labels, "mono8"), IMAGE))
    writer.write(out[STATUS_TOPIC], log_time,
                 serialize(status_message(frame.header, frame.fields), DIAGNOSTIC_ARRAY))
    if frame.overlay is not None and OVERLAY_TOPIC in out:
        writer.write(out[OVERLAY_TOPIC], log_time,
                     serialize(image_message(frame.header, frame.overlay, "rgb8"), IMAGE))


class _Stats:
    def __init__(self) -> None:
        self.frames = 0
        self.errors: list[str] = []
        self.present = dict.fromkeys(L.OUTCOME_NAMES, 0)
        self.levels = {"OK": 0, "WARN": 0, "ERROR": 0}
        self.inference_ms: list[float] = []
        self.predicted: dict[int, dict[str, bool] | None] = {}

    def add(self, frame: FrameOutputs) -> None:
        self.frames += 1
        self.levels[("OK", "WARN", "ERROR")[frame.fields.level]] += 1
        stamp = stamp_to_ns(frame.header.stamp)
        self.predicted[stamp] = frame.present
        if frame.present is None:
            self.errors.append(frame.fields.message)
            return
        for name, is_present in frame.present.items():
            self.present[name] += int(is_present)
        self.inference_ms.append(float(frame.inference_ms))

    def summary(self, in_bag: Path, out_bag: Path, seconds: float, segmenter: Any) -> dict:
        ms = self.inference_ms
        return {"input": str(in_bag), "output": str(out_bag), "frames": self.frames,
                "errors": len(self.errors), "error_messages": sorted(set(self.errors))[:10],
                "present_counts": self.present, "levels": self.levels,
                "inference_ms_p50": float(np.percentile(ms, 50)) if ms else None,
                "seconds": round(seconds, 3), "model": str(segmenter.model_path),
                "backend": segmenter.backend}


def _print_summary(summary: dict) -> None:
    present = ", ".join(f"{k} {v}" for k, v in summary["present_counts"].items())
    p50 = summary["inference_ms_p50"]
    print(f"outcome_bag: {summary['frames']} frames, {summary['errors']} errors "
          f"({summary['seconds']:.1f} s, inference p50 "
          f"{'-' if p50 is None else f'{p50:.1f} ms'}) -> {summary['output']}")
    print(f"  outcomes present in: {present}; status {summary['levels']}")
    for message in summary["error_messages"]:
        print(f"  error: {message}")
    if "score" in summary:
        s = summary["score"]
        print(f"  vs ground truth: image all-correct {s['image_all_correct']:.4f} over "
              f"{s['n_images']} images, presence recall {s['presence_recall']} -> "
              f"{Path(summary['output']) / SCORE_FILE}")


def build_offline_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="outcome_bag", description="Run the outcome segmenter on every depth image of a "
        "rosbag2 bag and write outcome/labels, outcome/status and outcome/overlay (with the "
        "input headers and log times) into a new bag; score it if the input bag has a "
        f"{GROUND_TRUTH_FILE}. No ROS installation or DDS needed.")
    p.add_argument("bag", type=Path, help="input bag folder (mcap or sqlite3)")
    p.add_argument("--out", type=Path, default=None,
                   help="output bag folder (default: <bag>_outcome)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--model", default=None, help="checkpoint or ONNX file (default: shipped)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    p.add_argument("--backend", choices=("auto", "torch", "onnx"), default="auto")
    p.add_argument("--threads", type=positive_int, default=None, help="inference threads")
    p.add_argument("--presence-min-pixels", type=positive_int, default=L.PRESENCE_MIN_PIXELS,
                   help="pixels an outcome needs to be present at 640x480 (default %(default)s)")
    p.add_argument("--fragment-max-pixels", type=non_negative_int, default=FRAGMENT_MAX_PIXELS,
                   help="absorb outcome fragments smaller than this (at 640x480) into the "
                        "outcome they touch; 0 = off (default %(default)s)")
    p.add_argument("--topic", default=DEPTH_TOPIC, help="depth image topic (default %(default)s)")
    p.add_argument("--camera-info-topic", default=CAMERA_INFO_TOPIC,
                   help="camera_info topic (default %(default)s)")
    p.add_argument("--namespace", default="",
                   help="namespace of relative topic names, inputs and outputs (default: /)")
    p.add_argument("--no-overlay", action="store_true", help="do not write outcome/overlay")
    p.add_argument("--overlay-alpha", type=float, default=R.DEFAULT_OVERLAY_ALPHA)
    p.add_argument("--no-copy-input", action="store_true",
                   help="write only the outcome topics, not the input bag's topics")
    p.add_argument("--storage", choices=STORAGES, default=None,
                   help="output storage (default: the input's)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def offline_main(argv: list[str] | None = None) -> int:
    """Console script ``outcome_bag``; returns the exit code."""
    args = build_offline_parser().parse_args(argv)
    try:
        summary = process_bag(
            args.bag, args.out, model=args.model, device=args.device, backend=args.backend,
            presence_min_pixels=args.presence_min_pixels,
            fragment_max_pixels=args.fragment_max_pixels, topic=args.topic,
            camera_info_topic=args.camera_info_topic, namespace=args.namespace,
            overlay=not args.no_overlay, overlay_alpha=args.overlay_alpha,
            copy_input=not args.no_copy_input, storage=args.storage, overwrite=args.overwrite,
            num_threads=args.threads, progress=not args.no_progress)
    except BagToolError as exc:
        print(f"outcome_bag: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("outcome_bag: interrupted", file=sys.stderr)
        return 130
    _print_summary(summary)
    return 0


def replay_main(argv: list[str] | None = None) -> int:
    """Console script ``outcome_replay`` (rclpy is imported only in there)."""
    from task_outcome_ros.replay import main

    return main(argv)


if __name__ == "__main__":
    sys.exit(offline_main())
