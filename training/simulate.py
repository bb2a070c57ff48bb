"""Stage 1: drop random objects (boxes, cylinders) into an open box, or place them on a shelf
board, with pybullet and record where each one comes to rest (docs/interface.md §1). The
scene spec (SceneConfig) gives the ranges; each episode records the fixture it drew
(training/fixture.py).

One pybullet world lives per worker process and is reused between episodes: the floor and the
fixture are moved (rebuilt only when the drawn geometry changes) and the objects removed and
respawned, which is far cheaper than building a world per episode. pybullet cannot free a
shape once a body has used it (removeCollisionShape refuses: "it is used"), so memory grew
~8 KB per episode; the world is therefore rebuilt with resetSimulation every
``REBUILD_EVERY`` episodes, which frees them and keeps memory flat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from training.chunks import load_chunks, run_chunks
from training.config import DatasetConfig, SceneConfig
from training.fixture import PlacedFixture, Region, _uniform, draw_fixture, first_fixture
from training.geometry import quat_to_matrix
from training.seeding import drawn_in_share, episode_rng


def random_quaternion(rng: np.random.Generator) -> list[float]:
    """Uniform random orientation (normalised 4-D Gaussian), as pybullet (x, y, z, w)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return [float(v) for v in q]


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
    fixture: PlacedFixture
    shapes: list[str]

    def without_objects(self) -> EpisodeDraw:
        """The same fixture, support and pose, with nothing placed."""
        return replace(self, sizes=[], masses=[], start_positions=[], start_orientations=[],
                       shapes=[])


def draw_shapes(scene: SceneConfig, n: int, rng: np.random.Generator) -> list[str]:
    """Each object's shape by the spec's weights (no draw when there is one shape)."""
    names = [name for name, w in scene.shape_weights if w > 0]
    if len(names) == 1:
        return names * n
    weights = np.array([w for _, w in scene.shape_weights if w > 0], float)
    return [names[k] for k in rng.choice(len(names), size=n, p=weights / weights.sum())]


def object_sizes(scene: SceneConfig, shapes: list[str], unit: np.ndarray) -> np.ndarray:
    """(n, 3) sizes from (n, 3) uniform [0, 1) draws: box edges, or a cylinder's diameter
    (twice, x and y) and height (z)."""
    sizes = np.empty_like(unit)
    for k, shape in enumerate(shapes):
        if shape == "box":
            lo, hi = scene.object_edge
            sizes[k] = lo + (hi - lo) * unit[k]
        else:
            (dlo, dhi), (hlo, hhi) = scene.cylinder_diameter, scene.cylinder_height
            d = dlo + (dhi - dlo) * unit[k, 0]
            sizes[k] = (d, d, hlo + (hhi - hlo) * unit[k, 2])
    return sizes


def draw_episode(scene: SceneConfig, rng: np.random.Generator,
                 fixture_rng: np.random.Generator) -> EpisodeDraw:
    """The physics draws come from ``rng`` in the order they always had; what the scene spec
    added (fixture geometry, shapes, release height) from ``fixture_rng``."""
    n = int(rng.integers(scene.min_objects, scene.max_objects + 1))
    unit_sizes = rng.uniform(0.0, 1.0, size=(n, 3))
    floor_z = float(rng.uniform(*scene.floor_height))
    yaw = math.radians(float(rng.uniform(*scene.fixture_yaw_deg)))
    fixture = draw_fixture(scene, yaw, floor_z, fixture_rng)
    region = fixture.region()
    shapes = draw_shapes(scene, n, fixture_rng)
    sizes = object_sizes(scene, shapes, unit_sizes)
    unit_offsets = rng.uniform(0.0, 1.0, size=(n, 2))
    orientations = [random_quaternion(rng) for _ in range(n)]
    masses = rng.uniform(*scene.object_mass, size=n)
    friction = float(rng.uniform(*scene.friction))
    restitution = float(rng.uniform(*scene.restitution))
    if scene.release_mode == "place":
        offsets, orientations, heights = _placement(scene, region, shapes, sizes,
                                                    unit_offsets, fixture_rng)
        offsets = fixture.to_world_xy(offsets, "fixture")
        starts = floor_z + heights
    else:
        reach = region.half_at(region.top) + scene.release_margin
        offsets = fixture.to_world_xy(-reach + 2 * reach * unit_offsets, scene.release_frame)
        if scene.release_orientation == "upright":
            orientations = [upright_quaternion(fixture_rng) for _ in range(n)]
        # Parenthesised as it always was, so the default task's data stay bit-identical.
        starts = np.full(n, floor_z + (region.top + _uniform(fixture_rng, scene.release_height)))
    # Released together; where bounding spheres would overlap, a later object starts higher.
    radii = np.linalg.norm(sizes, axis=1) / 2.0
    positions: list[list[float]] = []
    for i in range(n):
        base_z = float(starts[i])
        z = base_z
        for j, p in enumerate(positions):
            if np.hypot(*(offsets[i] - np.asarray(p[:2]))) < radii[i] + radii[j]:
                z = max(z, p[2] + radii[i] + radii[j] + 0.01)
        positions.append([float(offsets[i][0]), float(offsets[i][1]), float(z)])
    return EpisodeDraw(yaw, floor_z, friction, restitution, sizes.tolist(), masses.tolist(),
                       positions, orientations, fixture, shapes)


