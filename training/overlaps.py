"""Which frames show two objects touching in the image, whatever their outcomes.

Why: drawing the frames where two *outcomes* touch more often (``--touching-outcomes-weight``)
fixed two default images where a success box meets a stuck one and broke two stacks of success
boxes, as if it moved the network's prior for boxes on boxes (docs/experiments.md). The labels
cannot tell two touching objects of one outcome apart, so this module casts each frame's
objects again, each with an id of its own, at the working size: a frame counts when two
objects' pixels are 4-neighbours (one resting on, leaning on or seen in front of the other).
The cast uses the stored simulation, outcomes and camera, so it needs no re-render; the
scenery drawn per frame (neighbouring totes) is left out. Drawn 3x on the default task, these
frames did not get the stacked boxes right either; the id images are also what an
object-boundary target would need.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from task_outcome_ros.labels import BACKGROUND
from training.discover import load_outcomes
from training.fixture import episode_fixture
from training.hard_cases import run_episodes
from training.render import Camera, render, scene_boxes

FIRST_OBJECT_ID = 1  # object k of a frame gets id 1 + k in the id image; 0 is everything else


def working_camera(record: dict, size: tuple[int, int]) -> Camera:
    """The frame's camera (a manifest's ``camera`` record) for an image of ``size`` (w, h):
    the same pose and field of view, pixel centres mapped as an area resize maps them."""
    w, h = size
    sx, sy = w / record["width"], h / record["height"]
    return Camera(width=w, height=h, fx=record["fx"] * sx, fy=record["fy"] * sy,
                  cx=(record["cx"] + 0.5) * sx - 0.5, cy=(record["cy"] + 0.5) * sy - 0.5,
                  position=np.asarray(record["position"], float),
                  rotation=np.asarray(record["rotation"], float))


def object_id_image(episode: dict, outcomes: list[str], scene, table, camera: Camera
                    ) -> np.ndarray:
    """(H, W) uint8: ``FIRST_OBJECT_ID + k`` where object k of the episode is the nearest
    surface, 0 elsewhere (the fixture, a table and the floor occlude but carry no id)."""
    boxes = scene_boxes(episode, outcomes, scene, table)
    n = len(episode["objects"])  # scene_boxes lists the objects last
    ided = ([replace(b, label=BACKGROUND) for b in boxes[:len(boxes) - n]]
            + [replace(b, label=FIRST_OBJECT_ID + k) for k, b in enumerate(boxes[-n:])])
    _, ids, _ = render(ided, episode_fixture(episode, scene).room_floor_z, camera)
    return ids


def objects_touch(ids: np.ndarray) -> bool:
    """True when two different objects' pixels are 4-neighbours in an id image."""
    for a, b in ((ids[1:, :], ids[:-1, :]), (ids[:, 1:], ids[:, :-1])):
        if np.any((a >= FIRST_OBJECT_ID) & (b >= FIRST_OBJECT_ID) & (a != b)):
            return True
    return False


def frames_with_touching_objects(data_dir: Path, manifest: dict, episodes: np.ndarray,
                                 size: tuple[int, int]) -> np.ndarray:
    """(N,) bool per episode of ``episodes`` (a run's image indices): two objects touch in its
    frame cast at ``size`` with the camera of the run's ``manifest`` (``load_manifest``, which
    the trainer has loaded already). Raises ValueError when the run lacks its simulation
    results."""
    wanted = {int(e) for e in episodes}
    run = run_episodes(data_dir, wanted)
    if run is None:
        raise ValueError(f"{data_dir}: finding touching objects needs the run's simulate/ "
                         "results and manifest")
    cameras = {im["episode"]: im["camera"] for im in manifest["images"]}
    outcomes, table = load_outcomes(data_dir)
    by_index = {int(e["episode"]): e for e in run.episodes}
    touching = np.zeros(len(episodes), bool)
    for k, index in enumerate(int(e) for e in episodes):
        episode = by_index[index]
        if len(episode["objects"]) < 2:
            continue
        ids = object_id_image(episode, outcomes[index], run.cfg.scene, table,
                              working_camera(cameras[index], size))
        touching[k] = objects_touch(ids)
    return touching
