"""Episodes in which nothing is placed (``scene.empty_share``): the fixture, its scenery and the
camera as drawn, no object, no outcome pixel, and every other episode simulated exactly as
a spec without the share simulates it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from task_outcome_ros.labels import BACKGROUND, FIXTURE, IGNORE
from training.config import ConfigError
from training.discover import DiscoveryError, cluster, label_table
from training.overlaps import object_id_image, working_camera
from training.render import render_episode
from training.scene import load_scene
from training.simulate import World, is_empty_episode, simulate_episode

pytestmark = pytest.mark.unit

RUN_SEED = 5


def _spec(task="tote", **fields):
    base = load_scene(task)
    return dataclasses.replace(base, scene=dataclasses.replace(base.scene, **fields))


def _simulated(spec, episode: int) -> dict:
    """One episode simulated in a world of its own."""
    world = World(spec.scene)
    try:
        return simulate_episode(world, RUN_SEED, episode)
    finally:
        world.close()


def test_a_spec_without_the_share_never_empties_an_episode():
    scene = _spec().scene
    assert scene.empty_share == 0.0
    assert not any(is_empty_episode(scene, RUN_SEED, i) for i in range(200))


def test_the_share_empties_about_that_share_of_episodes():
    scene = _spec(empty_share=0.25).scene
    emptied = sum(is_empty_episode(scene, RUN_SEED, i) for i in range(2000))
    assert 400 < emptied < 600      # 500 expected, sd ~19


@pytest.mark.parametrize("task", ["default", "tote"])
def test_empty_episodes_hold_nothing_and_the_others_are_unchanged(task):
    """The tote spec builds a world per episode (its geometry is drawn); the default spec
    reuses one, so there an emptied episode also leaves the world's history different."""
    with_share, without = _spec(task, empty_share=0.5).scene, _spec(task).scene
    worlds = World(with_share), World(without)
    try:
        emptied = 0
        for i in range(10):
            a, b = (simulate_episode(w, RUN_SEED, i) for w in worlds)
            if is_empty_episode(with_share, RUN_SEED, i):
                emptied += 1
                assert a["objects"] == [] and b["objects"]
                assert a["sim_time"] == 0.0 and not a["timed_out"]
                # The fixture and support as the episode drew them.
                assert a["fixture"] == b["fixture"] and a["floor_z"] == b["floor_z"]
            else:
                assert a == b
        assert 0 < emptied < 10
    finally:
        for w in worlds:
            w.close()


def test_an_empty_episode_renders_the_fixture_and_no_outcome():
    spec = _spec(empty_share=0.5)
    table = label_table({"inside", "outside", "partly_inside"}, spec)
    episode = next(i for i in range(50) if is_empty_episode(spec.scene, RUN_SEED, i))
    record = _simulated(spec, episode)
    assert record["objects"] == []
    shot = render_episode(record, [], spec, RUN_SEED, table)
    assert set(np.unique(shot["labels"])) <= {BACKGROUND, FIXTURE, IGNORE}   # IGNORE: no depth
    assert (shot["labels"] == FIXTURE).sum() > 1000      # the tote is in view
    assert not any(shot["record"]["present"].values())
    assert not any(shot["record"]["pixel_counts"].values())
    # The frame's objects cast with ids of their own (training/overlaps.py): none.
    camera = working_camera(shot["record"]["camera"], (160, 120))
    assert not object_id_image(record, [], spec.scene, table, camera).any()


def test_a_run_of_only_empty_episodes_is_a_clear_discovery_error():
    with pytest.raises(DiscoveryError, match="no objects to cluster"):
        cluster([], load_scene("tote"))


@pytest.mark.parametrize("share", [-0.1, 0.6])
def test_an_empty_share_outside_zero_to_a_half_is_refused(share):
    with pytest.raises(ConfigError, match="empty_share"):
        _spec(empty_share=share).scene.validate()


# Empty cells (``scene.empty_cell_share``): the frame rendered with the fixture and the objects
# left out, a cell with nothing to judge, unlike the empty episodes above.

def test_a_cell_share_of_zero_never_empties_a_frame_and_a_share_does():
    from training.render import drawn_empty

    never = _spec(empty_cell_share=0.0).scene
    assert not any(drawn_empty(never, RUN_SEED, i) for i in range(200))
    scene = _spec(empty_cell_share=0.25).scene
    emptied = sum(drawn_empty(scene, RUN_SEED, i) for i in range(2000))
    assert 400 < emptied < 600      # 500 expected, sd ~19


@pytest.mark.parametrize("task", ["default", "tote"])
def test_an_empty_cell_is_all_background_and_the_other_frames_are_unchanged(task):
    from training.render import drawn_empty

    with_share, without = _spec(task, empty_cell_share=0.5), _spec(task, empty_cell_share=0.0)
    table = label_table({"inside", "outside", "partly_inside"}, without)
    frames = range(12)
    emptied = [i for i in frames if drawn_empty(with_share.scene, RUN_SEED, i)]
    assert 0 < len(emptied) < len(frames)
    for i in frames:
        record = _simulated(without, i)
        outcomes = ["success"] * len(record["objects"])
        shot = render_episode(record, outcomes, with_share, RUN_SEED, table)
        plain = render_episode(record, outcomes, without, RUN_SEED, table)
        if i in emptied:
            assert set(np.unique(shot["labels"])) <= {BACKGROUND, IGNORE}
            assert shot["record"]["emptied"] and not any(shot["record"]["present"].values())
            assert shot["record"]["camera"] == plain["record"]["camera"]   # the same view
            assert (plain["labels"] == FIXTURE).sum() > 1000               # the fixture gone
        else:
            assert "emptied" not in shot["record"]
            np.testing.assert_array_equal(shot["depth"], plain["depth"])
            np.testing.assert_array_equal(shot["labels"], plain["labels"])


@pytest.mark.parametrize("share", [-0.1, 0.6])
def test_an_empty_cell_share_outside_zero_to_a_half_is_refused(share):
    with pytest.raises(ConfigError, match="empty_cell_share"):
        _spec(empty_cell_share=share).scene.validate()