def upright_quaternion(rng: np.random.Generator) -> list[float]:
    """Object z up, random yaw, as pybullet (x, y, z, w)."""
    half = float(rng.uniform(0.0, math.pi))
    return [0.0, 0.0, math.sin(half), math.cos(half)]


def vertical_half_extent(shape: str, size, orientation: list[float]) -> float:
    """How far an object in this orientation reaches below (and above) its centre (m)."""
    r = quat_to_matrix(orientation)
    if shape == "cylinder":  # its axis is its local z
        return float(abs(r[2, 2]) * size[2] / 2
                     + math.sqrt(max(0.0, 1.0 - r[2, 2] ** 2)) * size[0] / 2)
    return float(np.sum(np.abs(r[2]) * np.asarray(size) / 2))


def quaternion_product(a: list[float], b: list[float]) -> list[float]:
    """The rotation ``a`` after ``b``, pybullet (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz]


def _placement(scene: SceneConfig, region: Region, shapes: list[str], sizes: np.ndarray,
               unit: np.ndarray, rng: np.random.Generator
               ) -> tuple[np.ndarray, list[list[float]], np.ndarray]:
    """A gripper's placements over the region's front edge (-y): (n, 2) fixture-frame
    offsets, orientations (upright, random yaw, then a tilt error about a random horizontal
    axis) and centre heights above the support putting each lowest point ``place_gap`` above
    the region's bottom."""
    along = max(0.0, region.half_x - scene.release_margin)
    offsets, orientations, heights = [], [], []
    for k, (shape, size) in enumerate(zip(shapes, sizes)):
        depth = _uniform(rng, scene.place_edge_offset)
        offsets.append([-along + 2 * along * unit[k, 0], -region.half_y + depth])
        tilt = math.radians(_uniform(rng, scene.place_tilt_deg))
        axis = float(rng.uniform(0.0, 2 * math.pi))
        q_tilt = [math.cos(axis) * math.sin(tilt / 2), math.sin(axis) * math.sin(tilt / 2),
                  0.0, math.cos(tilt / 2)]
        q = quaternion_product(q_tilt, upright_quaternion(rng))
        orientations.append(q)
        heights.append(region.bottom + _uniform(rng, scene.place_gap)
                       + vertical_half_extent(shape, size, q))
    return np.array(offsets), orientations, np.array(heights)


REBUILD_EVERY = 200
# pybullet keeps at most this many children in one compound shape and silently drops the
# rest (MAX_COMPOUND_COLLISION_SHAPES in its shared-memory API).
MAX_COMPOUND_SHAPES = 16


def object_collision_shape(pb, client: int, shape: str, size: list[float]) -> int:
    """A pybullet collision shape for an object record's ``shape`` and ``size`` (box edges, or
    a cylinder's diameter, diameter, height)."""
    if shape == "cylinder":  # pybullet cylinders stand along their local z
        return pb.createCollisionShape(pb.GEOM_CYLINDER, radius=size[0] / 2,
                                       height=size[2], physicsClientId=client)
    return pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[s / 2 for s in size],
                                   physicsClientId=client)


