"""Explicit randomness: every draw comes from a Generator seeded by (run seed, episode, stage).

Seeding per episode (not per worker) makes results independent of the worker count and of
the order chunks run in, which is what makes resumed runs byte-identical.
"""

from __future__ import annotations

import numpy as np

# One stream per stage, so changing e.g. the renderer never changes the physics draws.
# "fixture" holds the per-episode draws a spec added (footprint, wall height, table, shapes),
# "sensor" the per-frame sensor parameters, "sensor_model" which sensor model a frame gets,
# "camera_info" the calibration error of what the camera reports: streams of their own, so
# a spec with fixed values draws exactly what it drew before; "scenery" what stands around
# the fixture that nobody placed; "lost_depth" where the robustness suite's frames lose
# their depth (holes.lose_depth); "empty" whether an episode places nothing; "islands"
# where the robustness suite's frames get outlier islands (islands.add_islands);
# "empty_cell" whether a frame is rendered with no fixture and no object (render.drawn_empty).
STAGE_STREAMS = {"simulate": 1, "render": 2, "noise": 3, "split": 4, "augment": 5,
                 "fixture": 6, "sensor": 7, "robustness": 8, "sensor_model": 9,
                 "camera_info": 10, "scenery": 11, "lost_depth": 12, "empty": 13,
                 "islands": 14, "empty_cell": 15}


def episode_seed(run_seed: int, episode: int, stage: str) -> list[int]:
    """The entropy list recorded in the manifest; np.random.default_rng(it) reproduces draws."""
    return [int(run_seed), int(episode), STAGE_STREAMS[stage]]


def episode_rng(run_seed: int, episode: int, stage: str) -> np.random.Generator:
    return np.random.default_rng(episode_seed(run_seed, episode, stage))


def drawn_in_share(share: float, run_seed: int, episode: int, stage: str) -> bool:
    """Whether ``episode`` falls in a spec's ``share`` of the episodes, from stream ``stage``
    of its own, drawn only when the share is above 0: a spec without it draws nothing more."""
    return share > 0 and bool(episode_rng(run_seed, episode, stage).random() < share)
