"""Geometry of final object states in the fixture's frame, shared by discovery, hard cases
and their tests. Everything is measured against the episode's own fixture
(training/fixture.py): a rectangular footprint is measured per axis."""

from __future__ import annotations

import numpy as np

from training.config import SceneConfig
from training.fixture import PlacedFixture, episode_fixture

# Sample points per box axis for volume fractions. The grid includes the box's faces, so a box
# that pokes out of the target region by any amount loses at least one point: "fully inside" is
# exact, which is what separates "inside" from "partly inside" (see discover.py).
SAMPLE_GRID = 10
# Resting contacts interpenetrate by a few mm in Bullet; a box lying against an inner wall is
# inside the region, so its footprint (and its bottom) get this much tolerance.
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


def object_top(obj: dict, fixture: PlacedFixture) -> float:
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
    """Measurements of one final object state against the episode's target region (the
    fixture's ``Region``), in the fixture's frame.

    - ``com_offset``: the centre of mass's offset from the footprint's centre, per axis in
      units of that axis's half-width, the larger of the two (< 1 over the footprint);
    - ``com_beyond_edge``: how far the centre of mass lies beyond the region, in edge
      thicknesses: its distance beyond the footprint (the larger axis), or, when it lies
      below the region's bottom, the larger of that and its depth below it. < 0 inside, 0-1
      over the edge (a wall's top), > 1 beyond the fixture's outer footprint, or fallen
      below the region;
    - ``com_beyond_outer``: 1.0 when the centre of mass is beyond the outer footprint
      (footprint plus edge) or more than an edge thickness below the region's bottom;
    - ``inside_fraction``: fraction of the object's volume inside the region (its footprint,
      between its bottom and top);
    - ``footprint_fraction``: fraction of its volume over the footprint, at any height;
    - ``reach_beyond_footprint``: how far its farthest point reaches beyond the footprint (m;
      < 0: it stays that far inside);
    - ``over_fraction``: fraction of its volume over the outer footprint, at any height;
    - ``top_above_region``: height of its highest point above the region's top (m).
    """
    fixture = episode_fixture(episode, scene)
    region = fixture.region()
    pts = fixture.to_frame(object_sample_points(obj))
    com = fixture.to_frame(np.asarray(obj["position"]))
    # The footprint and edge at each point's own height (a leaning wall's box widens upwards).
    half_in, half_in_pts = region.half_at(com[2]), region.half_at(pts[:, 2])
    edge = float(region.edge_at(com[2]))
    half_out_pts = half_in_pts + region.edge_at(pts[:, 2])[:, None]
    over_xy = np.all(np.abs(pts[:, :2]) <= half_in_pts + CONTACT_SLOP, axis=1)
    within_z = (pts[:, 2] >= region.bottom - CONTACT_SLOP) & (pts[:, 2] <= region.top)
    # Below the region's bottom counts only once the centre of mass is there (a board's fallen
    # objects); above it, how far inside says nothing, so the spike at -1 stays a spike.
    beyond = float(np.max(np.abs(com[:2]) - half_in))
    if float(com[2]) < region.bottom:
        beyond = max(beyond, region.bottom - float(com[2]))
    return {
        "com_offset": float(np.max(np.abs(com[:2]) / half_in)),
        "com_beyond_edge": beyond / edge,
        "com_beyond_outer": float(np.any(np.abs(com[:2]) > half_in + edge)
                                  or com[2] < region.bottom - edge),
        "inside_fraction": float(np.mean(over_xy & within_z)),
        "footprint_fraction": float(np.mean(over_xy)),
        "reach_beyond_footprint": float(np.max(np.abs(pts[:, :2]) - half_in_pts)),
        "over_fraction": float(np.mean(np.all(np.abs(pts[:, :2]) < half_out_pts, axis=1))),
        "top_above_region": object_top(obj, fixture) - region.top,
    }


def geometric_outcome(m: dict[str, float], inside_rule: str = "top") -> str:
    """The yardstick of docs/interface.md §2 (never the label source), as a descriptor
    (``DESCRIPTORS``): "inside" if the centre of mass is inside the region and, by
    ``inside_rule`` (the spec's ``discover.yardstick_inside``), the top is below the region's
    top or all of the object is over the footprint; "outside" if the centre of mass is beyond
    the outer footprint or fell below the region; otherwise "partly_inside"."""
    held = (m["top_above_region"] <= 0.0 if inside_rule == "top"
            else m["footprint_fraction"] >= 1.0)
    if m["com_beyond_edge"] < 0.0 and held:
        return "inside"
    if m["com_beyond_outer"]:
        return "outside"
    return "partly_inside"
