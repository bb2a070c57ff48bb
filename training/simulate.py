"""Stage 1: drop 1-4 random boxes into an open container with pybullet and record where
each one comes to rest (docs/interface.md §1).

One pybullet world lives per worker process and is reused between episodes: the floor and the
container are moved and the objects removed and respawned, which is far cheaper than building a
world per episode. pybullet cannot free a box shape once a body has used it (removeCollisionShape
refuses: "it is used"), so memory grew ~8 KB per episode; the world is therefore rebuilt with
resetSimulation every ``REBUILD_EVERY`` episodes, which frees them and keeps memory flat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from training.chunks import load_chunks, run_chunks
from training.config import DatasetConfig, SceneConfig
from training.seeding import episode_rng


def random_quaternion(rng: np.random.Generator) -> list[float]:
    """Uniform random orientation (normalised 4-D Gaussian), as pybullet (x, y, z, w)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return [float(v) for v in q]


def container_boxes(scene: SceneConfig) -> list[tuple[tuple[float, float, float],
                                                      tuple[float, float, float]]]:
    """The container as five boxes (half extents, centre) in its own frame, floor at z=0.

    Shared by the physics and the renderer so they can never disagree about the geometry.
    """
    inner = scene.container_inner_size / 2.0
    t = scene.wall_thickness
    h = scene.wall_height
    outer = inner + t
    bottom = ((outer, outer, scene.bottom_thickness / 2.0), (0.0, 0.0, scene.bottom_thickness / 2))
    walls = [
        ((t / 2, outer, h / 2), (inner + t / 2, 0.0, h / 2)),
        ((t / 2, outer, h / 2), (-inner - t / 2, 0.0, h / 2)),
        ((inner, t / 2, h / 2), (0.0, inner + t / 2, h / 2)),
        ((inner, t / 2, h / 2), (0.0, -inner - t / 2, h / 2)),
    ]
    return [bottom, *walls]


@dataclass
class EpisodeDraw:
    """Everything random about one episode, drawn before the physics runs."""

    container_yaw: float
    floor_z: float
    friction: float
    restitution: float
    sizes: list[list[float]]
    masses: list[float]
    start_positions: list[list[float]]
    start_orientations: list[list[float]]


def draw_episode(scene: SceneConfig, rng: np.random.Generator) -> EpisodeDraw:
    n = int(rng.integers(scene.min_objects, scene.max_objects + 1))
    lo, hi = scene.object_edge
    sizes = rng.uniform(lo, hi, size=(n, 3))
    floor_z = float(rng.uniform(*scene.floor_height))
    yaw = math.radians(float(rng.uniform(*scene.container_yaw_deg)))
    offsets = rng.uniform(-scene.release_offset, scene.release_offset, size=(n, 2))
    orientations = [random_quaternion(rng) for _ in range(n)]
    masses = rng.uniform(*scene.object_mass, size=n)
    friction = float(rng.uniform(*scene.friction))
    restitution = float(rng.uniform(*scene.restitution))
    # Released together; where bounding spheres would overlap, a later object starts higher.
    radii = np.linalg.norm(sizes, axis=1) / 2.0
    positions: list[list[float]] = []
    base_z = floor_z + scene.release_height
    for i in range(n):
        z = base_z
        for j, p in enumerate(positions):
            if np.hypot(*(offsets[i] - np.asarray(p[:2]))) < radii[i] + radii[j]:
                z = max(z, p[2] + radii[i] + radii[j] + 0.01)
        positions.append([float(offsets[i][0]), float(offsets[i][1]), float(z)])
    return EpisodeDraw(yaw, floor_z, friction, restitution, sizes.tolist(), masses.tolist(),
                       positions, orientations)


REBUILD_EVERY = 200


