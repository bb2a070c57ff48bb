"""Geometry of final object states in the fixture's frame, shared by discovery, hard cases
and their tests. Everything is measured against the episode's own fixture
(training/fixture.py): a rectangular footprint is measured per axis."""

from __future__ import annotations

import numpy as np

from training.config import SceneConfig
from training.fixture import Fixture, episode_fixture

# Sample points per box axis for volume fractions. The grid includes the box's faces, so a box
# that pokes out of the container by any amount loses at least one point: "fully inside" is
# exact, which is what separates success from stuck objects (see discover.py).
SAMPLE_GRID = 10
# Resting contacts interpenetrate by a few mm in Bullet; a box lying against the inner wall
# is inside the container, so the inner footprint gets this much tolerance.
CONTACT_SLOP = 0.005  # m


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """pybullet quaternion(s) (x, y, z, w) -> rotation matrix/matrices."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _unit_box_grid() -> np.ndarray:
    axes = [np.linspace(-0.5, 0.5, SAMPLE_GRID)] * 3
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _unit_cylinder_grid() -> np.ndarray:
    """Points filling a cylinder of diameter 1 and height 1: rings of radius 0.1 .. 0.5 (the
    surface included, so any part outside loses a point) at SAMPLE_GRID heights."""
    rings = [(0.0, 0.0)]
    for r in np.linspace(0.5 / SAMPLE_GRID * 2, 0.5, SAMPLE_GRID // 2):
        n = max(6, int(round(2 * np.pi * r * SAMPLE_GRID * 2)))
        a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        rings += list(zip(r * np.cos(a), r * np.sin(a)))
    disc = np.array(rings)
    z = np.linspace(-0.5, 0.5, SAMPLE_GRID)
    return np.concatenate([np.column_stack([disc, np.full(len(disc), h)]) for h in z])


_UNIT_GRIDS = {"box": _unit_box_grid(), "cylinder": _unit_cylinder_grid()}


def object_sample_points(obj: dict) -> np.ndarray:
    """Points filling an object (box or cylinder), surface included, in world coordinates."""
    grid = _UNIT_GRIDS[obj.get("shape", "box")] * np.asarray(obj["size"])
    return grid @ quat_to_matrix(obj["orientation"]).T + np.asarray(obj["position"])


def object_top(obj: dict, fixture: Fixture) -> float:
    """Height of the object's highest point above the fixture's base (m)."""
    if obj.get("shape", "box") == "cylinder":  # the highest point of its two rim circles
        axis = quat_to_matrix(obj["orientation"])[:, 2]
        radial = np.sqrt(max(0.0, 1.0 - axis[2] ** 2))
        reach = abs(axis[2]) * obj["size"][2] / 2 + radial * obj["size"][0] / 2
        return float(obj["position"][2] + reach - fixture.base_z)
    corners = fixture.to_frame(box_corners(obj["size"], obj["position"], obj["orientation"]))
    return float(corners[:, 2].max())


def box_corners(size, position, orientation) -> np.ndarray:
    signs = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
    return (signs * np.asarray(size)) @ quat_to_matrix(orientation).T + np.asarray(position)


def object_measurements(obj: dict, episode: dict, scene: SceneConfig) -> dict[str, float]:
    """Measurements of one final object state against the episode's fixture, in its frame.

    - ``com_offset``: the centre of mass's offset from the footprint's centre, per axis in
      units of that axis's inner half-width, the larger of the two (< 1 inside the inner
      footprint);
    - ``com_beyond_wall``: how far the centre of mass lies beyond the walls' inner faces, in
      wall thicknesses (the larger axis): < 0 inside the inner footprint, 0-1 over the wall
      top, > 1 beyond the outer footprint;
    - ``com_beyond_outer``: 1.0 when the centre of mass is outside the outer footprint;
    - ``inside_fraction``: fraction of the object's volume inside the inner volume (inner
      footprint, below the rim top);
    - ``over_fraction``: fraction of its volume above the outer footprint;
    - ``top_above_rim``: height of its highest point above the rim top (m).
    """
    fixture = episode_fixture(episode, scene)
    half_in = np.array([fixture.half_x, fixture.half_y])
    half_out = half_in + fixture.wall_thickness
    pts = fixture.to_frame(object_sample_points(obj))
    com = fixture.to_frame(np.asarray(obj["position"]))
    inside_xy = np.all(np.abs(pts[:, :2]) <= half_in + CONTACT_SLOP, axis=1)
    return {
        "com_offset": float(np.max(np.abs(com[:2]) / half_in)),
        "com_beyond_wall": float(np.max(np.abs(com[:2]) - half_in) / fixture.wall_thickness),
        "com_beyond_outer": float(np.any(np.abs(com[:2]) > half_out)),
        "inside_fraction": float(np.mean(inside_xy & (pts[:, 2] <= fixture.wall_height))),
        "over_fraction": float(np.mean(np.all(np.abs(pts[:, :2]) < half_out, axis=1))),
        "top_above_rim": object_top(obj, fixture) - fixture.wall_height,
    }


def geometric_outcome(m: dict[str, float], scene: SceneConfig) -> str:
    """The yardstick of docs/interface.md §2 (never the label source): success if the centre of
    mass is inside the inner footprint and the top below the rim; fell_outside if the centre of
    mass is outside the outer footprint; otherwise stuck_on_rim."""
    if m["com_offset"] < 1.0 and m["top_above_rim"] <= 0.0:
        return "success"
    if m["com_beyond_outer"]:
        return "fell_outside"
    return "stuck_on_rim"
