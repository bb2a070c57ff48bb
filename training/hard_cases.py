"""Why an image is hard: geometric tags from the simulated final states, for the evaluation.

The outcome of an object is decided by geometry the depth camera sees only through its noise
(CONTRACTS §2): a box whose top is 3 mm above the rim is stuck_on_rim, 3 mm below it is a
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
  where discovery and the geometric rule of CONTRACTS §2 disagree).
"""

from __future__ import annotations

from pathlib import Path

from training.chunks import load_chunks
from training.config import dataset_config_from_dict, load_json
from training.geometry import object_measurements, outer_footprint_ratio

NEAR_RIM_M = 0.02
TAGS = ("near_rim", "across_wall")


def object_tags(m: dict[str, float], outer_ratio: float) -> set[str]:
    """Tags of one object from its ``geometry.object_measurements``."""
    tags = set()
    if m["com_offset"] < outer_ratio and abs(m["top_above_rim"]) < NEAR_RIM_M:
        tags.add("near_rim")
    if 0.0 < m["over_fraction"] < 1.0:
        tags.add("across_wall")
    return tags


def episode_tags(data_dir: Path, wanted: set[int]) -> dict[int, list[str]] | None:
    """Episode -> sorted tags, for the ``wanted`` episodes of the dataset run in ``data_dir``;
    None when the run has no simulation results to read (then there is no breakdown)."""
    data_dir = Path(data_dir)
    manifest_path = data_dir / "manifest.json"
    if not (data_dir / "simulate").is_dir() or not manifest_path.is_file():
        return None
    cfg = dataset_config_from_dict(load_json(manifest_path)["config"])
    scene = cfg.scene
    outer_ratio = outer_footprint_ratio(scene)
    try:
        episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    except (FileNotFoundError, ValueError):
        return None
    tags = {}
    for episode in episodes:
        if int(episode["episode"]) not in wanted:
            continue
        found: set[str] = set()
        for obj in episode["objects"]:
            found |= object_tags(object_measurements(obj, episode, scene), outer_ratio)
        tags[int(episode["episode"])] = sorted(found)
    return tags
