"""Each frame's objects cast again with ids of their own: which frames show two objects
touching in the image, whatever their outcomes, and each object pixel's distance to anything
that is not the same object.

Why: drawing the frames where two *outcomes* touch more often (``--touching-outcomes-weight``)
fixed two default images where a success box meets a stuck one and broke two stacks of success
boxes, as if it moved the network's prior for boxes on boxes (docs/experiments.md). The labels
cannot tell two touching objects of one outcome apart, so this module casts each frame's
objects again, each with an id of its own, at the working size: a frame counts when two
objects' pixels are 4-neighbours (one resting on, leaning on or seen in front of the other).
The cast uses the stored simulation, outcomes and camera, so it needs no re-render; the
scenery drawn per frame (neighbouring totes) is left out. Drawn 3x on the default task, these
frames did not get the stacked boxes right either. ``object_distance`` turns the id images
into the training-only target of ``--object-distance-weight`` (``losses.ObjectDistanceHead``),
which did not get them right either (docs/experiments.md).
"""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from task_outcome_ros.checkpoint import atomic_write_bytes
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
            + [replace(b, label=FIRST_OBJECT_ID + k)
               for k, b in enumerate(boxes[len(boxes) - n:])])   # not [-n:]: n may be 0
    _, ids, _ = render(ided, episode_fixture(episode, scene).room_floor_z, camera)
    return ids


def objects_touch(ids: np.ndarray) -> bool:
    """True when two different objects' pixels are 4-neighbours in an id image."""
    for a, b in ((ids[1:, :], ids[:-1, :]), (ids[:, 1:], ids[:, :-1])):
        if np.any((a >= FIRST_OBJECT_ID) & (b >= FIRST_OBJECT_ID) & (a != b)):
            return True
    return False


def cast_object_ids(data_dir: Path, manifest: dict, episodes: np.ndarray,
                    size: tuple[int, int], min_objects: int = 1):
    """Yields (k, id image) for the k-th episode of ``episodes`` (a run's image indices) with
    at least ``min_objects`` objects: its frame cast at ``size`` with the camera of the run's
    ``manifest`` (``load_manifest``, which the trainer has loaded already). Raises ValueError
    when the run lacks its simulation results."""
    wanted = {int(e) for e in episodes}
    run = run_episodes(data_dir, wanted)
    if run is None:
        raise ValueError(f"{data_dir}: casting the objects again needs the run's simulate/ "
                         "results and manifest")
    cameras = {im["episode"]: im["camera"] for im in manifest["images"]}
    outcomes, table = load_outcomes(data_dir)
    by_index = {int(e["episode"]): e for e in run.episodes}
    for k, index in enumerate(int(e) for e in episodes):
        episode = by_index[index]
        if len(episode["objects"]) >= min_objects:
            yield k, object_id_image(episode, outcomes[index], run.cfg.scene, table,
                                     working_camera(cameras[index], size))


def frames_with_touching_objects(data_dir: Path, manifest: dict, episodes: np.ndarray,
                                 size: tuple[int, int]) -> np.ndarray:
    """(N,) bool per episode of ``episodes``: two objects touch in its frame cast at ``size``
    (``cast_object_ids``)."""
    touching = np.zeros(len(episodes), bool)
    for k, ids in cast_object_ids(data_dir, manifest, episodes, size, min_objects=2):
        touching[k] = objects_touch(ids)
    return touching


# Object distances are kept up to this many working pixels: a 160 x 120 box seen from 2 m is
# 10-20 pixels across, so 6 reaches its middle, and what separates two stacked boxes is the
# dip to 1 along their seam.
OBJECT_DISTANCE_CLIP_PX = 6


def object_distance(ids: np.ndarray, clip_px: int = OBJECT_DISTANCE_CLIP_PX) -> np.ndarray:
    """(H, W) uint8: for each object pixel of an id image, its distance in pixels (1 on its
    outline; OpenCV's 3 x 3 mask, so diagonals are approximated, rounded) to the nearest pixel
    that is not the same object, clipped at ``clip_px``; 0 off the objects. Where two objects
    meet, both sides of the seam read 1, as against a background: the per-object shape a
    semantic label cannot give (two touching boxes of one outcome are one region of labels)."""
    out = np.zeros(ids.shape, np.uint8)
    for object_id in np.unique(ids[ids >= FIRST_OBJECT_ID]):
        inside = ids == object_id
        # Padded with "this object", so an object cut by the frame's edge is not measured
        # from it.
        padded = np.pad(inside, 1, constant_values=True).astype(np.uint8)
        dist = cv2.distanceTransform(padded, cv2.DIST_L2, 3)
        out[inside] = np.minimum(np.rint(dist[1:-1, 1:-1][inside]), clip_px)
    return out


def object_distance_images(data_dir: Path, manifest: dict, episodes: np.ndarray,
                           size: tuple[int, int]) -> np.ndarray:
    """(N, h, w) uint8 ``object_distance`` of each episode's frame cast at ``size`` (w, h)."""
    w, h = size
    out = np.zeros((len(episodes), h, w), np.uint8)
    for k, ids in cast_object_ids(data_dir, manifest, episodes, size):
        out[k] = object_distance(ids)
    return out


def object_distance_cache(run_dir: Path, manifest: dict, indices: np.ndarray, split: str,
                          size: tuple[int, int]) -> np.ndarray:
    """``object_distance_images`` of a split's images ``indices`` (the working-size cache's),
    kept in a file of its own beside that cache (under a minute for 19,000 default frames,
    made once, written atomically through a temporary file of its own, since runs made with
    ``--dataset-from`` share the cache folder); a file of other images, another size or
    another clip is refused."""
    path = Path(run_dir) / "cache" / f"{split}_{size[0]}x{size[1]}_object_distance.npz"
    if not path.exists():
        print(f"train: casting the {len(indices)} {split} frames' objects again for their "
              f"distances ({path.name})")
        distance = object_distance_images(Path(run_dir), manifest, indices, size)
        buffer = io.BytesIO()
        np.savez_compressed(buffer, indices=np.asarray(indices), object_distance=distance,
                            clip_px=OBJECT_DISTANCE_CLIP_PX)
        atomic_write_bytes(path, buffer.getvalue())
    with np.load(path) as data:
        stored = data["object_distance"]
        clip_px = int(data["clip_px"]) if "clip_px" in data.files else None  # older files
        if (not np.array_equal(data["indices"], indices)
                or stored.shape != (len(indices), size[1], size[0])
                or clip_px != OBJECT_DISTANCE_CLIP_PX):
            raise ValueError(f"{path} holds other images, another size or another clip than "
                             f"the {split} cache needs; delete it to rebuild it")
        return stored
