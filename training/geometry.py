"""Geometry of final object states in the container frame, shared by discovery and its tests."""

from __future__ import annotations

import numpy as np

from training.config import SceneConfig

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


def to_container_frame(points: np.ndarray, container_yaw: float, floor_z: float) -> np.ndarray:
    """World points (..., 3) -> container frame (origin at the container's floor centre)."""
    c, s = np.cos(-container_yaw), np.sin(-container_yaw)
    p = np.asarray(points, dtype=np.float64) - np.array([0.0, 0.0, floor_z])
    return np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1], p[..., 2]], -1)


def box_sample_points(size, position, orientation) -> np.ndarray:
    """A uniform grid of points filling a box, faces included, in world coordinates."""
    axes = [np.linspace(-0.5, 0.5, SAMPLE_GRID)] * 3
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) * np.asarray(size)
    return g @ quat_to_matrix(orientation).T + np.asarray(position)


def box_corners(size, position, orientation) -> np.ndarray:
    signs = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
    return (signs * np.asarray(size)) @ quat_to_matrix(orientation).T + np.asarray(position)


def object_measurements(obj: dict, episode: dict, scene: SceneConfig) -> dict[str, float]:
    """Measurements of one final object state, all in the container frame.

    - ``com_offset``: Chebyshev distance of the centre of mass from the container axis, in units
      of the inner half-width (< 1 inside the inner footprint, > outer/inner outside the walls);
    - ``inside_fraction``: fraction of the object's volume inside the container's inner volume
      (inner footprint, below the rim top);
    - ``over_fraction``: fraction of its volume above the container's outer footprint;
    - ``top_above_rim``: height of its highest corner above the rim top (m).
    """
    half_in = scene.container_inner_size / 2.0
    half_out = half_in + scene.wall_thickness
    yaw, floor_z = episode["container_yaw"], episode["floor_z"]
    pts = to_container_frame(box_sample_points(obj["size"], obj["position"],
                                               obj["orientation"]), yaw, floor_z)
    cheb = np.max(np.abs(pts[:, :2]), axis=1)
    com = to_container_frame(np.asarray(obj["position"]), yaw, floor_z)
    corners = to_container_frame(box_corners(obj["size"], obj["position"], obj["orientation"]),
                                 yaw, floor_z)
    return {
        "com_offset": float(np.max(np.abs(com[:2])) / half_in),
        "inside_fraction": float(np.mean((cheb <= half_in + CONTACT_SLOP)
                                         & (pts[:, 2] <= scene.wall_height))),
        "over_fraction": float(np.mean(cheb < half_out)),
        "top_above_rim": float(corners[:, 2].max() - scene.wall_height),
    }


def outer_footprint_ratio(scene: SceneConfig) -> float:
    """The outer wall's half-width in units of the inner half-width (``com_offset``'s unit)."""
    return 1.0 + scene.wall_thickness / (scene.container_inner_size / 2)


def geometric_outcome(m: dict[str, float], scene: SceneConfig) -> str:
    """The yardstick of docs/interface.md §2 (never the label source): success if the centre of
    mass is inside the inner footprint and the top below the rim; fell_outside if the centre of
    mass is outside the outer footprint; otherwise stuck_on_rim."""
    if m["com_offset"] < 1.0 and m["top_above_rim"] <= 0.0:
        return "success"
    if m["com_offset"] > outer_footprint_ratio(scene):
        return "fell_outside"
    return "stuck_on_rim"
