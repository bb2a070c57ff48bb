"""The envelope a model was trained for, and whether one frame lies inside it.

A network trained on one cell says nothing useful about another: fed real totes, the default
model reported ``fell_outside`` everywhere, empty totes included. So every frame is checked,
cheaply, against what the checkpoint was trained on (docs/interface.md §5):

- the depth of the scene: the median valid depth must lie near the envelope's camera
  distances (``DEPTH_SLACK``: what the training renders themselves span, with a margin; for a
  task on a table, plus the drop to the room floor), and so must the median depth of the
  fixture's pixels (``FIXTURE_DEPTH_SLACK``);
- a support plane: enough of the frame must lie on the fitted floor (``MIN_SUPPORT_FRACTION``);
- the fixture: the network must see it in a part of the frame (``MIN_FIXTURE_FRACTION``);
- the camera: camera_info's focal length, scaled to the trained width, must lie in the
  trained range (``FOCAL_SLACK``).

The thresholds come from the training renders of the bundled specs, not from any evaluation
set: default (1.6-2.4 m) renders have median depths of 1.70-2.54 m and fixture fractions of
0.15 or more; tote (0.5-1.3 m) renders, on a table, 0.46-2.29 m and 0.027 or more.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from task_outcome_ros.camera import Intrinsics

# The frame's median valid depth within [lo x distance_min, hi x distance_max]: on a floor the
# renders span 0.93-1.3x the look-at distance (the far floor pulls the median beyond it), so
# the bounds hold the default renders (1.70-2.54 m in 1.44-3.0 m).
DEPTH_SLACK = (0.9, 1.25)
# With a task on a table the room floor past the table's edge pulls the frame's median deeper
# (tote renders: up to 2.1x the look-at distance, 2.29 m), so the upper bound adds the drop
# from the table top to the room floor. The fixture is what the camera distance is measured
# to: its median depth is 0.77-1.28x the look-at distance in the training renders (default
# 0.93-1.11, tote 0.85-1.28, shelf 0.77-1.06; 300-3,000 renders each), whatever else is in
# view, so it refuses what the frame's median alone lets through.
FIXTURE_DEPTH_SLACK = (0.7, 1.4)
MIN_VALID_FRACTION = 0.2     # of the frame's pixels
MIN_SUPPORT_FRACTION = 0.05  # of the valid working-size pixels within SUPPORT_BAND_M of it
SUPPORT_BAND_M = 0.01
FIXTURE_NOT_SEEN = "fixture not seen"  # the reason given when too few pixels are the fixture
MIN_FIXTURE_FRACTION = 0.01  # of the valid pixels labelled as the fixture
FOCAL_SLACK = 0.1            # +-10 % beyond the trained focal range


@dataclass(frozen=True)
class Envelope:
    """What a checkpoint was trained on (from its dataset config)."""

    task: str
    width: int
    height: int
    focal_px: tuple[float, float]       # fx at ``width``
    distance_m: tuple[float, float]     # camera to the fixture's centre
    support_drop_m: float = 0.0         # table top to room floor (0: the support is the floor)

    @classmethod
    def from_dataset_config(cls, dataset: dict[str, Any]) -> Envelope | None:
        """From the plain dataset config a checkpoint embeds (``train_config["dataset"]``);
        None when it has none (a hand-made checkpoint: nothing to check against)."""
        camera = (dataset or {}).get("camera")
        if not camera:
            return None
        scene = dataset.get("scene") or {}
        # A task on a table: the room floor lies up to the highest table top below it (the
        # spec's table_height is always a validated (min, max) pair).
        drop = max(scene["table_height"]) if scene.get("table_size") is not None else 0.0
        return cls(str(dataset.get("task", "default")), int(camera["width"]),
                   int(camera["height"]), tuple(float(v) for v in camera["focal_px"]),
                   tuple(float(v) for v in camera["distance"]), float(drop))

    def to_dict(self) -> dict:
        return asdict(self)

    def depth_range(self) -> tuple[float, float]:
        """Where the frame's median depth may lie."""
        return (self.distance_m[0] * DEPTH_SLACK[0],
                self.distance_m[1] * DEPTH_SLACK[1] + self.support_drop_m)

    def fixture_depth_range(self) -> tuple[float, float]:
        """Where the median depth of the fixture's pixels may lie."""
        return (self.distance_m[0] * FIXTURE_DEPTH_SLACK[0],
                self.distance_m[1] * FIXTURE_DEPTH_SLACK[1])

    def focal_range(self, width: int) -> tuple[float, float]:
        """The trained fx range for an image ``width`` px wide (with the slack)."""
        scale = width / self.width
        return (self.focal_px[0] * scale * (1 - FOCAL_SLACK),
                self.focal_px[1] * scale * (1 + FOCAL_SLACK))


