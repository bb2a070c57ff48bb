"""``outcome_bag``: a rosbag2 bag in -> the node's outputs in a new bag, scored if it can be.

The offline path uses rosbags only: no rclpy, no DDS, no ROS installation. Each depth image
goes through the node's own step (``frames.process_frame``), so the labels, status and overlay
written here are what the node would publish for the same message (the timing values aside).
A ``ground_truth.json`` beside the input bag (``python -m training export-bag`` writes one) is
scored with the presence rule. Outputs go to ``<namespace>/outcome/...``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from task_outcome_ros import labels as L
from task_outcome_ros import outcome_report as R
from task_outcome_ros.bag_io import (
    CAMERA_INFO,
    CAMERA_INFO_TOPIC,
    DEPTH_TOPIC,
    DIAGNOSTIC_ARRAY,
    IMAGE,
    LABELS_TOPIC,
    OVERLAY_TOPIC,
    STATUS_TOPIC,
    STORAGES,
    BagToolError,
    bag_connection,
    bag_storage,
    copy_connection,
    deserialize,
    image_message,
    make_header,
    open_reader,
    open_writer,
    require_connection,
    resolve_topic,
    serialize,
    stamp_to_ns,
    status_message,
    typestore,
)
from task_outcome_ros.cli_args import non_negative_int, positive_int
from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS
from task_outcome_ros.frames import FrameOutputs, process_frame
from task_outcome_ros.ground_truth import (
    GROUND_TRUTH_FILE,
    load_ground_truth,
    require_outcomes,
    score,
)

SCORE_FILE = "score.json"
SUMMARY_FILE = "summary.json"


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
        if ground_truth is not None:  # a model of another task fails before the first frame
            require_outcomes(ground_truth, segmenter.table.outcome_names)
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
            stats = _Stats(segmenter.table)
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
                                     fragment_max_pixels=fragment_max_pixels,
                                     # one topic is one camera: as the node does
                                     reuse_floor_fit=True)
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
        why = f"bad depth image: cannot deserialize: {exc}"
        return FrameOutputs(make_header(log_time, ""), R.error_fields(why), error=why)
    return process_frame(segmenter, msg, camera_info, overlay_alpha=overlay_alpha,
                         t_start=t_start)


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
    def __init__(self, table: L.LabelTable) -> None:
        self.frames = 0
        self.errors: list[str] = []
        self.present = dict.fromkeys(table.outcome_names, 0)  # frames each outcome is in
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
    p.add_argument("--model", default=None,
                   help="a shipped model's name or a checkpoint file (default: default)")
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


if __name__ == "__main__":
    sys.exit(offline_main())