class World:
    """A reusable pybullet DIRECT world: the room floor, the fixture and maybe a table."""

    def __init__(self, scene: SceneConfig):
        import pybullet as pb  # imported here so other stages don't need pybullet loaded

        self.pb = pb
        self.scene = scene
        self.client = pb.connect(pb.DIRECT)
        self.shape_key: tuple | None = None
        self._build()

    def _build(self, fixture: PlacedFixture | None = None) -> None:
        """A fresh world. The fixture's (and table's) collision shapes follow ``fixture``'s
        geometry; its pose is set per episode. A spec that draws the geometry per episode
        rebuilds per episode, so a result never depends on the episodes before it."""
        pb, scene, c = self.pb, self.scene, self.client
        pb.resetSimulation(physicsClientId=c)
        self.episodes_since_build = 0
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=scene.timestep,
                                     numSolverIterations=scene.solver_iterations,
                                     deterministicOverlappingPairs=1, physicsClientId=c)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.floor = pb.createMultiBody(0, plane, physicsClientId=c)
        if fixture is None:  # the spec's first fixture, until an episode says otherwise
            fixture = first_fixture(scene)
        # Labels do not matter to physics: the fixture's and the room's solids are one body,
        # or several when they are more than one compound shape may hold.
        boxes = fixture.solid_boxes() + fixture.background_boxes()
        self.fixture_bodies = []
        for first in range(0, len(boxes), MAX_COMPOUND_SHAPES):
            part = boxes[first:first + MAX_COMPOUND_SHAPES]
            shape = pb.createCollisionShapeArray(
                [pb.GEOM_BOX] * len(part), halfExtents=[list(b[0]) for b in part],
                collisionFramePositions=[list(b[1]) for b in part],
                collisionFrameOrientations=[pb.getQuaternionFromEuler(b[2]) for b in part],
                physicsClientId=c)
            self.fixture_bodies.append(pb.createMultiBody(0, shape, physicsClientId=c))
        self.table = None
        if fixture.table is not None:
            half, _ = fixture.table.box()
            table_shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(half),
                                                  physicsClientId=c)
            self.table = pb.createMultiBody(0, table_shape, physicsClientId=c)
        self.shape_key = fixture.shape_key()
        self.objects: list[int] = []   # body ids of this episode's objects

    def close(self) -> None:
        self.pb.disconnect(self.client)

    def _prepare(self, fixture: PlacedFixture) -> None:
        """Remove the last episode's objects; rebuild when due or when the geometry changed."""
        if self.episodes_since_build >= REBUILD_EVERY or fixture.shape_key() != self.shape_key:
            self._build(fixture)
            return
        for body in self.objects:
            self.pb.removeBody(body, physicsClientId=self.client)
        self.objects = []

    def _object_shape(self, shape: str, size: list[float]) -> int:
        return object_collision_shape(self.pb, self.client, shape, size)

    def run(self, draw: EpisodeDraw) -> dict:
        pb, c, scene, fixture = self.pb, self.client, self.scene, draw.fixture
        self._prepare(fixture)
        self.episodes_since_build += 1
        pb.setGravity(*fixture.gravity(), physicsClientId=c)  # leaning on a tilted support
        yaw_q = pb.getQuaternionFromEuler([0, 0, draw.container_yaw])
        pb.resetBasePositionAndOrientation(self.floor, [0, 0, fixture.room_floor_z],
                                           [0, 0, 0, 1], physicsClientId=c)
        for body in self.fixture_bodies:
            pb.resetBasePositionAndOrientation(body, [fixture.x, fixture.y, draw.floor_z], yaw_q,
                                               physicsClientId=c)
        statics = [self.floor, *self.fixture_bodies]
        if self.table is not None:
            _, centre = fixture.table.box()
            pb.resetBasePositionAndOrientation(self.table, list(centre), yaw_q,
                                               physicsClientId=c)
            statics.append(self.table)
        # Bullet multiplies the two bodies' coefficients: static bodies at 1 make the drawn
        # value the effective one for object-fixture and object-floor contacts.
        for body in statics:
            pb.changeDynamics(body, -1, lateralFriction=1.0, restitution=1.0,
                              physicsClientId=c)
        for shape_name, size, mass, pos, orn in zip(draw.shapes, draw.sizes, draw.masses,
                                                    draw.start_positions,
                                                    draw.start_orientations):
            shape = self._object_shape(shape_name, size)
            body = pb.createMultiBody(mass, shape, basePosition=pos, baseOrientation=orn,
                                      physicsClientId=c)
            pb.changeDynamics(body, -1, lateralFriction=draw.friction,
                              restitution=draw.restitution, physicsClientId=c)
            if scene.rolling_friction > 0:  # only then: other specs simulate as they did
                pb.changeDynamics(body, -1, rollingFriction=scene.rolling_friction,
                                  spinningFriction=scene.rolling_friction,
                                  physicsClientId=c)
            self.objects.append(body)

        check_every = 6
        hold_needed = int(math.ceil(scene.rest_hold_time / scene.timestep))
        max_steps = int(round(scene.max_episode_time / scene.timestep))
        still = [0] * len(self.objects)
        steps = 0
        while self.objects and steps < max_steps:
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
                "shape": draw.shapes[k],
                "size": [round(s, 6) for s in draw.sizes[k]],
                "mass": round(draw.masses[k], 6),
                "position": [float(v) for v in pos],
                "orientation": [float(v) for v in orn],
                "settled": still[k] >= hold_needed,
            })
        return {
            "container_yaw": draw.container_yaw,
            "floor_z": draw.floor_z,
            "fixture": fixture.to_record(),
            "friction": draw.friction,
            "restitution": draw.restitution,
            "sim_time": steps * scene.timestep,
            "timed_out": min(still, default=hold_needed) < hold_needed,
            "objects": objects,
        }


def is_empty_episode(scene: SceneConfig, run_seed: int, episode: int) -> bool:
    """Whether nothing is placed in this episode (``scene.empty_share``), from a stream of its
    own: the other episodes are drawn exactly as without the share."""
    return drawn_in_share(scene.empty_share, run_seed, episode, "empty")


def simulate_episode(world: World, run_seed: int, episode: int) -> dict:
    """Draw and simulate one episode; the result depends only on (run_seed, episode)."""
    draw = draw_episode(world.scene, episode_rng(run_seed, episode, "simulate"),
                        episode_rng(run_seed, episode, "fixture"))
    if is_empty_episode(world.scene, run_seed, episode):
        draw = draw.without_objects()
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