class World:
    """A reusable pybullet DIRECT world with a floor and the container."""

    def __init__(self, scene: SceneConfig):
        import pybullet as pb  # imported here so other stages don't need pybullet loaded

        self.pb = pb
        self.scene = scene
        self.client = pb.connect(pb.DIRECT)
        self._build()

    def _build(self) -> None:
        pb, scene = self.pb, self.scene
        pb.resetSimulation(physicsClientId=self.client)
        self.episodes_since_build = 0
        pb.setGravity(0, 0, -9.81, physicsClientId=self.client)
        pb.setPhysicsEngineParameter(fixedTimeStep=scene.timestep,
                                     numSolverIterations=scene.solver_iterations,
                                     deterministicOverlappingPairs=1,
                                     physicsClientId=self.client)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=self.client)
        self.floor = pb.createMultiBody(0, plane, physicsClientId=self.client)
        boxes = container_boxes(scene)
        shape = pb.createCollisionShapeArray(
            [pb.GEOM_BOX] * len(boxes), halfExtents=[list(b[0]) for b in boxes],
            collisionFramePositions=[list(b[1]) for b in boxes], physicsClientId=self.client)
        self.container = pb.createMultiBody(0, shape, physicsClientId=self.client)
        self.objects: list[int] = []   # body ids of this episode's boxes

    def close(self) -> None:
        self.pb.disconnect(self.client)

    def _clear_objects(self) -> None:
        if self.episodes_since_build >= REBUILD_EVERY:
            self._build()
            return
        for body in self.objects:
            self.pb.removeBody(body, physicsClientId=self.client)
        self.objects = []

    def run(self, draw: EpisodeDraw) -> dict:
        pb, c, scene = self.pb, self.client, self.scene
        self._clear_objects()
        self.episodes_since_build += 1
        yaw_q = pb.getQuaternionFromEuler([0, 0, draw.container_yaw])
        pb.resetBasePositionAndOrientation(self.floor, [0, 0, draw.floor_z], [0, 0, 0, 1],
                                           physicsClientId=c)
        pb.resetBasePositionAndOrientation(self.container, [0, 0, draw.floor_z], yaw_q,
                                           physicsClientId=c)
        # Bullet multiplies the two bodies' coefficients: static bodies at 1 make the drawn
        # value the effective one for object-container and object-floor contacts.
        for body in (self.floor, self.container):
            pb.changeDynamics(body, -1, lateralFriction=1.0, restitution=1.0,
                              physicsClientId=c)
        for size, mass, pos, orn in zip(draw.sizes, draw.masses, draw.start_positions,
                                        draw.start_orientations):
            shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[s / 2 for s in size],
                                            physicsClientId=c)
            body = pb.createMultiBody(mass, shape, basePosition=pos, baseOrientation=orn,
                                      physicsClientId=c)
            pb.changeDynamics(body, -1, lateralFriction=draw.friction,
                              restitution=draw.restitution, physicsClientId=c)
            self.objects.append(body)

        check_every = 6
        hold_needed = int(math.ceil(scene.rest_hold_time / scene.timestep))
        max_steps = int(round(scene.max_episode_time / scene.timestep))
        still = [0] * len(self.objects)
        steps = 0
        while steps < max_steps:
            for _ in range(check_every):
                pb.stepSimulation(physicsClientId=c)
            steps += check_every
            for k, body in enumerate(self.objects):
                lin, ang = pb.getBaseVelocity(body, physicsClientId=c)
                at_rest = (math.hypot(*lin) < scene.rest_linear_speed
                           and math.hypot(*ang) < scene.rest_angular_speed)
                still[k] = still[k] + check_every if at_rest else 0
            if min(still) >= hold_needed:
                break
        objects = []
        for k, body in enumerate(self.objects):
            pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=c)
            objects.append({
                "size": [round(s, 6) for s in draw.sizes[k]],
                "mass": round(draw.masses[k], 6),
                "position": [float(v) for v in pos],
                "orientation": [float(v) for v in orn],
                "settled": still[k] >= hold_needed,
            })
        return {
            "container_yaw": draw.container_yaw,
            "floor_z": draw.floor_z,
            "friction": draw.friction,
            "restitution": draw.restitution,
            "sim_time": steps * scene.timestep,
            "timed_out": min(still) < hold_needed,
            "objects": objects,
        }


def simulate_episode(world: World, run_seed: int, episode: int) -> dict:
    """Draw and simulate one episode; the result depends only on (run_seed, episode)."""
    draw = draw_episode(world.scene, episode_rng(run_seed, episode, "simulate"))
    result = world.run(draw)
    result["episode"] = episode
    return result


# ---- stage entry point: worker-process state and the chunk function --------------------------

_WORLD: World | None = None
_SEED = 0


def _init_worker(scene: SceneConfig, seed: int) -> None:
    global _WORLD, _SEED
    _WORLD, _SEED = World(scene), seed


def _simulate_chunk(episodes: tuple[int, int]) -> dict:
    assert _WORLD is not None
    # A fresh world per chunk: results then depend only on the episode, never on what this
    # worker simulated before (checked by the determinism test).
    _WORLD._build()
    return {"episodes": [simulate_episode(_WORLD, _SEED, i) for i in range(*episodes)]}


def run_simulate(run_dir: Path, cfg: DatasetConfig) -> list[dict]:
    """Simulate every episode of the run into <run>/simulate/ (resumable) and return them."""
    stage_dir = Path(run_dir) / "simulate"
    run_chunks(stage_dir, cfg.episodes, cfg.chunk_size, cfg.workers, _simulate_chunk,
               "simulate", initializer=_init_worker, initargs=(cfg.scene, cfg.seed))
    return load_chunks(stage_dir, cfg.episodes, cfg.chunk_size)
