"""Per-episode fixtures (training/fixture.py): a rectangular container's geometry, features,
yardstick and labels, and the analytic renderer's new shapes against pybullet's own ray test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from task_outcome_ros.labels import DEFAULT_TABLE, FIXTURE
from training.config import DiscoverConfig, SceneConfig, _from_dict
from training.discover import features
from training.fixture import Fixture, Table, draw_fixture, episode_fixture, fixture_from_record
from training.geometry import geometric_outcome, object_measurements, object_sample_points
from training.render import Camera, SceneBox, look_at, render, scene_boxes
from training.scene import load_scene

task_word = DiscoverConfig().outcome_name  # descriptor -> the default task's word

pytestmark = pytest.mark.unit

# A 0.8 x 0.4 m tote (inner), 0.15 m walls, turned by 30 degrees, off the origin, on a table.
TOTE = Fixture(half_x=0.4, half_y=0.2, wall_height=0.15, wall_thickness=0.01,
               bottom_thickness=0.01, x=0.1, y=-0.05, yaw=math.radians(30), base_z=0.75,
               table=Table(0.9, 0.7, 0.1, -0.05, 0.75, 0.0))
# The paper's 1 m container at the origin, level.
SQUARE = dict(half_x=0.5, half_y=0.5, wall_height=0.25, wall_thickness=0.02,
              bottom_thickness=0.02, x=0.0, y=0.0, yaw=0.0, base_z=0.0)
SCENE = SceneConfig(inner_size_x=(0.8, 0.8), inner_size_y=(0.4, 0.4), wall_height=(0.15, 0.15),
                    wall_thickness=0.01, bottom_thickness=0.01)


def _episode(*objects: dict) -> dict:
    return {"container_yaw": TOTE.yaw, "floor_z": TOTE.base_z, "fixture": TOTE.to_record(),
            "objects": list(objects)}


def _at(local_xy: tuple[float, float], z: float, size=(0.06, 0.06, 0.06), shape="box") -> dict:
    """An upright object whose centre sits at fixture-frame (x, y) and height z above its base."""
    c, s = math.cos(TOTE.yaw), math.sin(TOTE.yaw)
    x, y = local_xy
    world = [TOTE.x + c * x - s * y, TOTE.y + s * x + c * y, TOTE.base_z + z]
    return {"shape": shape, "size": list(size), "position": world,
            "orientation": [0.0, 0.0, 0.0, 1.0]}


# Along the long axis 0.35 m is inside (half 0.4); along the short one it is far outside.
INSIDE_LONG = _at((0.35, 0.0), 0.05)
OUTSIDE_SHORT = _at((0.0, 0.35), 0.05 - 0.75 + 0.75)  # beside the tote, on the table
ON_SHORT_WALL = _at((0.0, 0.205), 0.18)               # resting across the long wall's top
TALL_INSIDE = _at((-0.2, 0.05), 0.11, size=(0.05, 0.05, 0.2), shape="cylinder")


@pytest.mark.parametrize("obj,expected", [(INSIDE_LONG, "success"),
                                          (OUTSIDE_SHORT, "fell_outside"),
                                          (ON_SHORT_WALL, "stuck_on_rim"),
                                          (TALL_INSIDE, "stuck_on_rim")],
                         ids=["inside-long-axis", "outside-short-axis", "on-wall", "tall"])
def test_a_rectangle_is_measured_per_axis(obj, expected):
    m = object_measurements(obj, _episode(obj), SCENE)
    assert task_word(geometric_outcome(m)) == expected
    if obj is INSIDE_LONG:  # 0.35 of a 0.4 half width: inside, though > the short half 0.2
        assert m["com_offset"] == pytest.approx(0.35 / 0.4)
        assert m["inside_fraction"] == 1.0
    if obj is OUTSIDE_SHORT:
        assert m["com_offset"] == pytest.approx(0.35 / 0.2) and m["inside_fraction"] == 0.0
    if obj is TALL_INSIDE:  # a cylinder standing 0.21 m tall in 0.15 m walls
        assert m["top_above_region"] == pytest.approx(0.21 - 0.15)


def test_features_keep_the_gap_between_inside_and_sticking_out():
    inside = object_measurements(INSIDE_LONG, _episode(INSIDE_LONG), SCENE)
    poking = _at((0.0, 0.0), 0.15 - 0.03 + 0.002)  # top 2 mm above the rim
    out = object_measurements(poking, _episode(poking), SCENE)
    assert 0.0 < out["top_above_region"] < 0.003 and out["inside_fraction"] < 1.0
    f_in, f_out = features([inside, out])
    assert f_in[1] == 0.0 and f_out[1] > 3 * 0.12  # protrusion: more than 3 eps apart


def test_cylinder_sample_points_fill_the_cylinder_and_its_surface():
    obj = {"shape": "cylinder", "size": [0.2, 0.2, 0.1], "position": [0.0, 0.0, 0.0],
           "orientation": [0.0, 0.0, 0.0, 1.0]}
    pts = object_sample_points(obj)
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert r.max() == pytest.approx(0.1) and r.min() == 0.0
    assert np.abs(pts[:, 2]).max() == pytest.approx(0.05)


def test_fixture_records_round_trip_and_fixed_ranges_draw_nothing():
    assert fixture_from_record(TOTE.to_record()) == TOTE
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    fixed = draw_fixture(SceneConfig(), 0.3, 0.01, rng)
    assert rng.bit_generator.state == state  # the default task draws what it always drew
    assert (fixed.half_x, fixed.half_y, fixed.yaw, fixed.base_z) == (0.5, 0.5, 0.3, 0.01)
    legacy = episode_fixture({"container_yaw": 0.3, "floor_z": 0.01}, SceneConfig())
    assert legacy == fixed


def test_a_fixed_table_size_pair_is_a_fixed_range():
    pair = _from_dict(SceneConfig, {"table_size": [1.8, 1.4]})
    ranges = _from_dict(SceneConfig, {"table_size": [[1.8, 1.8], [1.4, 1.4]]})
    assert pair == ranges and pair.table_size == ((1.8, 1.8), (1.4, 1.4))


def test_a_table_edge_margin_puts_the_fixture_anywhere_on_a_drawn_table():
    scene = load_scene("tote").scene
    margin = scene.table_edge_margin
    rng = np.random.default_rng(3)
    gaps, sizes = [], []
    for _ in range(300):
        fixture = draw_fixture(scene, float(rng.uniform(-math.pi, math.pi)), 0.0, rng)
        table = fixture.table
        # The table's centre in the fixture's frame: the table turns with the fixture.
        centre = fixture.to_frame(np.array([table.x, table.y, fixture.base_z]))[:2]
        outer = fixture.outer_half_footprint()   # walls, their lean and the lip
        gap = np.array([table.half_x, table.half_y]) - np.abs(centre) - outer
        gaps.append(gap.min())
        sizes.append((2 * table.half_x, 2 * table.half_y))
    gaps, sizes = np.array(gaps), np.array(sizes)
    assert gaps.min() >= margin - 1e-9          # always standing on the table
    assert np.mean(gaps < margin + 0.05) > 0.15  # often near an edge ...
    assert np.mean(gaps > 0.15) > 0.15           # ... often far from every edge
    for axis, (lo, hi) in enumerate(scene.table_size):  # sizes cover the drawn ranges
        assert lo <= sizes[:, axis].min() < lo + 0.1 and hi - 0.1 < sizes[:, axis].max() <= hi


def _camera_over(fixture: Fixture, distance=1.0, elevation=70.0, azimuth=20.0, f=500.0):
    target = fixture.centre()
    el, az = math.radians(elevation), math.radians(azimuth)
    pos = target + distance * np.array([math.cos(el) * math.cos(az),
                                        math.cos(el) * math.sin(az), math.sin(el)])
    return Camera(160, 120, f / 4, f / 4, 79.5, 59.5, pos, look_at(pos, target, azimuth))


def test_rectangular_container_labels_sit_where_the_geometry_is():
    episode = _episode(INSIDE_LONG, OUTSIDE_SHORT)
    boxes = scene_boxes(episode, ["success", "fell_outside"], SCENE, DEFAULT_TABLE)
    depth, labels, _ = render(boxes, TOTE.room_floor_z, _camera_over(TOTE))
    assert (labels == FIXTURE).sum() > 500
    for outcome in ("success", "fell_outside"):
        assert (labels == DEFAULT_TABLE.outcome_ids[outcome]).sum() > 20, outcome
    # Background is the table top around the tote and, beyond its edge, the room floor.
    cam = _camera_over(TOTE)
    v, u = np.nonzero((labels == 0) & np.isfinite(depth))
    rays = cam.rotation @ np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy,
                                    np.ones(len(u))])
    z = cam.position[2] + depth[v, u] * rays[2]
    assert np.sum(np.abs(z - TOTE.base_z) < 1e-3) > 1000      # the table top
    assert np.sum(np.abs(z - TOTE.room_floor_z) < 1e-3) > 100  # the floor past its edge


def test_straight_down_views_are_well_defined():
    rot = look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3), azimuth_deg=90.0)
    assert np.allclose(rot.T @ rot, np.eye(3)) and np.allclose(rot[:, 2], [0, 0, -1])
    rolled = look_at(np.array([1.0, 0.0, 1.0]), np.zeros(3), roll_deg=10.0)
    plain = look_at(np.array([1.0, 0.0, 1.0]), np.zeros(3))
    assert np.allclose(rolled[:, 2], plain[:, 2])  # roll turns about the optical axis only
    assert math.degrees(math.acos(rolled[:, 0] @ plain[:, 0])) == pytest.approx(10.0)


def test_cylinders_and_boxes_render_like_pybullets_own_ray_test():
    """Depth and which body is hit, per pixel, against pybullet's rayTestBatch on the same
    shapes (a lying and a tilted cylinder, a box)."""
    pb = pytest.importorskip("pybullet")
    shapes = [
        ("cylinder", (0.08, 0.08, 0.3), (0.0, 0.0, 0.08), (0.5, 0.5, 0.5, 0.5)),
        ("cylinder", (0.12, 0.12, 0.1), (0.2, 0.15, 0.1), (0.2, 0.0, 0.3, 0.93)),
        ("box", (0.1, 0.2, 0.05), (-0.2, 0.1, 0.025), (0.0, 0.0, 0.38, 0.92)),
    ]
    client = pb.connect(pb.DIRECT)
    try:
        solids, bodies = [], []
        for k, (shape, size, pos, quat) in enumerate(shapes):
            quat = tuple(np.asarray(quat) / np.linalg.norm(quat))
            if shape == "cylinder":
                col = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=size[0] / 2,
                                              height=size[2], physicsClientId=client)
            else:
                col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[s / 2 for s in size],
                                              physicsClientId=client)
            bodies.append(pb.createMultiBody(0, col, basePosition=pos, baseOrientation=quat,
                                             physicsClientId=client))
            obj = {"shape": shape, "size": list(size), "position": list(pos),
                   "orientation": list(quat)}
            solids.append(SceneBox(np.array(size) / 2, np.array(pos),
                                   _rotation(obj), 10 + k, cylinder=shape == "cylinder"))
        target = np.zeros(3)
        pos = np.array([0.6, -0.5, 0.7])
        cam = Camera(64, 48, 110.0, 110.0, 31.5, 23.5, pos, look_at(pos, target))
        depth, labels, _ = render(solids, -1.0, cam)
        u, v = np.meshgrid(np.arange(64), np.arange(48))
        rays = cam.rotation @ np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy,
                                        np.ones_like(u, float)]).reshape(3, -1)
        ends = pos[:, None] + 5.0 * rays
        hits = pb.rayTestBatch([list(pos)] * ends.shape[1], ends.T.tolist(),
                               physicsClientId=client)
    finally:
        pb.disconnect(client)
    body_to_label = {b: 10 + k for k, b in enumerate(bodies)}
    ours = labels.reshape(-1)
    theirs = np.array([body_to_label.get(h[0], 0) for h in hits])
    hit = theirs > 0
    assert hit.sum() > 300 and {11, 12} <= set(theirs[hit])  # both cylinders are in view
    # Same body on all but silhouette pixels.
    assert np.mean(ours[hit] == theirs[hit]) > 0.98
    # Depth along the optical axis: pybullet's hit fraction of a 5 m ray of length |ray|.
    # Bullet rounds convex shapes' edges by its collision margin, so a few edge pixels differ
    # by up to a centimetre; everywhere else the two agree to a millimetre.
    theirs_depth = np.array([h[2] for h in hits]) * 5.0
    same = hit & (ours == theirs)
    error = np.abs(depth.reshape(-1)[same] - theirs_depth[same])
    assert np.median(error) < 5e-4 and np.mean(error < 2e-3) > 0.93, np.percentile(error, 95)
    assert error.max() < 0.02


def _rotation(obj: dict) -> np.ndarray:
    from training.geometry import quat_to_matrix

    return quat_to_matrix(obj["orientation"])


def test_sensor_parameters_given_as_ranges_are_drawn_per_frame_and_recorded():
    import dataclasses

    from training.config import DatasetConfig, NoiseConfig
    from training.render import render_episode

    noise = NoiseConfig(sigma_disparity_px=(0.03, 0.12), speckle_max_radius_px=(1, 5),
                        max_range=(3.5, 4.5)).validate()
    cfg = dataclasses.replace(DatasetConfig(), noise=noise).validate()
    episode = {"episode": 0, "container_yaw": 0.2, "floor_z": 0.0, "objects": []}
    records = [render_episode({**episode, "episode": k}, [], cfg, 4, DEFAULT_TABLE)["record"]
               for k in range(4)]
    sigmas = [r["sensor"]["sigma_disparity_px"] for r in records]
    assert all(0.03 <= s <= 0.12 for s in sigmas) and len(set(sigmas)) == 4
    assert all(r["sensor"]["speckle_max_radius_px"] in range(1, 6) for r in records)
    assert all(r["sensor"]["baseline"] == 0.075 for r in records)  # fixed stays fixed
    again = render_episode({**episode, "episode": 2}, [], cfg, 4, DEFAULT_TABLE)
    assert again["record"]["sensor"] == records[2]["sensor"]
    fixed = render_episode(episode, [], DatasetConfig(), 4, DEFAULT_TABLE)["record"]
    assert "sensor" not in fixed  # a spec without ranges records (and draws) nothing new


def test_a_share_of_frames_gets_the_tof_sensor_and_camera_info_has_its_own_error():
    import dataclasses

    from training.config import CameraConfig, DatasetConfig, TofConfig
    from training.render import render_episode, reported_camera

    cfg = dataclasses.replace(
        DatasetConfig(), tof=TofConfig(share=0.5, sigma_1m=(0.001, 0.004)),
        camera=CameraConfig(info_focal_error=0.04, info_principal_error_px=4.0)).validate()
    episode = {"episode": 0, "container_yaw": 0.2, "floor_z": 0.0, "objects": []}
    records = [render_episode({**episode, "episode": k}, [], cfg, 2, DEFAULT_TABLE)["record"]
               for k in range(16)]
    models = [r["sensor"]["model"] for r in records]
    assert {"tof", "kinect_v1"} == set(models)
    assert all(0.001 <= r["sensor"]["sigma_1m"] <= 0.004 for r in records
               if r["sensor"]["model"] == "tof")
    for r in records:
        true, info = r["camera"], reported_camera(r)
        assert info is r["camera_info"] and info["fx"] == info["fy"]
        assert abs(info["fx"] / true["fx"] - 1) <= 0.04 and info["fx"] != true["fx"]
        assert abs(info["cx"] - true["cx"]) <= 4.0 and abs(info["cy"] - true["cy"]) <= 4.0
    again = render_episode({**episode, "episode": 5}, [], cfg, 2, DEFAULT_TABLE)["record"]
    assert again["sensor"] == records[5]["sensor"]
    assert again["camera_info"] == records[5]["camera_info"]
    plain = render_episode(episode, [], DatasetConfig(), 2, DEFAULT_TABLE)["record"]
    assert "camera_info" not in plain and reported_camera(plain) is plain["camera"]


def test_a_tilted_support_leans_gravity_and_looks_tilted_to_a_level_camera():
    tilted = Fixture(**SQUARE, tilt_deg=6.0, tilt_azimuth_deg=40.0)
    g = np.array(tilted.gravity())
    assert np.linalg.norm(g) == pytest.approx(9.81)
    assert math.degrees(math.acos(-g[2] / 9.81)) == pytest.approx(6.0)
    assert Fixture(**SQUARE).gravity() == [0, 0, -9.81]
    # A camera straight down (against the true vertical) sees the floor inclined by 6 deg.
    from training.config import CameraConfig
    from training.render import draw_camera

    cam_cfg = CameraConfig(elevation_deg=(90.0, 90.0), distance=(2.0, 2.0), target_offset=0.0)
    camera, _ = draw_camera(cam_cfg, tilted, np.random.default_rng(0))
    episode = {"container_yaw": 0.0, "floor_z": 0.0, "fixture": tilted.to_record(),
               "objects": []}
    depth, labels, _ = render(scene_boxes(episode, [], SCENE, DEFAULT_TABLE), tilted.room_floor_z,
                              camera)
    v, u = np.nonzero(labels == 0)
    x = (u - camera.cx) / camera.fx * depth[v, u]
    y = (v - camera.cy) / camera.fy * depth[v, u]
    a = np.column_stack([x, y, np.ones_like(x)])
    gx, gy, _ = np.linalg.lstsq(a, depth[v, u], rcond=None)[0]  # z = gx x + gy y + c
    assert math.degrees(math.atan(math.hypot(gx, gy))) == pytest.approx(6.0, abs=0.05)
