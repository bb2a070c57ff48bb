"""The fixture of one episode: the container (and the table under it) as drawn from the spec.

A scene spec gives ranges (footprint, wall height, pose, table); each episode draws one
concrete ``Fixture``, records it in its simulation result, and every later stage (geometry,
discovery, rendering, hard cases) rebuilds it from that record, so physics, labels and
measurements can never disagree about the geometry.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from training.config import SceneConfig

Box = tuple[tuple[float, float, float], tuple[float, float, float]]  # half extents, centre


@dataclass(frozen=True)
class Table:
    """A static table top: half extents of its top, its centre (x, y), top and room floor."""

    half_x: float
    half_y: float
    x: float
    y: float
    top_z: float
    floor_z: float

    def box(self) -> Box:
        """The table as one solid box from the room floor to its top (world frame)."""
        half_z = (self.top_z - self.floor_z) / 2
        return (self.half_x, self.half_y, half_z), (self.x, self.y, self.floor_z + half_z)


@dataclass(frozen=True)
class Fixture:
    """An open-top container with a rectangular inner footprint, standing on the support."""

    half_x: float            # m, inner half extents
    half_y: float
    wall_height: float       # m, base to rim top
    wall_thickness: float
    bottom_thickness: float
    x: float                 # m, base centre in the world
    y: float
    yaw: float               # rad, about z
    base_z: float            # m, the support plane the container stands on
    table: Table | None = None
    # The support's tilt from level: this many degrees, about a horizontal axis at this
    # azimuth. Simulation and geometry work in the support's frame (z normal to it), so a tilt
    # is gravity leaning in that frame, and cameras, placed against the true vertical, see
    # the whole scene tilted.
    tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 0.0

    def tilt_rotation(self) -> np.ndarray:
        """Support frame -> true (gravity-aligned) frame: the tilt about its horizontal axis."""
        az = math.radians(self.tilt_azimuth_deg)
        return axis_angle_rotation(np.array([math.cos(az), math.sin(az), 0.0]),
                                   math.radians(self.tilt_deg))

    def gravity(self) -> list[float]:
        """Gravity in the support's frame (the simulation's)."""
        return [float(v) for v in self.tilt_rotation().T @ np.array([0.0, 0.0, -9.81])]

    @property
    def room_floor_z(self) -> float:
        """The lowest plane of the scene: the room floor (below the table, if there is one)."""
        return self.base_z if self.table is None else self.table.floor_z

    @property
    def rotation(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def container_boxes(self) -> list[Box]:
        """The container as five boxes (half extents, centre) in its own frame, base at z=0."""
        hx, hy, t, h = self.half_x, self.half_y, self.wall_thickness, self.wall_height
        ox, oy = hx + t, hy + t
        bottom = ((ox, oy, self.bottom_thickness / 2), (0.0, 0.0, self.bottom_thickness / 2))
        walls = [
            ((t / 2, oy, h / 2), (hx + t / 2, 0.0, h / 2)),
            ((t / 2, oy, h / 2), (-hx - t / 2, 0.0, h / 2)),
            ((hx, t / 2, h / 2), (0.0, hy + t / 2, h / 2)),
            ((hx, t / 2, h / 2), (0.0, -hy - t / 2, h / 2)),
        ]
        return [bottom, *walls]

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> the fixture frame (origin at its base centre)."""
        c, s = np.cos(-self.yaw), np.sin(-self.yaw)
        p = np.asarray(points, dtype=np.float64) - np.array([self.x, self.y, self.base_z])
        return np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1],
                         p[..., 2]], -1)

    def to_world_xy(self, offsets: np.ndarray, frame: str = "fixture") -> np.ndarray:
        """(n, 2) horizontal offsets from the footprint's centre -> world x, y. ``frame``
        "fixture": offsets along the container's walls; "world": along the world axes."""
        offsets = np.asarray(offsets, dtype=np.float64)
        if frame == "fixture" and self.yaw != 0.0:
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            offsets = offsets @ np.array([[c, s], [-s, c]])
        if self.x or self.y:
            offsets = offsets + np.array([self.x, self.y])
        return offsets

    def centre(self) -> np.ndarray:
        """World point halfway up the walls over the footprint's centre (the cameras aim here)."""
        return np.array([self.x, self.y, self.base_z + self.wall_height / 2])

    def to_record(self) -> dict:
        return asdict(self)


def axis_angle_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues' formula)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                  [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


def fixture_from_record(record: dict) -> Fixture:
    table = record.get("table")
    return Fixture(**{**record, "table": Table(**table) if table else None})


def episode_fixture(episode: dict, scene: SceneConfig) -> Fixture:
    """The fixture an episode was simulated with. Episodes simulated before fixtures were
    recorded had the spec's one square container at the origin."""
    if "fixture" in episode:
        return fixture_from_record(episode["fixture"])
    return Fixture(scene.inner_size_x[0] / 2, scene.inner_size_y[0] / 2, scene.wall_height[0],
                   scene.wall_thickness, scene.bottom_thickness, 0.0, 0.0,
                   float(episode["container_yaw"]), float(episode["floor_z"]))


def _uniform(rng: np.random.Generator, interval: tuple[float, float]) -> float:
    """A draw from [lo, hi]; a fixed value (lo == hi) consumes no randomness."""
    lo, hi = interval
    return float(lo) if lo == hi else float(rng.uniform(lo, hi))


def draw_fixture(scene: SceneConfig, yaw: float, base_z: float,
                 rng: np.random.Generator) -> Fixture:
    """The episode's fixture: footprint, wall height and position from ``rng`` (its own
    stream), yaw and support height as the episode drew them."""
    half_x = _uniform(rng, scene.inner_size_x) / 2
    half_y = _uniform(rng, scene.inner_size_y) / 2
    wall_height = _uniform(rng, scene.wall_height)
    offset = scene.container_offset
    x, y = (float(v) for v in rng.uniform(-offset, offset, 2)) if offset > 0 else (0.0, 0.0)
    table = None
    if scene.table_size is not None:
        height = _uniform(rng, scene.table_height)
        toff = scene.table_offset
        tx, ty = (float(v) for v in rng.uniform(-toff, toff, 2)) if toff > 0 else (0.0, 0.0)
        table = Table(scene.table_size[0] / 2, scene.table_size[1] / 2, x + tx, y + ty,
                      base_z, base_z - height)
    tilt, tilt_azimuth = 0.0, 0.0
    if scene.support_tilt_deg[1] > 0:
        tilt = _uniform(rng, scene.support_tilt_deg)
        tilt_azimuth = float(rng.uniform(0.0, 360.0))
    return Fixture(half_x, half_y, wall_height, scene.wall_thickness, scene.bottom_thickness,
                   x, y, yaw, base_z, table, tilt, tilt_azimuth)
