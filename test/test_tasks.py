"""Tasks are specs: the shelf board's geometry, discovery's descriptors and label tables, and
the shelf spec end to end on a small run (training/fixture.py, discover.py, scenes/)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from task_outcome_ros.labels import BACKGROUND, DEFAULT_TABLE, FIXTURE, LabelTable
from training.config import ConfigError, DatasetConfig, DiscoverConfig
from training.discover import (
    DiscoveryError,
    cluster,
    dbscan_collapsed,
    describe_cluster,
    label_table,
)
from training.fixture import Board, fixture_from_record
from training.geometry import geometric_outcome, object_measurements
from training.hard_cases import object_gap, object_tags
from training.render import Camera, look_at, render, scene_boxes
from training.scene import SCENES_DIR, load_scene
from training.simulate import draw_episode, vertical_half_extent

pytestmark = pytest.mark.unit

SHELF = load_scene("shelf")
# A 0.9 x 0.3 m board, its top 0.8 m up, on legs, turned by 20 degrees, front edge at -y.
BOARD = Board(half_x=0.45, half_y=0.15, height=0.8, thickness=0.025, clearance=0.4,
              x=0.2, y=-0.1, yaw=math.radians(20), base_z=0.0)


def _episode(*objects: dict) -> dict:
    return {"container_yaw": BOARD.yaw, "floor_z": 0.0, "fixture": BOARD.to_record(),
            "objects": list(objects)}


def _at(local_x: float, local_y: float, z: float, size=(0.1, 0.1, 0.1)) -> dict:
    """An upright box centred at board-frame (x, y), its centre z above the floor."""
    world = BOARD.to_world([local_x, local_y, z])
    return {"shape": "box", "size": list(size), "position": world.tolist(),
            "orientation": [0.0, 0.0, math.sin(BOARD.yaw / 2), math.cos(BOARD.yaw / 2)]}


ON_BOARD = _at(0.1, 0.0, 0.85)
OVERHANGING = _at(0.0, -0.15 + 0.03, 0.85)        # 2 cm of its 10 cm beyond the front edge
FALLEN = _at(0.0, -0.45, 0.05)                    # on the floor in front
UNDER = _at(0.0, 0.0, 0.05)                       # on the floor, under the board
CASES = [(ON_BOARD, "inside"), (OVERHANGING, "partly_inside"), (FALLEN, "outside"),
         (UNDER, "outside")]


@pytest.mark.parametrize("obj,expected", CASES, ids=["on", "overhanging", "fallen", "under"])
def test_the_shelf_yardstick_judges_the_footprint(obj, expected):
    m = object_measurements(obj, _episode(obj), SHELF.scene)
    assert geometric_outcome(m, "footprint") == expected
    if obj is OVERHANGING:
        assert m["reach_beyond_footprint"] == pytest.approx(0.02, abs=1e-6)
        assert object_gap(m, "footprint") == pytest.approx(0.02, abs=1e-6)
    if obj is UNDER:  # over the footprint, but fallen below the board: not inside it
        assert m["footprint_fraction"] == 1.0 and m["inside_fraction"] == 0.0


def test_board_records_round_trip_and_its_solids_stand_on_the_support():
    assert fixture_from_record(BOARD.to_record()) == BOARD
    region = BOARD.region()
    assert (region.bottom, region.top, region.edge) == pytest.approx((0.8, 1.2, 0.025))
    board, *legs = BOARD.solid_boxes()
    assert len(legs) == 4 and board[1][2] + board[0][2] == pytest.approx(0.8)
    assert all(leg[1][2] - leg[0][2] == pytest.approx(0.0) for leg in legs)
    on_wall = fixture_from_record({**BOARD.to_record(), "wall_mounted": True})
    assert on_wall.solid_boxes() == [board] and len(on_wall.background_boxes()) == 1


def test_shelf_labels_sit_on_the_board_and_the_objects():
    """Rendered from in front (-y, 30 degrees up): the board is the fixture, the wall behind a
    wall-mounted board is background, each object has its outcome's id."""
    table = LabelTable.build("shelf", [("on_shelf", False), ("fell_off", True),
                                       ("hanging_over_edge", True)])
    on_wall = fixture_from_record({**BOARD.to_record(), "wall_mounted": True})
    episode = {**_episode(ON_BOARD, FALLEN), "fixture": on_wall.to_record()}
    boxes = scene_boxes(episode, ["on_shelf", "fell_off"], SHELF.scene, table)
    target = on_wall.centre()
    az = math.degrees(on_wall.yaw) + 270.0
    el = math.radians(30.0)
    position = target + 1.8 * np.array([math.cos(el) * math.cos(math.radians(az)),
                                        math.cos(el) * math.sin(math.radians(az)),
                                        math.sin(el)])
    camera = Camera(640, 480, 560.0, 560.0, 319.5, 239.5, position,
                    look_at(position, target, az, 0.0))
    depth, labels, _ = render(boxes, on_wall.room_floor_z, camera)
    assert (labels == FIXTURE).sum() > 2000
    for name in ("on_shelf", "fell_off"):
        assert (labels == table.outcome_ids[name]).sum() > 200, name
    # The wall behind the board is background, and nearer than the floor there would be.
    wall = (labels == BACKGROUND) & (np.arange(480)[:, None] < 100)
    assert wall.sum() > 1000 and np.nanmax(depth[wall]) < 4.0


