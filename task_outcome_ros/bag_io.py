"""rosbags plumbing shared by the bag tools: typestore, messages, readers, writers, topics.

No rclpy and no DDS: ``outcome_bag`` (bag_tools.py), ``outcome_replay`` (replay.py) and the
training side's ``export-bag`` read and write rosbag2 bags with the rosbags library alone.

Topic names are resolved like the node's relative names: ``depth/image_raw`` with namespace
``/cam1`` is ``/cam1/depth/image_raw``. A bag without that topic but with exactly one
``.../depth/image_raw`` uses that one, so a bag recorded under another namespace still works.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from task_outcome_ros import outcome_report as R
from task_outcome_ros.depth import encode_depth

# The node's topics, as bags record them (re-exported for the bag tools).
from task_outcome_ros.topics import (  # noqa: F401
    CAMERA_INFO_TOPIC,
    DEPTH_TOPIC,
    LABELS_TOPIC,
    OVERLAY_TOPIC,
    STATUS_TOPIC,
)

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
STORAGES = ("mcap", "sqlite3")


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
