"""Presence recall by where an outcome's objects came to rest: on the support, or beneath it.

Why: in a task whose fixture stands on a table, an object that falls may stay on the table
top or drop to the room floor, and the two look nothing alike to the camera. Tote model
0.15.0 found 16 of the 23 validation images whose small fallen objects (under 800 px) all lay
on the table, but 14 of the 31 whose all lay on the room floor, where the local relief
reads an object beside the table's edge as part of a surface (docs/evaluation.md, "Where
its small fallen objects lie"). One recall per outcome, or per size, hides that.

Each image's outcome gets a place from its objects' final centres of mass (the simulation's
own frame, z normal to the support): beneath the support when lower than halfway between
the table top and the room floor, else on it; "both" when its objects lie on both. All of
the outcome's objects count, seen or not: a fallen object out of view on the room floor
makes an image whose visible one lies on the table "both". Tasks without a table have one
place, so they get no breakdown. Within a place, recall is binned by size as in
size_recall.py.
"""

from __future__ import annotations

from pathlib import Path

from training.discover import load_outcomes
from training.fixture import Table, episode_fixture
from training.hard_cases import RunEpisodes
from training.size_recall import recall_by_size

ON_SUPPORT, BENEATH_SUPPORT, BOTH = "on the support", "beneath the support", "both"
PLACES = (ON_SUPPORT, BENEATH_SUPPORT, BOTH)


def object_place(position, table: Table) -> str:
    """Where an object whose centre of mass is at ``position`` rests, by its height."""
    return BENEATH_SUPPORT if position[2] < (table.top_z + table.floor_z) / 2 else ON_SUPPORT


def place_of(object_places: set[str]) -> str:
    """One outcome's place in an image, from the places of its objects."""
    return next(iter(object_places)) if len(object_places) == 1 else BOTH


def places_of(run: RunEpisodes | None, data_dir: Path) -> dict[int, dict[str, str]] | None:
    """Episode -> {outcome: place} for the episodes of ``run`` (the dataset run in
    ``data_dir``, whose outcomes.json names each object's outcome); None without a run, its
    outcomes, or a table in its task."""
    if run is None or run.cfg.scene.table_size is None \
            or not (Path(data_dir) / "outcomes.json").is_file():
        return None
    outcomes, _ = load_outcomes(data_dir)
    by_episode = {}
    for episode in run.episodes:
        e = int(episode["episode"])
        table = episode_fixture(episode, run.cfg.scene).table
        if len(episode["objects"]) != len(outcomes[e]):
            raise ValueError(f"{data_dir}: episode {e} has {len(episode['objects'])} objects "
                             f"in simulate/ but {len(outcomes[e])} in outcomes.json; run "
                             "discover again")
        object_places: dict[str, set[str]] = {}
        for obj, outcome in zip(episode["objects"], outcomes[e]):
            object_places.setdefault(outcome, set()).add(object_place(obj["position"], table))
        by_episode[e] = {outcome: place_of(found) for outcome, found in object_places.items()}
    return by_episode


def recall_by_place(rows: list[dict], episode_places: dict[int, dict[str, str]] | None,
                    outcome_names: list[str], height: int, width: int) -> dict:
    """Per outcome and place: presence recall by size (size_recall.recall_by_size) over the
    images where the outcome is truly present and its objects rest there. Empty without
    places."""
    if episode_places is None:
        return {}
    by_outcome = {}
    for outcome in outcome_names:
        by_outcome[outcome] = {}
        for place in PLACES:
            subset = [r for r in rows if episode_places[r["episode"]].get(outcome) == place]
            bins = recall_by_size(subset, [outcome], height, width)["by_outcome"][outcome]
            by_outcome[outcome][place] = bins
    return {"recall_by_place": {"places": list(PLACES), "by_outcome": by_outcome}}
