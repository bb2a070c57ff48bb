"""Why an image is hard: geometric tags from the simulated final states, for the evaluation.

The outcome of an object is decided by geometry the depth camera sees only through its noise
(docs/interface.md §2): a box whose top is 3 mm above the rim is stuck_on_rim, 3 mm below it is a
success. At 1.6-2.4 m the Kinect-like sensor's depth noise is about 3-8 mm per pixel and its
depth steps (1/8 px of disparity) 8-17 mm (training/noise.py), so those images sit at the
limit of what the sensor can tell, whatever the network. Evaluation
tags each image with the reasons below and reports the mistakes per reason and the score on
images that have none of them, so a figure can be read against what the sensor can tell.

Tags (an image may have several):

- ``near_rim``: an object whose centre of mass is within the container's outer footprint has
  its highest corner within ``NEAR_RIM_M`` of the rim top (success vs stuck_on_rim);
- ``across_wall``: an object lies partly over the container's footprint and partly beyond
  it, i.e. across the wall (fell_outside vs stuck_on_rim: which cluster such a box joins is
  where discovery and the geometric rule of docs/interface.md §2 disagree).

Besides the tags, each image gets its *rim gap*: the smallest |top - rim| over the objects
above the container's footprint (None without one). Evaluation reports all-correct per
``RIM_GAP_BINS_MM`` bin, which shows how fast the task gets easier away from the rim.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from training.chunks import load_chunks
from training.config import dataset_config_from_dict, load_json
from training.geometry import object_measurements

NEAR_RIM_M = 0.02
TAGS = ("near_rim", "across_wall")
# Lower edges of the rim-gap bins (mm); the last bin is open and also holds images with no
# object above the container.
RIM_GAP_BINS_MM = (0.0, 2.0, 5.0, 10.0, 20.0)


@dataclass(frozen=True)
class HardCase:
    """What makes one image hard: its tags and its rim gap (m; None: nothing over the box)."""

    tags: tuple[str, ...]
    rim_gap_m: float | None


def object_tags(m: dict[str, float]) -> set[str]:
    """Tags of one object from its ``geometry.object_measurements``."""
    tags = set()
    gap = object_rim_gap(m)
    if gap is not None and gap < NEAR_RIM_M:
        tags.add("near_rim")
    if 0.0 < m["over_fraction"] < 1.0:
        tags.add("across_wall")
    return tags


def object_rim_gap(m: dict[str, float]) -> float | None:
    """|top - rim| (m) of an object whose centre of mass is over the container, else None."""
    return None if m["com_beyond_outer"] else abs(m["top_above_rim"])


def rim_gap_bin(gap_m: float | None) -> int:
    """Index into ``RIM_GAP_BINS_MM`` of an image's rim gap (None: the last, open bin)."""
    if gap_m is None:
        return len(RIM_GAP_BINS_MM) - 1
    return max(i for i, lo in enumerate(RIM_GAP_BINS_MM) if gap_m * 1000.0 >= lo)


def rim_gap_bin_names() -> list[str]:
    edges = [f"{lo:g}" for lo in RIM_GAP_BINS_MM]
    return [f"{a}-{b} mm" for a, b in zip(edges, edges[1:])] + [f">= {edges[-1]} mm"]


def episode_hard_cases(data_dir: Path, wanted: set[int]) -> dict[int, HardCase] | None:
    """Episode -> HardCase for the ``wanted`` episodes of the dataset run in ``data_dir``;
    None when the run has no simulation results to read (then there is no breakdown)."""
    data_dir = Path(data_dir)
    manifest_path = data_dir / "manifest.json"
    if not (data_dir / "simulate").is_dir() or not manifest_path.is_file():
        return None
    cfg = dataset_config_from_dict(load_json(manifest_path)["config"])
    scene = cfg.scene
    try:
        episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    except (FileNotFoundError, ValueError):
        return None
    cases = {}
    for episode in episodes:
        if int(episode["episode"]) not in wanted:
            continue
        found: set[str] = set()
        gaps = []
        for obj in episode["objects"]:
            m = object_measurements(obj, episode, scene)
            found |= object_tags(m)
            if (gap := object_rim_gap(m)) is not None:
                gaps.append(gap)
        cases[int(episode["episode"])] = HardCase(tuple(sorted(found)),
                                                  min(gaps) if gaps else None)
    return cases
