"""Scenery nobody placed: copies of the fixture standing beside it, with things in them.

Real cells put totes and bins in rows and racks, and the camera that watches one sees its
neighbours and what they hold. Each neighbour takes one of the fixture's four sides (so two
make a row or a corner), at the fixture's base height, on the table or past its edge. A
spec's ``neighbour_*`` fields (``SceneConfig``) draw that per frame, at render time, from the
episode's own "scenery" stream: the physics never sees it, so a neighbour is only drawn on a
side where no simulated object came to rest (one that fell there would have hit it). Every
solid here is background.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from training.config import SceneConfig
from training.fixture import PlacedFixture, euler_rotation

CLEARANCE_M = 0.02   # between a neighbour's footprint and any simulated object's reach
SIDES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0))   # (fixture axis, direction)


@dataclass(frozen=True)
class Solid:
    """A box in the world: half extents, centre and rotation (its axes in the world)."""

    half: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray


def draw_neighbours(fixture: PlacedFixture, scene: SceneConfig, objects: list[dict],
                    rng: np.random.Generator) -> tuple[list[Solid], dict | None]:
    """This frame's neighbours and their contents, and what was drawn (None: none).
    ``objects``: the episode's simulated objects (``position``, ``size``)."""
    if scene.neighbour_share <= 0 or rng.random() >= scene.neighbour_share:
        return [], None
    count = int(rng.integers(scene.neighbour_count[0], scene.neighbour_count[1] + 1))
    half = fixture.outer_half_footprint()
    local_objects, reach = object_reach(fixture, objects)
    solids, drawn = [], []
    for side in rng.permutation(len(SIDES))[:count]:
        axis, direction = SIDES[side]
        gap = float(rng.uniform(*scene.neighbour_gap))
        offset = np.zeros(2)
        offset[axis] = direction * (2 * half[axis] + gap)
        offset[1 - axis] = float(rng.uniform(-0.1, 0.1)) * half[1 - axis]
        contents = int(rng.integers(scene.neighbour_contents[0],
                                    scene.neighbour_contents[1] + 1))
        boxes = _contents(fixture, scene, contents, rng)   # drawn even if skipped: same stream
        if np.any(np.all(np.abs(local_objects - offset) <= half + reach[:, None], axis=1)):
            continue   # a simulated object lies where this neighbour would stand
        solids += _neighbour_solids(fixture, offset, boxes)
        drawn.append({"offset": [round(float(v), 4) for v in offset], "contents": contents})
    return solids, ({"neighbours": drawn} if drawn else None)


def object_reach(fixture: PlacedFixture, objects: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Each object's centre in the fixture's frame (x, y) and how far its body may reach from
    it (half its bounding box's diagonal), plus the clearance."""
    if not objects:
        return np.zeros((0, 2)), np.zeros(0)
    centres = fixture.to_frame(np.array([o["position"] for o in objects], float))[:, :2]
    reach = np.array([np.linalg.norm(o["size"]) / 2 for o in objects]) + CLEARANCE_M
    return centres, reach


def _contents(fixture: PlacedFixture, scene: SceneConfig, n: int,
              rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """n boxes resting on the target region's bottom, in the fixture's frame: (half extents,
    centre, yaw). They may overlap one another, which reads as a pile."""
    region = fixture.region()
    inner = region.half_at(region.bottom)
    boxes = []
    for _ in range(n):
        half = rng.uniform(*scene.object_edge, size=3) / 2
        half[:2] = np.minimum(half[:2], 0.45 * inner)
        yaw = float(rng.uniform(0.0, math.pi))
        room = np.maximum(inner - np.hypot(half[0], half[1]), 0.0)
        xy = rng.uniform(-room, room)
        boxes.append((half, np.array([xy[0], xy[1], region.bottom + half[2]]), yaw))
    return boxes


def _neighbour_solids(fixture: PlacedFixture, offset: np.ndarray,
                      boxes: list[tuple[np.ndarray, np.ndarray, float]]) -> list[Solid]:
    """The fixture's solids and the contents, moved by ``offset`` in its frame, in the world."""
    shift = np.array([offset[0], offset[1], 0.0])
    rotation = fixture.rotation
    solids = [Solid(np.array(half, float), fixture.to_world(np.array(centre) + shift),
                    rotation @ euler_rotation(turn))
              for half, centre, turn in fixture.solid_boxes()]
    for half, centre, yaw in boxes:
        c, s = math.cos(yaw), math.sin(yaw)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        solids.append(Solid(half, fixture.to_world(centre + shift), rotation @ turn))
    return solids
