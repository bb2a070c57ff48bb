"""What one processed frame's outputs say: overlay pixels and status fields (docs/interface.md §5).

Pure functions (numpy and str in, numpy and plain tuples out, no rclpy), shared by the node and
the bag tools, so a bag processed offline carries exactly what the node publishes live. The
callers only wrap the results in their message types (rclpy or rosbags). Outcome names,
failure modes and colours are the model's label table; the status carries that table (value
``label_table``), so its readers (check.py, live_bag.py) never assume a task.
"""

from __future__ import annotations

import functools
import json
import math
from typing import Any, NamedTuple

import cv2
import numpy as np

from task_outcome_ros import labels as L
from task_outcome_ros.camera import Intrinsics, intrinsics_for_image  # noqa: F401 (re-export)
from task_outcome_ros.envelope import envelope_value

UNCHECKED = "unchecked: the checkpoint records no training envelope"

STATUS_NAME = "task_outcome"
# diagnostic_msgs/DiagnosticStatus levels (the byte constants, as ints).
OK, WARN, ERROR = 0, 1, 2
DEFAULT_OVERLAY_ALPHA = 0.5
LABEL_TABLE_KEY = "label_table"  # status value: the table's classes as compact JSON


# --- overlay -----------------------------------------------------------------------------------

def colourise_depth(depth_m: np.ndarray) -> np.ndarray:
    """float metres (NaN invalid) -> RGB uint8 grey shading (near bright), invalid mid-grey."""
    valid = np.isfinite(depth_m)
    rgb = np.empty(depth_m.shape + (3,), np.uint8)
    rgb[:] = L.IGNORE_COLOUR
    if valid.any():
        # Robust range from a subsample: a full-image percentile costs ~10 ms at 640 x 480.
        step = max(1, int(math.sqrt(depth_m.size / 20_000)))
        sample = depth_m[::step, ::step]
        sample = sample[np.isfinite(sample)]
        lo, hi = np.percentile(sample, (1, 99)) if sample.size else np.nanpercentile(
            depth_m, (1, 99))
        scale = 255.0 / max(float(hi - lo), 1e-6)
        grey = cv2.convertScaleAbs(np.where(valid, depth_m, lo), alpha=-scale,
                                   beta=255.0 + lo * scale)  # near -> 255, far -> 0, saturated
        # Grey, not a rainbow: the label colours (green/yellow/red) must stand out from it.
        np.copyto(rgb, np.repeat(grey[..., None], 3, axis=2), where=valid[..., None])
    return rgb


def overlay_rgb(depth_m: np.ndarray, labels: np.ndarray,
                alpha: float = DEFAULT_OVERLAY_ALPHA,
                table: L.LabelTable = L.DEFAULT_TABLE) -> np.ndarray:
    """Colourised depth with every non-background label blended in at ``alpha`` (H x W x 3),
    in the colours of ``table``."""
    out = colourise_depth(depth_m)
    mask = labels != L.BACKGROUND
    if alpha > 0 and mask.any():
        blend = cv2.addWeighted(L.colourise(labels, table), alpha, out, 1.0 - alpha, 0.0)
        np.copyto(out, blend, where=mask[..., None])
    return out


# --- status ------------------------------------------------------------------------------------

class Centroid(NamedTuple):
    """One failure object: its outcome, index (largest first) and optical-frame position."""

    outcome: str
    index: int
    xyz: tuple[float, float, float]


class StatusFields(NamedTuple):
    """The content of the one DiagnosticStatus named STATUS_NAME."""

    level: int
    message: str
    values: list[tuple[str, str]]


class StatusOutcomes(NamedTuple):
    """The outcomes a status reports on, in id order, and which of them are failure modes."""

    names: tuple[str, ...]
    failures: tuple[str, ...]


def status_level(present: dict[str, bool], failures: tuple[str, ...]) -> int:
    """OK when only success-like outcomes (or nothing) are present, WARN when one of
    ``failures`` (a table's failure modes) is."""
    return WARN if any(present.get(name, False) for name in failures) else OK


@functools.lru_cache(maxsize=8)  # one table per model: encoded once, not every frame
def label_table_value(table: L.LabelTable) -> str:
    """The status value ``label_table``: per class its id, name, colour and whether it is a
    failure mode, as compact JSON (clients learn the outcomes of any task from it)."""
    return json.dumps(table.to_dict()["classes"], separators=(",", ":"))


