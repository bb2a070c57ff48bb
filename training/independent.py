"""``python -m training independent``: an evaluation set the training pipeline never touches.

It takes the simulated final states and discovered outcomes of a dataset run (the physics
and the task's own outcome definition) and makes every image another way:

- **Rendering**: pybullet's own ``rayTestBatch`` against collision shapes built here from the
  episode records, instead of the analytic caster of ``render.py``; labels from the body each
  ray hits, the incidence angle from pybullet's hit normal.
- **Cameras** drawn here, a little beyond the spec's envelope: 5 % nearer and farther,
  3 degrees lower and higher, roll up to +-10 degrees, the support tilted up to 4 degrees
  (as a rotation of the camera about the fixture), the look-at point 20 % farther off.
- **Noise** written separately from ``noise.py`` and ``tof.py``, after Nguyen, Izadi & Lovell
  (2012): Gaussian axial noise 0.0012 + 0.0019 (z - 0.4)^2 m times a per-image factor of
  0.7-1.6, depth quantised to Kinect steps of 2.85e-3 z^2 m, a fixed-width shadow band left
  of every foreground edge, dropout near depth edges and at grazing angles, elliptic holes,
  a per-image depth scale error and range limits. camera_info is off by up to 2 % in focal
  length.

Images go into ``--out`` in the dataset's on-disk format (``images/``, ``manifest.json`` with
every image in the ``val`` split), so ``python -m training evaluate --data OUT`` scores it.
Every draw comes from a generator seeded by (seed, episode, 77), recorded in the manifest;
images are made in resumable chunks by ``--workers`` processes.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np

from task_outcome_ros.labels import (
    BACKGROUND,
    IGNORE,
    LabelTable,
    outcome_pixel_counts,
    outcomes_present,
)
from training.chunks import load_chunks, run_chunks
from training.config import dataset_config_from_dict, load_json, save_json
from training.discover import load_outcomes
from training.fixture import NO_TURN, axis_angle_rotation, episode_fixture
from training.render import look_at, write_pair
from training.simulate import object_collision_shape

RAY_BATCH = 8_192           # rays per rayTestBatch call (pybullet answers at most 16,383)
RAY_LENGTH_M = 8.0
SEED_STREAM = 77            # third entry of every image's seed, apart from seeding.py's streams
CHUNK_IMAGES = 25           # images per resumable unit of work


def draw_view(cfg, fixture, rng: np.random.Generator) -> dict:
    """A camera a little beyond the spec's envelope (see the module docstring)."""
    cam = cfg.camera
    near, far = cam.distance
    distance = rng.uniform(0.95 * near, 1.05 * far)
    lo, hi = cam.elevation_deg
    elevation = math.radians(min(89.0, rng.uniform(lo - 3.0, hi + 3.0)))
    # The envelope's azimuths, 5 degrees wider each way (all around for the default task).
    lo, hi = cam.azimuth_deg
    azimuth = math.radians(rng.uniform(lo - 5.0, hi + 5.0) if hi - lo < 350.0
                           else rng.uniform(0.0, 360.0))
    if cam.azimuth_frame == "fixture":
        azimuth += fixture.yaw
    offset = rng.uniform(-1.0, 1.0, 3) * 1.2 * cam.target_offset / math.sqrt(3.0)
    target = np.asarray(fixture.centre()) + offset
    position = target + distance * np.array([math.cos(elevation) * math.cos(azimuth),
                                             math.cos(elevation) * math.sin(azimuth),
                                             math.sin(elevation)])
    rotation = look_at(position, target, math.degrees(azimuth), rng.uniform(-10.0, 10.0))
    # A support tilted by up to 4 degrees looks, to the camera, like the camera turned
    # about the fixture by as much.
    toward = rng.uniform(0, 2 * math.pi)
    tilt = axis_angle_rotation(np.array([math.cos(toward), math.sin(toward), 0.0]),
                               math.radians(rng.uniform(0.0, 4.0)))
    position = target + tilt @ (position - target)
    rotation = tilt @ rotation
    f = rng.uniform(*cam.focal_px)
    width, height = cam.width, cam.height
    cx = (width - 1) / 2 + rng.uniform(-1.2, 1.2) * cam.principal_offset_px
    cy = (height - 1) / 2 + rng.uniform(-1.2, 1.2) * cam.principal_offset_px
    reported = f * (1.0 + rng.uniform(-0.02, 0.02))
    return {"width": width, "height": height, "fx": f, "fy": f, "cx": cx, "cy": cy,
            "position": position.tolist(), "rotation": rotation.tolist(),
            "reported_fx": reported}


