"""Presence recall by where an outcome's objects came to rest: on the support, or beneath it.

Why: in a task whose fixture stands on a table, an object that falls may stay on the table
top or drop to the room floor, and the two look nothing alike to the camera. Tote model
0.15.0 found 16 of the 23 validation images whose small fallen objects (under 800 px) all lay
on the table, but 14 of the 31 whose all lay on the room floor, where the local relief
reads an object beside the table's edge as part of a surface (docs/evaluation.md, "Where
its small fallen objects lie"). One recall per outcome, or per size, hides that.

Each image's outcome gets a place from its objects' final centres of mass (the simulation's
own frame, z normal to the support): beneath the support when lower than halfway between
the table top and the room floor, else on it; "both" when its objects lie on both. Tasks
without a table have one place, so they get no breakdown. Within a place, recall is
binned by size as in size_recall.py.
"""

from __future__ import annotations

from pathlib import Path

from training.chunks import load_chunks
from training.config import dataset_config_from_dict, load_json
from training.discover import load_outcomes
from training.fixture import Table, episode_fixture
from training.size_recall import recall_by_size

ON_SUPPORT, BENEATH_SUPPORT, BOTH = "on the support", "beneath the support", "both"
PLACES = (ON_SUPPORT, BENEATH_SUPPORT, BOTH)


def object_place(position, table: Table) -> str:
    """Where an object whose centre of mass is at ``position`` rests, by its height."""
    return BENEATH_SUPPORT if position[2] < (table.top_z + table.floor_z) / 2 else ON_SUPPORT


def place_of(places: set[str]) -> str:
    """One outcome's place in an image, from its objects' places."""
    return places.pop() if len(places) == 1 else BOTH


def episode_places(data_dir: Path, wanted: set[int]) -> dict[int, dict[str, str]] | None:
    """Episode -> {outcome: place} for the ``wanted`` episodes of the dataset run in
    ``data_dir``; None when the run has no simulation or outcomes to read, or its task
    stands on no table."""
    data_dir = Path(data_dir)
    manifest_path = data_dir / "manifest.json"
    if not (data_dir / "simulate").is_dir() or not (data_dir / "outcomes.json").is_file() \
            or not manifest_path.is_file():
        return None
    cfg = dataset_config_from_dict(load_json(manifest_path)["config"])
    if cfg.scene.table_size is None:
        return None
    try:
        episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    except (FileNotFoundError, ValueError):
        return None
    outcomes, _ = load_outcomes(data_dir)
    found = {}
    for episode in episodes:
        e = int(episode["episode"])
        if e not in wanted:
            continue
        table = episode_fixture(episode, cfg.scene).table
        by_outcome: dict[str, set[str]] = {}
        for obj, outcome in zip(episode["objects"], outcomes[e]):
            by_outcome.setdefault(outcome, set()).add(object_place(obj["position"], table))
        found[e] = {outcome: place_of(places) for outcome, places in by_outcome.items()}
    return found


def recall_by_place(rows: list[dict], places: dict[int, dict[str, str]] | None,
                    outcome_names: list[str], height: int, width: int) -> dict:
    """Per outcome and place: presence recall by size (size_recall.recall_by_size) over the
    images where the outcome is truly present and its objects rest there. Empty without
    places."""
    if places is None:
        return {}
    table = {}
    for outcome in outcome_names:
        table[outcome] = {}
        for place in PLACES:
            subset = [r for r in rows if places[r["episode"]].get(outcome) == place]
            report = recall_by_size(subset, [outcome], height, width)
            table[outcome][place] = report["by_outcome"][outcome]
    return {"recall_by_place": {"places": list(PLACES), "by_outcome": table}}