def test_placements_put_objects_just_above_the_board_near_its_front_edge():
    rng = np.random.default_rng(3)
    for k in range(20):
        draw = draw_episode(SHELF.scene, rng, np.random.default_rng(k))
        region = draw.fixture.region()
        for shape, size, pos, q in zip(draw.shapes, draw.sizes, draw.start_positions,
                                       draw.start_orientations):
            local = draw.fixture.to_frame(np.asarray(pos))
            lowest = local[2] - vertical_half_extent(shape, size, q)
            assert region.bottom - 1e-9 <= lowest  # never inside the board
            if lowest <= region.bottom + 0.05 + 1e-9:  # not raised to clear another object
                assert -0.06 - 1e-9 <= local[1] + region.half_y <= 0.14 + 1e-9
            assert abs(local[0]) <= region.half_x - SHELF.scene.release_margin + 1e-9


def _members(descriptor: str, n: int = 20) -> list[dict]:
    base = {"inside": (1.0, 0.3, 0.0), "outside": (0.0, 2.0, 1.0),
            "partly_inside": (0.6, 0.9, 0.0)}[descriptor]
    return [{"inside_fraction": base[0], "com_offset": base[1], "com_beyond_outer": base[2],
             "com_beyond_edge": -0.5 if base[0] else 2.0} for _ in range(n)]


def test_descriptors_and_the_label_table_follow_the_clusters():
    for descriptor in ("inside", "outside", "partly_inside"):
        assert describe_cluster(_members(descriptor)) == descriptor
    cfg = DatasetConfig()
    assert label_table({"inside", "outside", "partly_inside"}, cfg) == DEFAULT_TABLE
    # Found only two: the success-like one first, ids follow what was found.
    two = label_table({"partly_inside", "outside"}, cfg)
    assert two.outcome_names == ("fell_outside", "stuck_on_rim") and two.failures == \
        ("fell_outside", "stuck_on_rim")
    shelf = label_table({"inside", "outside", "partly_inside"}, SHELF)
    assert shelf.classes == ("background", "shelf", "on_shelf", "fell_off",
                             "hanging_over_edge")


def test_two_clusters_that_look_alike_are_an_error_not_a_merge():
    # Two dense, well separated groups that are both entirely inside.
    far = [{**m, "com_beyond_edge": -1.0} for m in _members("inside", 40)]
    near = [{**m, "com_beyond_edge": 0.0} for m in _members("inside", 40)]
    with pytest.raises(DiscoveryError, match="2 clusters are 'inside'"):
        cluster(far + near, DatasetConfig())


def test_dbscan_on_collapsed_copies_gives_dbscans_own_answer():
    from sklearn.cluster import DBSCAN

    rng = np.random.default_rng(5)
    # Discovery's shape: two exact spikes of many copies, a spread cluster between them,
    # and scattered points that end up as noise.
    x = np.concatenate([np.tile([-1.0, 0.0], (300, 1)), np.tile([2.0, 1.0], (200, 1)),
                        rng.normal([0.5, 0.5], 0.03, (150, 2)), rng.uniform(-1, 2, (40, 2))])
    x = x[rng.permutation(len(x))]
    for eps, min_samples in ((0.12, 10), (0.05, 30), (0.3, 5)):
        expected = DBSCAN(eps=eps, min_samples=min_samples).fit(x)
        labels, core = dbscan_collapsed(x, eps, min_samples)
        np.testing.assert_array_equal(labels, expected.labels_)
        assert set(np.flatnonzero(core)) == set(expected.core_sample_indices_)
    assert len(set(labels)) > 2  # the clusters and the noise this test is about exist