def status_outcomes(values: dict[str, str]) -> StatusOutcomes:
    """The outcomes of a status's key/values: from its ``label_table`` value; for a status
    without a readable one from its ``<name>.present`` keys (an older node served the default
    task only; outcomes of another task then all count as failures, so that a check never
    calls a place a success it cannot judge); with neither, the default task's."""
    text = values.get(LABEL_TABLE_KEY)
    if text is not None:
        try:
            table = L.LabelTable.from_dict({"classes": json.loads(text)})
            return StatusOutcomes(table.outcome_names, table.failures)
        except ValueError:  # unreadable (LabelTableError is one too): fall back to the keys
            pass
    names = tuple(key.removesuffix(".present") for key in values if key.endswith(".present"))
    if names and set(names) <= set(L.DEFAULT_TABLE.outcome_names):
        return StatusOutcomes(names, tuple(n for n in names if n in L.DEFAULT_TABLE.failures))
    if names:  # another task's, without its table: nothing is known to be a success
        return StatusOutcomes(names, names)
    return StatusOutcomes(L.DEFAULT_TABLE.outcome_names, L.DEFAULT_TABLE.failures)


def present_message(present: dict[str, bool]) -> str:
    names = sorted(name for name, is_present in present.items() if is_present)
    return ",".join(names) if names else "none"


def _outcome_values(result: Any, intrinsics: Intrinsics | None, table: L.LabelTable,
                    ) -> tuple[list[tuple[str, str]], list[Centroid]]:
    values: list[tuple[str, str]] = []
    centroids: list[Centroid] = []
    for name in table.outcome_names:
        objects = result.objects.get(name, [])
        values += [(f"{name}.present", str(bool(result.present[name])).lower()),
                   (f"{name}.pixels", str(int(result.pixel_counts[name]))),
                   (f"{name}.objects", str(len(objects)))]
        if name not in table.failures:
            continue
        for k, obj in enumerate(objects):
            u, v = (float(c) for c in obj.centroid_px)
            values.append((f"{name}.{k}.centroid_px", f"{u:.1f},{v:.1f}"))
            z = obj.median_depth_m
            if intrinsics is not None and z is not None and math.isfinite(z) and z > 0:
                xyz = intrinsics.back_project(u, v, float(z))
                values.append((f"{name}.{k}.centroid_m", ",".join(f"{c:.3f}" for c in xyz)))
                centroids.append(Centroid(name, k, xyz))
    return values, centroids


def object_centroids(result: Any, intrinsics: Intrinsics | None,
                     table: L.LabelTable = L.DEFAULT_TABLE) -> list[Centroid]:
    """3-D centroids of the objects of ``table``'s failure modes (empty without intrinsics)."""
    return _outcome_values(result, intrinsics, table)[1]


def timing_values(inference_ms: float | None, dropped: int, latency_ms: float,
                  ) -> list[tuple[str, str]]:
    """inference_ms (when inference ran), dropped_frames and latency_ms (arrival -> status)."""
    values = [] if inference_ms is None else [("inference_ms", f"{float(inference_ms):.2f}")]
    return values + [("dropped_frames", str(int(dropped))),
                     ("latency_ms", f"{float(latency_ms):.2f}")]


def status_fields(result: Any, intrinsics: Intrinsics | None = None, *,
                  table: L.LabelTable = L.DEFAULT_TABLE, camera_note: str | None = None,
                  dropped: int = 0, latency_ms: float = 0.0) -> StatusFields:
    """Level, message and key/values of a processed frame (``result``: an OutcomeResult of a
    model whose label table is ``table``).

    Per outcome ``present``, ``pixels`` and ``objects``; per failure object its pixel centroid
    and, with ``intrinsics``, its optical-frame position; ``label_table`` (the classes, see
    ``label_table_value``); ``camera_note`` says why camera_info was not used; ``envelope``
    (``ok``, ``outside: <why>``, or unchecked for a checkpoint without a training envelope);
    then the timing values. WARN when a failure mode of ``table`` is present; outside the
    envelope the level is at least WARN and the message says so.
    """
    values, _ = _outcome_values(result, intrinsics, table)
    values.append((LABEL_TABLE_KEY, label_table_value(table)))
    if camera_note:
        values.append(("camera_info", camera_note))
    outside = list(getattr(result, "outside_envelope", []))
    values.append(("envelope", envelope_value(outside) if getattr(result, "envelope_checked",
                                                                   False) else UNCHECKED))
    if getattr(result, "support_plane", None):  # kept from an earlier frame, or fitted anew
        values.append(("support_plane", result.support_plane))
    values += timing_values(result.inference_ms, dropped, latency_ms)
    level = status_level(result.present, table.failures)
    message = present_message(result.present)
    if outside:  # never OK for a frame the model cannot judge (docs/interface.md §5)
        level = max(level, WARN)
        message = f"{message}; outside the trained envelope: {'; '.join(outside)}"
    return StatusFields(level, message, values)


def error_fields(why: str, *, dropped: int = 0, latency_ms: float = 0.0) -> StatusFields:
    """The ERROR status of a frame that could not be processed."""
    return StatusFields(ERROR, why, timing_values(None, dropped, latency_ms))