@dataclass(frozen=True)
class FrameStats:
    """What the envelope check needs of one frame, computed while segmenting it."""

    valid_fraction: float
    median_depth_m: float | None
    support_fraction: float | None      # None: the model has no height channel
    fixture_fraction: float
    fixture_depth_m: float | None = None  # median depth of its pixels; None: not seen


def frame_stats(depth: np.ndarray, labels: np.ndarray, heights_m: np.ndarray | None,
                fixture_id: int) -> FrameStats:
    """``depth``: sanitised metres (NaN invalid); ``labels``: the segmentation, same size;
    ``heights_m``: working-size heights above the fitted floor (NaN where invalid)."""
    valid = np.isfinite(depth)
    n_valid = int(valid.sum())
    median = float(np.median(depth[valid])) if n_valid else None
    support = None
    if heights_m is not None:
        finite = np.isfinite(heights_m)
        support = (float(np.mean(np.abs(heights_m[finite]) < SUPPORT_BAND_M))
                   if finite.any() else 0.0)
    on_fixture = valid & (labels == fixture_id)
    n_fixture = int(np.count_nonzero(on_fixture))
    fixture = n_fixture / n_valid if n_valid else 0.0
    fixture_depth = (float(np.median(depth[on_fixture]))
                     if n_fixture and fixture >= MIN_FIXTURE_FRACTION else None)
    return FrameStats(n_valid / depth.size, median, support, fixture, fixture_depth)


def check(envelope: Envelope | None, stats: FrameStats,
          intrinsics: Intrinsics | None = None) -> list[str]:
    """Why the frame is outside the envelope (empty: inside)."""
    if envelope is None:
        return []
    why = []
    if stats.valid_fraction < MIN_VALID_FRACTION:
        why.append(f"only {stats.valid_fraction:.0%} of the pixels have depth")
    lo, hi = envelope.depth_range()
    if stats.median_depth_m is not None and not lo <= stats.median_depth_m <= hi:
        why.append(f"median depth {stats.median_depth_m:.2f} m, trained "
                   f"{envelope.distance_m[0]:g}-{envelope.distance_m[1]:g} m")
    if stats.support_fraction is not None and stats.support_fraction < MIN_SUPPORT_FRACTION:
        why.append("no support plane found")
    if stats.fixture_fraction < MIN_FIXTURE_FRACTION:
        why.append(FIXTURE_NOT_SEEN)
    flo, fhi = envelope.fixture_depth_range()
    if stats.fixture_depth_m is not None and not flo <= stats.fixture_depth_m <= fhi:
        why.append(f"fixture at {stats.fixture_depth_m:.2f} m, trained "
                   f"{envelope.distance_m[0]:g}-{envelope.distance_m[1]:g} m")
    if intrinsics is not None:
        flo, fhi = envelope.focal_range(intrinsics.width)
        if not flo <= intrinsics.fx <= fhi:
            scale = intrinsics.width / envelope.width
            why.append(f"fx {intrinsics.fx:.0f} px, trained {envelope.focal_px[0] * scale:.0f}"
                       f"-{envelope.focal_px[1] * scale:.0f} px at {intrinsics.width} px wide")
    return why


def envelope_value(why: list[str]) -> str:
    """The status's ``envelope`` value."""
    return "outside: " + "; ".join(why) if why else "ok"