def test_outcome_names_are_validated():
    with pytest.raises(ConfigError, match="distinct descriptors"):
        DiscoverConfig(outcome_names=(("inside", "a"), ("on_top", "b"))).validate()
    with pytest.raises(ConfigError, match="distinct lower-case words"):
        DiscoverConfig(outcome_names=(("inside", "same"), ("outside", "same"))).validate()
    with pytest.raises(ConfigError, match="yardstick_inside"):
        DiscoverConfig(yardstick_inside="rim").validate()


def test_hard_cases_follow_the_tasks_boundary():
    barely = _at(0.0, -0.15 + 0.04, 0.85)  # 1 cm over the edge
    m = object_measurements(barely, _episode(barely), SHELF.scene)
    assert object_tags(m, "footprint") == {"near_boundary"}  # within the 2.5 cm edge
    assert object_tags(object_measurements(ON_BOARD, _episode(ON_BOARD), SHELF.scene),
                       "footprint") == set()
    assert object_gap(m, "top") == pytest.approx(abs(m["top_above_region"]))


# Digests of the first 30 episodes' draws (physics, fixture, camera) of seed 0, floats rounded
# to 1e-9 so that the last bits of a CPU's vectorised maths do not count (the unrounded
# digests of commit d836a58 differed on a machine of another CPU). Made by the package at
# 0.8.0: the default task's data, and the tote spec's before it drew its table ("tote-0.8.0":
# one 1.8 x 1.4 m table, the tote within +-5 cm of its centre), must stay what they were.
DRAW_DIGESTS = {"default": "483f8708e4915b0a", "tote-0.8.0": "62ac15bd3b49268b"}


def _rounded(value):
    if isinstance(value, float):
        return round(value, 9)
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return value


@pytest.mark.parametrize("spec", sorted(DRAW_DIGESTS))
def test_the_default_and_older_tote_tasks_draw_what_they_always_drew(spec, tmp_path):
    import hashlib
    import json
    from dataclasses import asdict

    from training.render import draw_camera
    from training.seeding import episode_rng

    if spec == "tote-0.8.0":  # a spec with a fixed (x, y) table and table_offset still loads
        data = yaml.safe_load((SCENES_DIR / "tote.yaml").read_text())
        data["scene"].pop("table_edge_margin")
        for newer in ("wall_flare_deg", "lip_width", "handle_hole_share", "plain_wall_share",
                      "neighbour_share"):
            data["scene"].pop(newer, None)
        data["scene"].update(table_size=[1.8, 1.4], table_offset=0.05)
        (tmp_path / "tote.yaml").write_text(yaml.safe_dump(data))
        cfg = load_scene(tmp_path / "tote.yaml")
    else:
        cfg = load_scene(spec)
    digest = hashlib.sha256()
    for i in range(30):
        d = draw_episode(cfg.scene, episode_rng(0, i, "simulate"), episode_rng(0, i, "fixture"))
        fixture = {k: v for k, v in asdict(d.fixture).items() if k != "kind"}
        walls = [fixture.pop(k) for k in ("flare_deg", "lip_width", "handle_holes")
                 if k in fixture]
        assert not any(walls)   # these specs draw upright walls without lip or holes
        cam, _ = draw_camera(cfg.camera, d.fixture, episode_rng(0, i, "render"))
        record = [d.container_yaw, d.floor_z, d.friction, d.restitution, d.sizes, d.masses,
                  d.start_positions, d.start_orientations, fixture, d.shapes,
                  cam.position.tolist(), cam.rotation.tolist(), cam.fx, cam.cx, cam.cy]
        plain = json.loads(json.dumps(record))  # numpy scalars and tuples as plain JSON
        digest.update(json.dumps(_rounded(plain), sort_keys=True).encode())
    assert digest.hexdigest()[:16] == DRAW_DIGESTS[spec]


def test_fixture_kinds_and_release_modes_are_checked_together(tmp_path):
    import dataclasses

    board = SHELF.scene
    for change, match in (({"board_height": (0.02, 0.5)}, "board_height"),
                          ({"place_edge_offset": (0.0, 0.3)}, "place_edge_offset"),
                          ({"fixture": "open_box"}, "release_mode = 'place'")):
        with pytest.raises(ConfigError, match=match):
            dataclasses.replace(board, **change).validate()
    with pytest.raises(ConfigError, match="reserved|none of"):
        DiscoverConfig(outcome_names=(("inside", "iou"),)).validate()
    # A board spec must give its outcomes words (the defaults are the container task's).
    spec = tmp_path / "bare_shelf.yaml"
    spec.write_text("name: bare_shelf\nscene: {fixture: board, release_mode: place}\n"
                    "camera: {azimuth_frame: fixture}\n")
    with pytest.raises(ConfigError, match="discover.outcome_names"):
        load_scene(spec)
