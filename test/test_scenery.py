"""Scenery nobody placed (training/scenery.py): neighbouring copies of the fixture, drawn per
frame at render time, all background, never where a simulated object lies."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from task_outcome_ros.labels import BACKGROUND
from training.config import ConfigError
from training.discover import label_table
from training.fixture import first_fixture
from training.render import draw_camera, episode_scene, render, render_episode
from training.scene import load_scene
from training.scenery import draw_neighbours

pytestmark = pytest.mark.unit


def _scene(**fields):
    scene = load_scene("tote").scene
    return dataclasses.replace(scene, **fields)


def test_a_spec_without_neighbours_draws_nothing_and_takes_nothing_from_the_stream():
    rng = np.random.default_rng(0)
    solids, drawn = draw_neighbours(first_fixture(_scene(neighbour_share=0.0)),
                                    _scene(neighbour_share=0.0), [], rng)
    assert solids == [] and drawn is None
    assert rng.random() == np.random.default_rng(0).random()


def test_neighbours_stand_beside_the_fixture_in_a_row_with_their_contents():
    scene = _scene(neighbour_share=1.0, neighbour_count=(2, 2), neighbour_gap=(0.05, 0.05),
                   neighbour_contents=(3, 3))
    fixture = first_fixture(scene)
    half = fixture.outer_half_footprint()
    solids, drawn = draw_neighbours(fixture, scene, [], np.random.default_rng(3))
    assert len(drawn["neighbours"]) == 2
    per_neighbour = len(fixture.solid_boxes()) + 3
    assert len(solids) == 2 * per_neighbour
    for n in drawn["neighbours"]:
        offset = np.abs(n["offset"])
        axis = int(np.argmax(offset / half))
        # Edge to edge 5 cm apart along one axis, nearly aligned along the other.
        assert offset[axis] == pytest.approx(2 * half[axis] + 0.05, abs=1e-3)
        assert offset[1 - axis] <= 0.1 * half[1 - axis] + 1e-3
    # Each neighbour: the fixture's solids, then its contents, resting on its floor inside
    # its walls.
    region = fixture.region()
    walls = len(fixture.solid_boxes())
    for k, n in enumerate(drawn["neighbours"]):
        contents = solids[k * per_neighbour + walls:(k + 1) * per_neighbour]
        assert len(contents) == 3
        for solid in contents:
            local = fixture.to_frame(solid.centre)
            assert local[2] == pytest.approx(region.bottom + solid.half[2], abs=1e-6)
            inside = np.abs(local[:2] - np.array(n["offset"]))
            assert np.all(inside + np.hypot(*solid.half[:2]) <= [region.half_x, region.half_y])


def test_no_neighbour_stands_where_a_simulated_object_came_to_rest():
    scene = _scene(neighbour_share=1.0, neighbour_count=(4, 4), neighbour_gap=(0.0, 0.0))
    fixture = first_fixture(scene)
    half = fixture.outer_half_footprint()
    # One object on the table just beyond the +x wall: that side must stay empty.
    beside = {"position": [float(half[0] + 0.1), 0.0, 0.05], "size": [0.06, 0.06, 0.06]}
    for seed in range(20):
        _, drawn = draw_neighbours(fixture, scene, [beside], np.random.default_rng(seed))
        offsets = [n["offset"] for n in drawn["neighbours"]]
        assert len(offsets) == 3 and not any(o[0] > half[0] for o in offsets)


def test_a_rendered_neighbour_only_ever_adds_background():
    """The same view with and without neighbours (clean renders): every pixel they change is
    background, the frame records what was drawn, and the fixture stays in view."""
    base = load_scene("tote")
    with_row = dataclasses.replace(base, scene=dataclasses.replace(
        base.scene, neighbour_share=1.0, neighbour_count=(2, 2), neighbour_contents=(4, 4)))
    without = dataclasses.replace(base, scene=dataclasses.replace(base.scene,
                                                                  neighbour_share=0.0))
    table = label_table({"inside", "outside"}, base)
    changed_total = 0
    for index in range(4):
        fixture = first_fixture(base.scene, yaw=0.3 * index)
        episode = {"episode": index, "fixture": fixture.to_record(), "objects": []}
        camera, _ = draw_camera(base.camera, fixture, np.random.default_rng(index))
        (boxes_a, drawn_a), (boxes_b, drawn_b) = (
            episode_scene(episode, [], cfg, 0, table) for cfg in (with_row, without))
        assert drawn_a["neighbours"] and drawn_b is None
        depth_a, labels_a, _ = render(boxes_a, fixture.room_floor_z, camera)
        depth_b, labels_b, _ = render(boxes_b, fixture.room_floor_z, camera)
        changed = (depth_a != depth_b) & (np.isfinite(depth_a) | np.isfinite(depth_b))
        assert (labels_a[changed] == BACKGROUND).all()
        assert (labels_a[~changed] == labels_b[~changed]).all()
        changed_total += int(changed.sum())
    assert changed_total > 1000      # the neighbours were in view at all
    record = render_episode(episode, [], with_row, 0, table)["record"]
    assert record["scenery"] == drawn_a


@pytest.mark.parametrize("fields, error", [
    ({"neighbour_share": 1.5}, "neighbour_share"),
    ({"neighbour_count": (0, 2)}, r"neighbour_count\[0\]"),
    ({"neighbour_count": (2, 1)}, "min must not exceed max"),
    ({"neighbour_contents": (0, 2.5)}, "whole number"),
    ({"neighbour_gap": (0.2, 0.1)}, "min must not exceed max"),
    ({"neighbour_share": 0.5, "fixture": "board", "wall_flare_deg": (0.0, 0.0),
      "lip_width": (0.0, 0.0), "handle_hole_share": 0.0, "plain_wall_share": 0.0},
     "copies of an open box"),
])
def test_bad_neighbour_fields_are_refused(fields, error):
    with pytest.raises(ConfigError, match=error):
        _scene(**fields).validate()
