"""``python -m training export-bag``: a dataset run's images as a rosbag2 bag, with ground truth.

Writes ``depth/image_raw`` (sensor_msgs/Image, 32FC1 or 16UC1) and ``depth/camera_info``
(sensor_msgs/CameraInfo: the episode's K, P = [K | 0], plumb_bob with zero D) at a fixed rate,
stamps from a fixed epoch (same run and options, same messages), message log time = header
stamp, camera_info written just before its image. Beside the messages, inside the bag folder:
``ground_truth.json`` (per frame its index, stamp, episode, size, pixel counts and presence per
outcome) and, with ``--with-labels``, the label PNGs under ``labels/``. ``outcome_bag`` reads
that file to score its answers; ``outcome_replay`` plays the bag to a running node.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from tqdm import tqdm

from task_outcome_ros import bag_io as B
from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.cli_args import positive_float, positive_int
from task_outcome_ros.ground_truth import GROUND_TRUTH_FILE
from task_outcome_ros.labels import PRESENCE_MIN_PIXELS
from training.dataset import load_manifest, manifest_table
from training.render import image_paths, read_pair, reported_camera

# 2023-11-14T22:13:20Z. Fixed rather than the wall clock, so exports are reproducible.
EPOCH_NS = 1_700_000_000 * 1_000_000_000
ENCODINGS = ("32FC1", "16UC1")
SPLITS = ("val", "train", "all")
DEFAULT_FRAME_ID = "camera_depth_optical_frame"
GROUND_TRUTH_FORMAT = "task_outcome_ros ground truth 1"


def frame_stamp_ns(index: int, rate_hz: float) -> int:
    return EPOCH_NS + int(round(index * 1e9 / rate_hz))


def export_bag(run_dir: Path, bag: Path | None = None, *, split: str = "val",
               limit: int | None = None, rate_hz: float = 5.0, encoding: str = "32FC1",
               storage: str = "mcap", frame_id: str = DEFAULT_FRAME_ID, namespace: str = "",
               with_labels: bool = False, overwrite: bool = False,
               progress: bool = True) -> dict:
    """Write the bag; returns the ground truth (also ``<bag>/ground_truth.json``)."""
    run_dir = Path(run_dir)
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    if not rate_hz > 0:
        raise ValueError(f"rate must be > 0 Hz, got {rate_hz}")
    if not frame_id:
        raise ValueError("frame_id must not be empty")
    manifest = load_manifest(run_dir)  # FileNotFoundError names the file
    images = [im for im in manifest["images"] if split == "all" or im["split"] == split]
    if limit is not None:
        images = images[:limit]
    if not images:
        raise ValueError(f"{run_dir / 'manifest.json'}: no images in split {split!r}")
    bag = Path(bag) if bag else run_dir / "bags" / f"{split}_{encoding}"
    try:
        image_topic = B.resolve_topic(B.DEPTH_TOPIC, namespace)
        info_topic = B.resolve_topic(B.CAMERA_INFO_TOPIC, namespace)
        writer = B.open_writer(bag, storage, overwrite)
    except B.BagToolError as exc:
        raise ValueError(str(exc)) from None

    frames = []
    try:
        # camera_info first: at equal log times both storages keep the write order.
        info_conn = writer.add_connection(info_topic, B.CAMERA_INFO, typestore=B.typestore())
        image_conn = writer.add_connection(image_topic, B.IMAGE, typestore=B.typestore())
        for index, im in enumerate(tqdm(images, desc="export-bag", unit="img",
                                        disable=not progress)):
            depth, _ = read_pair(run_dir, im["episode"])
            height, width = depth.shape
            cam = reported_camera(im)
            if (cam["width"], cam["height"]) != (width, height):
                raise ValueError(f"{run_dir / 'manifest.json'}: episode {im['episode']} camera "
                                 f"is {cam['width']} x {cam['height']}, its image {width} x "
                                 f"{height}")
            stamp = frame_stamp_ns(index, rate_hz)
            header = B.make_header(stamp, frame_id)
            info = B.camera_info_message(header, width, height,
                                         Intrinsics.from_record(cam).k())
            writer.write(info_conn, stamp, B.serialize(info, B.CAMERA_INFO))
            writer.write(image_conn, stamp,
                         B.serialize(B.depth_image_message(header, depth, encoding), B.IMAGE))
            frame = {"index": index, "stamp": {"sec": stamp // 1_000_000_000,
                                               "nanosec": stamp % 1_000_000_000},
                     "stamp_ns": stamp, "episode": im["episode"], "split": im["split"],
                     "width": width, "height": height, "present": im["present"],
                     "pixel_counts": im["pixel_counts"], "objects": im["objects"]}
            frames.append(frame)
    finally:
        writer.close()

    if with_labels:
        (bag / "labels").mkdir()
        for frame in frames:
            name = f"{frame['episode']:06d}_labels.png"
            shutil.copyfile(image_paths(run_dir, frame["episode"])[1], bag / "labels" / name)
            frame["labels_png"] = f"labels/{name}"
    truth = {"format": GROUND_TRUTH_FORMAT, "bag": str(bag), "run": str(run_dir), "split": split,
             "seed": manifest.get("seed"), "image_topic": image_topic,
             "camera_info_topic": info_topic, "frame_id": frame_id, "encoding": encoding,
             "storage": storage, "rate_hz": rate_hz, "epoch_ns": EPOCH_NS,
             "presence_min_pixels": PRESENCE_MIN_PIXELS, "n_frames": len(frames),
             "label_table": manifest_table(manifest).to_dict(), "frames": frames}
    (bag / GROUND_TRUTH_FILE).write_text(json.dumps(truth, indent=1) + "\n")
    return truth


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("runs/default"),
                   help="dataset run folder with manifest.json (default: %(default)s)")
    p.add_argument("--bag", type=Path, default=None,
                   help="bag folder to create (default: <out>/bags/<split>_<encoding>)")
    p.add_argument("--split", choices=SPLITS, default="val")
    p.add_argument("--limit", type=positive_int, default=None, help="at most N images")
    p.add_argument("--rate", type=positive_float, default=5.0,
                   help="frames per second of the stamps (default %(default)s)")
    p.add_argument("--encoding", choices=ENCODINGS, default="32FC1")
    p.add_argument("--storage", choices=B.STORAGES, default="mcap")
    p.add_argument("--frame-id", default=DEFAULT_FRAME_ID)
    p.add_argument("--namespace", default="", help="topic prefix, e.g. /cam1 (default: none)")
    p.add_argument("--with-labels", action="store_true",
                   help="copy the ground-truth label PNGs into <bag>/labels/")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")


def cmd_export_bag(args: argparse.Namespace) -> None:
    truth = export_bag(args.out, args.bag, split=args.split, limit=args.limit,
                       rate_hz=args.rate, encoding=args.encoding, storage=args.storage,
                       frame_id=args.frame_id, namespace=args.namespace,
                       with_labels=args.with_labels, overwrite=args.overwrite)
    print(f"export-bag: {truth['n_frames']} frames ({args.split}, {args.encoding}, "
          f"{args.rate:g} Hz, {args.storage}) on {truth['image_topic']} and "
          f"{truth['camera_info_topic']} -> {truth['bag']} (+ {GROUND_TRUTH_FILE})")


