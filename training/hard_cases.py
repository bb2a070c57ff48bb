"""Why an image is hard: geometric tags from the simulated final states, for the evaluation.

The outcome of an object is decided by geometry the depth camera sees only through its noise
(docs/interface.md §2): in the default task a box whose top is 3 mm above the rim is
stuck_on_rim, 3 mm below it a success; on a shelf, a box overhanging the board's edge by 3 mm
is hanging over it, 3 mm short of it on the shelf. At 1.6-2.4 m the Kinect-like sensor's
depth noise is about 3-8 mm per pixel and its depth steps (1/8 px of disparity) 8-17 mm
(training/noise.py), so those images sit at the limit of what the sensor can tell, whatever
the network. Evaluation tags each image with the reasons below and reports the mistakes per
reason and the score on images that have none of them, so a figure can be read against what
the sensor can tell.

Which boundary separates "inside" from "partly inside" is the task's own, the one its
geometric yardstick uses (``discover.yardstick_inside``): the region's top for an open box
(its walls hold the sides), the footprint's edge for a board. An object's *boundary gap* is
its distance from that boundary: |top - region top|, or |how far it reaches beyond the
footprint|.

Tags (an image may have several):

- ``near_boundary``: an object whose centre of mass is within the fixture's outer footprint
  is within ``NEAR_BOUNDARY_M`` of the boundary (inside vs partly inside);
- ``across_edge``: an object lies partly over the fixture's outer footprint and partly beyond
  it, i.e. across its edge (outside vs partly inside: which cluster such an object joins is
  where discovery and the geometric rule of docs/interface.md §2 disagree).

Besides the tags, each image gets its *boundary gap*: the smallest gap over its objects
within the outer footprint (None without one). Evaluation reports all-correct per
``GAP_BINS_MM`` bin, which shows how fast the task gets easier away from the boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from training.chunks import load_chunks
from training.config import DatasetConfig, dataset_config_from_dict, load_json
from training.geometry import object_measurements

NEAR_BOUNDARY_M = 0.02
TAGS = ("near_boundary", "across_edge")
# Lower edges of the boundary-gap bins (mm); the last bin is open and also holds images with
# no object over the fixture.
GAP_BINS_MM = (0.0, 2.0, 5.0, 10.0, 20.0)


@dataclass(frozen=True)
class HardCase:
    """What makes one image hard: its tags and its boundary gap (m; None: nothing over the
    fixture)."""

    tags: tuple[str, ...]
    gap_m: float | None


def object_tags(m: dict[str, float], inside_rule: str = "top") -> set[str]:
    """Tags of one object from its ``geometry.object_measurements``."""
    tags = set()
    gap = object_gap(m, inside_rule)
    if gap is not None and gap < NEAR_BOUNDARY_M:
        tags.add("near_boundary")
    if 0.0 < m["over_fraction"] < 1.0:
        tags.add("across_edge")
    return tags


def object_gap(m: dict[str, float], inside_rule: str = "top") -> float | None:
    """The boundary gap (m) of an object whose centre of mass is within the outer footprint,
    else None: |top - region top| (rule "top") or |reach beyond the footprint| ("footprint")."""
    if m["com_beyond_outer"]:
        return None
    return abs(m["top_above_region"] if inside_rule == "top" else m["reach_beyond_footprint"])


def gap_bin(gap_m: float | None) -> int:
    """Index into ``GAP_BINS_MM`` of an image's boundary gap (None: the last, open bin)."""
    if gap_m is None:
        return len(GAP_BINS_MM) - 1
    return max(i for i, lo in enumerate(GAP_BINS_MM) if gap_m * 1000.0 >= lo)


def gap_bin_names() -> list[str]:
    edges = [f"{lo:g}" for lo in GAP_BINS_MM]
    return [f"{a}-{b} mm" for a, b in zip(edges, edges[1:])] + [f">= {edges[-1]} mm"]


@dataclass(frozen=True)
class RunEpisodes:
    """The simulated final states of some of a dataset run's episodes, with the run's config:
    what the evaluation's breakdowns read (hard cases here, places in rest_place.py)."""

    cfg: DatasetConfig
    episodes: list[dict]


def run_episodes(data_dir: Path, wanted: set[int]) -> RunEpisodes | None:
    """The ``wanted`` episodes of the dataset run in ``data_dir``; None when the run has no
    simulation results to read (then there is no breakdown)."""
    data_dir = Path(data_dir)
    manifest_path = data_dir / "manifest.json"
    if not (data_dir / "simulate").is_dir() or not manifest_path.is_file():
        return None
    cfg = dataset_config_from_dict(load_json(manifest_path)["config"])
    try:
        episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    except (FileNotFoundError, ValueError):
        return None
    return RunEpisodes(cfg, [e for e in episodes if int(e["episode"]) in wanted])


def hard_cases_of(run: RunEpisodes | None) -> dict[int, HardCase] | None:
    """Episode -> HardCase for the episodes of ``run`` (None: no breakdown)."""
    if run is None:
        return None
    scene, rule = run.cfg.scene, run.cfg.discover.yardstick_inside
    cases = {}
    for episode in run.episodes:
        tags: set[str] = set()
        gaps = []
        for obj in episode["objects"]:
            m = object_measurements(obj, episode, scene)
            tags |= object_tags(m, rule)
            if (gap := object_gap(m, rule)) is not None:
                gaps.append(gap)
        cases[int(episode["episode"])] = HardCase(tuple(sorted(tags)),
                                                  min(gaps) if gaps else None)
    return cases


def episode_hard_cases(data_dir: Path, wanted: set[int]) -> dict[int, HardCase] | None:
    """Episode -> HardCase for the ``wanted`` episodes of the dataset run in ``data_dir``;
    None when the run has no simulation results to read (then there is no breakdown)."""
    return hard_cases_of(run_episodes(data_dir, wanted))