class RayWorld:
    """The episode's static shapes and objects as pybullet bodies, for ray tests only."""

    def __init__(self) -> None:
        import pybullet as pb

        self.pb = pb
        self.client = pb.connect(pb.DIRECT)

    def close(self) -> None:
        self.pb.disconnect(self.client)

    def build(self, episode: dict, outcomes: list[str], scene, table: LabelTable
              ) -> dict[int, int]:
        """Reset the world to ``episode``; returns body id -> pixel label."""
        pb, c = self.pb, self.client
        pb.resetSimulation(physicsClientId=c)
        fixture = episode_fixture(episode, scene)
        labels = {}
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        floor = pb.createMultiBody(0, plane, basePosition=[0, 0, fixture.room_floor_z],
                                   physicsClientId=c)
        labels[floor] = BACKGROUND
        yaw = pb.getQuaternionFromEuler([0, 0, fixture.yaw])
        for label, (half, centre, turn) in fixture.labelled_boxes():
            box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(half),
                                          physicsClientId=c)
            pos, orn = pb.multiplyTransforms([fixture.x, fixture.y, fixture.base_z], yaw,
                                             list(centre), pb.getQuaternionFromEuler(turn))
            if turn == NO_TURN:   # bullet's product is single precision: keep yaw exact
                orn = yaw
            labels[pb.createMultiBody(0, box, basePosition=pos, baseOrientation=orn,
                                      physicsClientId=c)] = label
        if fixture.table is not None:
            half, centre = fixture.table.box()
            box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(half),
                                          physicsClientId=c)
            labels[pb.createMultiBody(0, box, basePosition=list(centre), baseOrientation=yaw,
                                      physicsClientId=c)] = BACKGROUND
        for obj, outcome in zip(episode["objects"], outcomes):
            shape = object_collision_shape(pb, c, obj.get("shape", "box"), obj["size"])
            body = pb.createMultiBody(0, shape, basePosition=obj["position"],
                                      baseOrientation=obj["orientation"], physicsClientId=c)
            labels[body] = table.outcome_ids[outcome]
        return labels

    def cast(self, view: dict, body_labels: dict[int, int]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clean depth along the optical axis (NaN: no hit), labels and |cos incidence|."""
        w, h = view["width"], view["height"]
        rot = np.asarray(view["rotation"])
        u, v = np.meshgrid(np.arange(w), np.arange(h))
        rays = np.stack([(u - view["cx"]) / view["fx"], (v - view["cy"]) / view["fy"],
                         np.ones((h, w))]).reshape(3, -1)
        dirs = (rot @ rays).T                                  # world, optical-z component 1
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        origin = np.asarray(view["position"])
        ends = origin + RAY_LENGTH_M * unit
        rows = []   # (body id, hit fraction, normal x, y, z) per ray
        for start in range(0, len(unit), RAY_BATCH):
            stop = min(start + RAY_BATCH, len(unit))
            hits = self.pb.rayTestBatch([origin.tolist()] * (stop - start),
                                        ends[start:stop].tolist(), physicsClientId=self.client)
            if len(hits) != stop - start:
                raise RuntimeError(f"pybullet answered {len(hits)} of {stop - start} rays")
            rows.extend((hit[0], hit[2], *hit[4]) for hit in hits)
        table = np.array(rows, dtype=np.float64)
        body, fraction, normal = table[:, 0].astype(np.int64), table[:, 1], table[:, 2:]
        hit = body >= 0
        along = RAY_LENGTH_M * fraction / np.linalg.norm(dirs, axis=1)  # optical-axis depth
        depth = np.where(hit, along, np.nan).astype(np.float32).reshape(h, w)
        lookup = np.full(max(body_labels) + 2, BACKGROUND, np.uint8)   # index -1: no hit
        for body_id, label in body_labels.items():
            lookup[body_id] = label
        labels = lookup[body].reshape(h, w)
        cos = np.abs(np.sum(normal * unit, axis=1)).astype(np.float32).reshape(h, w)
        return depth, labels, cos


def nguyen_noise(depth: np.ndarray, labels: np.ndarray, cos: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A Kinect-like sensor written apart from ``noise.py`` (see the module docstring)."""
    z = depth.astype(np.float64)
    valid = np.isfinite(z)
    zf = np.where(valid, z, 0.0)
    h, w = z.shape
    sigma = (0.0012 + 0.0019 * (zf - 0.4) ** 2) * rng.uniform(0.7, 1.6)
    z = zf * (1.0 + rng.normal(0.0, 0.003)) + rng.normal(size=(h, w)) * sigma
    step = 2.85e-3 * np.maximum(zf, 0.1) ** 2
    z = np.round(z / step) * step
    # Shadow band: pixels up to `band` px left of a depth edge whose near side is 3 cm nearer.
    band = int(rng.integers(4, 13))
    far_fill = np.where(valid, zf, 1e3).astype(np.float32)
    edge = np.zeros((h, w), bool)
    edge[:, :-1] = far_fill[:, :-1] - far_fill[:, 1:] > 0.03       # the far side of an edge
    near_side = np.full((h, w), 1e3, np.float32)
    near_side[:, :-1][edge[:, :-1]] = far_fill[:, 1:][edge[:, :-1]]
    # The nearest edge surface among this pixel and the band - 1 pixels to its right.
    right_near = cv2.erode(near_side, np.ones((1, band), np.uint8), anchor=(0, 0),
                           borderType=cv2.BORDER_REPLICATE)
    valid &= ~(zf - right_near > 0.03)
    # Edge dropout: within one pixel of a depth jump of 3 cm, half the pixels.
    jump = (cv2.dilate(far_fill, np.ones((3, 3), np.uint8))
            - cv2.erode(far_fill, np.ones((3, 3), np.uint8))) > 0.03
    valid &= ~(jump & (rng.random((h, w)) < 0.5))
    # Grazing angles: dropout ramps from 75-80 deg to all at 86 deg.
    angle = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    start = rng.uniform(75.0, 80.0)
    valid &= rng.random((h, w)) >= np.clip((angle - start) / (86.0 - start), 0.0, 1.0)
    # Elliptic holes.
    holes = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.poisson(120))):
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (int(rng.integers(1, 5)), int(rng.integers(1, 4)))
        cv2.ellipse(holes, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    valid &= holes == 0
    valid &= (z >= 0.45) & (z <= rng.uniform(3.8, 4.6))
    out = np.where(valid, z, np.nan).astype(np.float32)
    lab = labels.copy()
    lab[~valid] = IGNORE
    return out, lab


_STATE: dict = {}


def _init_worker(out_dir: str, cfg, episodes: list[dict], outcomes: list[list[str]],
                 table: LabelTable, seed: int) -> None:
    cv2.setNumThreads(1)
    _STATE.update(out_dir=Path(out_dir), cfg=cfg, episodes=episodes, outcomes=outcomes,
                  table=table, seed=seed, world=RayWorld())


def independent_image(i: int) -> dict:
    """Cast, noise and write image ``i``; returns its manifest record."""
    cfg, seed, world = _STATE["cfg"], _STATE["seed"], _STATE["world"]
    episode, outcomes = _STATE["episodes"][i], _STATE["outcomes"][i]
    rng = np.random.default_rng([seed, i, SEED_STREAM])
    table = _STATE["table"]
    body_labels = world.build(episode, outcomes, cfg.scene, table)
    view = draw_view(cfg, episode_fixture(episode, cfg.scene), rng)
    clean, labels, cos = world.cast(view, body_labels)
    depth, noisy_labels = nguyen_noise(clean, labels, cos, rng)
    write_pair(_STATE["out_dir"], i, depth, noisy_labels)
    return {"episode": i, "split": "val", "seed": [seed, i, SEED_STREAM], "camera": view,
            "camera_info": {**{k: view[k] for k in ("width", "height", "cx", "cy")},
                            "fx": view["reported_fx"], "fy": view["reported_fx"]},
            "objects": outcomes, "present": outcomes_present(noisy_labels, table=table),
            "pixel_counts": outcome_pixel_counts(noisy_labels, table)}


def _chunk(images: tuple[int, int]) -> dict:
    return {"episodes": [independent_image(i) for i in range(*images)]}


def make_independent_set(data_dir: Path, out_dir: Path, images: int, seed: int = 0,
                         workers: int = 2) -> dict:
    """``images`` independent images of the first episodes of ``data_dir``'s run, made in
    resumable chunks (an interrupted run picks up where it stopped)."""
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    config = load_json(data_dir / "config.json")
    cfg = dataset_config_from_dict(config)
    episodes = load_chunks(data_dir / "simulate", cfg.episodes, cfg.chunk_size)
    outcomes, table = load_outcomes(data_dir)
    count = min(images, len(episodes))
    out_dir.mkdir(parents=True, exist_ok=True)
    recipe = {"source": str(data_dir), "images": count, "seed": seed}
    saved = out_dir / "independent.json"
    if saved.exists() and load_json(saved) != recipe:
        raise ValueError(f"{out_dir} holds another independent set ({load_json(saved)}); "
                         "use a new --out")
    save_json(saved, recipe)
    for name in ("simulate", "outcomes.json", "config.json"):  # hard-case tags, the task
        if not (out_dir / name).exists():
            copy = shutil.copytree if (data_dir / name).is_dir() else shutil.copy2
            copy(data_dir / name, out_dir / name)
    stage = out_dir / "independent"
    run_chunks(stage, count, CHUNK_IMAGES, workers, _chunk, "independent",
               initializer=_init_worker,
               initargs=(str(out_dir), cfg, episodes, outcomes, table, seed))
    manifest = {"config": config, **recipe, "generator": "training/independent.py",
                "label_table": table.to_dict(),
                "images": load_chunks(stage, count, CHUNK_IMAGES)}
    save_json(out_dir / "manifest.json", manifest)
    return manifest
