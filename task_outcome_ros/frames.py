"""One depth frame through the outcome pipeline: the step the node and ``outcome_bag`` share.

A message (rclpy's or rosbags', anything with ``sensor_msgs/Image``'s fields) and the newest
camera_info go in; what the node publishes for that frame comes out: labels, status fields,
optionally the overlay, plus the segmentation result for markers. Keeping this in one place is
what makes ``outcome_bag``'s output the node's output for the same message (timing aside).

No rclpy here: the node converts the outputs to messages and logs the problems this returns.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from task_outcome_ros import outcome_report as R
from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.depth import DepthDecodeError, decode_depth


@dataclass
class FrameOutputs:
    """What one frame produced. ``error`` set means an ERROR status and nothing else."""

    header: Any
    fields: R.StatusFields
    labels: np.ndarray | None = None
    overlay: np.ndarray | None = None
    result: Any | None = None  # inference.OutcomeResult
    intrinsics: Intrinsics | None = None
    error: str | None = None
    # Notes for the log, not errors: camera_info ignored, nominal camera used.
    notes: list[str] = field(default_factory=list)

    @property
    def present(self) -> dict[str, bool] | None:
        return None if self.result is None else dict(self.result.present)

    @property
    def inference_ms(self) -> float | None:
        return None if self.result is None else float(self.result.inference_ms)


NO_CAMERA_INFO_NOTE = ("no usable depth/camera_info: the network's height channel uses the "
                       "nominal camera, whose heights are a few per cent off")


def frame_intrinsics(camera_info: Any | None, width: int, height: int,
                     ) -> tuple[Intrinsics | None, str | None]:
    """The camera_info's pinhole camera for a ``width`` x ``height`` frame, or None and why."""
    if camera_info is None:
        return None, None
    try:
        return R.intrinsics_for_image(int(camera_info.width), int(camera_info.height),
                                      camera_info.k, width, height), None
    except ValueError as exc:
        return None, f"ignored: {exc}"


def process_frame(segmenter: Any, msg: Any, camera_info: Any | None, *,
                  overlay_alpha: float | None = None, t_start: float | None = None,
                  dropped: int = 0) -> FrameOutputs:
    """Decode ``msg``, segment it with ``segmenter`` (an ``OutcomeSegmenter``: ``segment``
    and its label ``table``) and build the status fields.

    ``overlay_alpha`` None: no overlay (nobody asked for it). ``t_start`` (time.monotonic)
    is when the frame arrived, for ``latency_ms``; ``dropped`` is the node's count of
    overwritten frames (0 offline). One bad frame never raises: it comes back with
    ``error`` set and ERROR fields.
    """
    t_start = time.monotonic() if t_start is None else t_start
    header = msg.header

    def failed(why: str) -> FrameOutputs:
        fields = R.error_fields(why, dropped=dropped, latency_ms=since_ms(t_start))
        return FrameOutputs(header, fields, error=why)

    try:
        depth = decode_depth(msg.encoding, int(msg.height), int(msg.width), int(msg.step),
                             bool(msg.is_bigendian), msg.data)
    except DepthDecodeError as exc:
        return failed(f"bad depth image: {exc}")
    height, width = depth.shape
    intrinsics, camera_note = frame_intrinsics(camera_info, width, height)
    notes = [f"camera_info {camera_note}"] if camera_note else []
    if intrinsics is None and getattr(segmenter, "uses_intrinsics", False):
        notes.append(NO_CAMERA_INFO_NOTE)
    try:
        # The intrinsics also set the network's height channel when the model was trained
        # with them (OutcomeSegmenter.uses_intrinsics); otherwise the nominal camera.
        result = segmenter.segment(depth, intrinsics, sanitized=True)  # decode_depth's
    except Exception as exc:  # one frame the model cannot take never stops the caller
        return failed(f"inference failed on a {width} x {height} frame: {exc}")
    labels = np.ascontiguousarray(result.labels, dtype=np.uint8)
    # The segmenter's table names the outcomes, failure modes and colours of its model.
    fields = R.status_fields(result, intrinsics, table=segmenter.table,
                             camera_note=camera_note, dropped=dropped,
                             latency_ms=since_ms(t_start))
    overlay = None if overlay_alpha is None else R.overlay_rgb(depth, labels, overlay_alpha,
                                                               segmenter.table)
    return FrameOutputs(header, fields, labels, overlay, result, intrinsics, notes=notes)


def since_ms(t_start: float) -> float:
    """Milliseconds from arrival to now (queueing, decoding and inference)."""
    return (time.monotonic() - t_start) * 1e3
