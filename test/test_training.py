"""Training and evaluation: the paper's metric on hand-made labels, a short real training run
on a freshly generated dataset, and a proof of life of the shipped checkpoint."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import make_checkpoint

from task_outcome_ros.fragments import FRAGMENT_MAX_PIXELS
from task_outcome_ros.labels import DEFAULT_TABLE, FIXTURE, outcomes_present, presence_scores
from task_outcome_ros.model import DEFAULT_NORMALISATION, check_normalisation
from training.config import ConfigError, DiscoverConfig, TrainConfig
from training.dataset import load_cache, load_manifest
from training.discover import load_outcomes
from training.evaluate import confusion, evaluate
from training.hard_cases import episode_hard_cases

# The default task's outcome ids (docs/interface.md §3).
SUCCESS, FELL_OUTSIDE, STUCK_ON_RIM = (DEFAULT_TABLE.outcome_ids[name] for name in
                                      DEFAULT_TABLE.outcome_names)


task_word = DiscoverConfig().outcome_name  # descriptor -> the default task's word

pytestmark = pytest.mark.pipeline


def test_presence_scores_on_hand_made_presence():
    truth = np.array([[1, 0, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1]], bool)
    pred = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [1, 1, 1]], bool)
    s = presence_scores(truth, pred)
    assert s["image_all_correct"] == pytest.approx(0.5)
    assert s["fell_outside"]["presence_recall"] == 0.0        # its one true image missed
    assert s["fell_outside"]["presence_precision"] == 0.0     # its one prediction wrong
    assert s["success"]["presence_recall"] == 1.0
    assert s["stuck_on_rim"]["presence_precision"] == 1.0


def test_presence_rule_and_confusion_on_hand_made_label_images():
    truth = np.zeros((480, 640), np.uint8)
    truth[100:200, 100:200] = FIXTURE
    truth[120:130, 120:125] = SUCCESS          # 50 px: exactly the threshold -> present
    truth[300:306, 300:308] = FELL_OUTSIDE     # 48 px: below it -> absent
    truth[0, 0] = 255
    present = outcomes_present(truth)
    assert present == {"success": True, "fell_outside": False, "stuck_on_rim": False}
    pred = truth.copy()
    pred[0, 0] = STUCK_ON_RIM                  # an ignored pixel never counts
    pred[300:306, 300:308] = 0
    conf = confusion(truth, pred, DEFAULT_TABLE.num_classes)
    assert conf.sum() == truth.size - 1
    assert conf[FELL_OUTSIDE, 0] == 48 and conf[STUCK_ON_RIM].sum() == 0
    # Half-size image: the threshold scales with the pixel count (50 * 1/4 -> 12.5 -> 12).
    small = np.zeros((240, 320), np.uint8)
    small[:3, :4] = SUCCESS
    assert outcomes_present(small)["success"] is True


def test_train_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="train.epochs"):
        TrainConfig(epochs=0).validate()
    with pytest.raises(ConfigError, match="train.device"):
        TrainConfig(device="tpu").validate()
    with pytest.raises(ConfigError, match="train.channels_last"):
        TrainConfig(channels_last=1).validate()
    with pytest.raises(ConfigError, match="train.camera_intrinsics"):
        TrainConfig(camera_intrinsics="yes").validate()
    with pytest.raises(ConfigError, match="train.nearest_height"):
        TrainConfig(nearest_height=1).validate()
    with pytest.raises(ConfigError, match="train.max_width"):
        TrainConfig(max_width=4).validate()
    with pytest.raises(ConfigError, match="train.near_boundary_weight"):
        TrainConfig(near_boundary_weight=0.5).validate()
    for bad in (8, 1, 65, 15.0, True, 0.0, False):
        with pytest.raises(ConfigError, match="train.relief_window_px"):
            TrainConfig(relief_window_px=bad).validate()
    for good in (0, 3, 15):
        assert TrainConfig(relief_window_px=good).validate().relief_window_px == good
    for bad in (2, 17, 3.0, True):
        with pytest.raises(ConfigError, match="train.relief_smoothing_px"):
            TrainConfig(relief_window_px=15, relief_smoothing_px=bad).validate()
    with pytest.raises(ConfigError, match="relief_smoothing_px = 3 needs relief_window_px"):
        TrainConfig(relief_smoothing_px=3).validate()
    smooth = TrainConfig(relief_window_px=15, relief_smoothing_px=3).validate()
    with pytest.raises(ConfigError, match="relief_base_px = 7 needs relief_window_px"):
        TrainConfig(relief_base_px=7).validate()
    with pytest.raises(ConfigError, match="train.relief_base_px"):
        TrainConfig(relief_window_px=15, relief_base_px=4).validate()
    with pytest.raises(ConfigError, match="relief_noise_sds = 5.0 needs relief_smoothing_px"):
        TrainConfig(relief_window_px=15, relief_noise_sds=5.0).validate()
    with pytest.raises(ConfigError, match="train.relief_noise_sds"):
        TrainConfig(relief_window_px=15, relief_smoothing_px=3, relief_noise_sds=11.0).validate()
    with pytest.raises(ConfigError, match="relief_beneath_support needs relief_window_px"):
        TrainConfig(relief_beneath_support=True).validate()
    with pytest.raises(ConfigError, match="relief_beneath_support = 1: expected true/false"):
        TrainConfig(relief_window_px=15, relief_beneath_support=1).validate()
    assert TrainConfig(relief_window_px=15, relief_beneath_support=True).validate()
    assert TrainConfig(relief_window_px=15, relief_smoothing_px=3,
                       relief_noise_sds=5.0).validate().relief_noise_sds == 5.0
    for off in (0, 0.0):
        assert TrainConfig(relief_noise_sds=off).validate().relief_noise_sds == off
    assert smooth.relief_smoothing_px == 3
    with pytest.raises(ConfigError, match="train.full_size_head = 8 needs space_to_depth 2"):
        TrainConfig(full_size_head=8).validate()
    with pytest.raises(ConfigError, match="train.full_size_head"):
        TrainConfig(space_to_depth=2, full_size_head=33).validate()
    assert TrainConfig(space_to_depth=2, full_size_head=8).validate().model_args[
        "full_size_head"] == 8
    # Unused, later options stay out of model_args: older runtimes can build the network.
    assert not {"space_to_depth", "full_size_head"} & set(TrainConfig().model_args)


def test_the_networks_width_and_depth_come_from_the_command_line():
    from task_outcome_ros.model import build_model
    from training.__main__ import build_parser, resolve_train_config

    args = build_parser().parse_args(["train", "--base-width", "4", "--levels", "6",
                                      "--input-size", "320", "240"])
    config = resolve_train_config(args)
    assert (config.model_args["base_width"], config.model_args["levels"]) == (4, 6)
    model = build_model(config.model_args).eval()
    assert model.stride == 64
    with torch.no_grad():  # 240 rows are padded to 256 and cropped back
        assert model(torch.zeros(1, 3, 240, 320)).shape == (1, 5, 240, 320)
    defaults = resolve_train_config(build_parser().parse_args(["train"])).model_args
    assert (defaults["base_width"], defaults["levels"]) == (8, 5)
    with pytest.raises(ConfigError, match="train.levels"):
        TrainConfig(levels=7).validate()
    wide = resolve_train_config(build_parser().parse_args(
        ["train", "--base-width", "4", "--levels", "6", "--head-width", "8"]))
    assert build_model(wide.model_args).head.in_channels == 8
    assert "head_width" not in defaults   # unused: older runtimes still build the network
    with pytest.raises(ConfigError, match="train.head_width = 4 must exceed base_width"):
        TrainConfig(base_width=4, head_width=4).validate()


def test_epoch_order_is_a_permutation_or_draws_in_proportion_to_the_weights():
    from training.train import epoch_order

    gen = torch.Generator().manual_seed(0)
    assert sorted(epoch_order(50, None, gen)) == list(range(50))
    weights = np.repeat([1.0, 3.0, 0.0], 2000)           # thirds: normal, favoured, never
    order = epoch_order(6000, weights, gen)
    assert len(order) == 6000 and order.max() < 4000     # weight 0 is never drawn
    assert 0.72 < np.mean(order >= 2000) < 0.78          # 3 : 1 -> 75 % from the favoured


def test_augmentation_keeps_labels_and_redraws_noise_at_the_sensors_level():
    from training.augment import augment
    from training.redrawn_noise import SENSOR_NOISE_PER_Z2

    gen = torch.Generator().manual_seed(0)
    depth = torch.full((64, 120, 160), 2.0)
    labels = torch.zeros((64, 120, 160), dtype=torch.long)
    labels[:, 40:80, 60:100] = SUCCESS
    out, valid, out_labels = augment(depth.clone(), torch.ones_like(depth), labels, gen)[:3]
    # Labels only move with the image (mirror, shift): same object area, nothing relabelled.
    assert set(out_labels.unique().tolist()) <= {0, SUCCESS, 255}
    assert ((out_labels == SUCCESS).sum((1, 2)) == 40 * 40).all()
    inner = out[:, 10:-10, 10:-10]
    sd = (inner - inner.mean((1, 2), keepdim=True)).std((1, 2))
    # At 160 x 120 one working pixel averages 16 sensor pixels: sd / z^2 at most 0.0016 / 4.
    ceiling = SENSOR_NOISE_PER_Z2 / 4 * 2.0 ** 2
    assert sd.max() <= 1.1 * ceiling and sd.min() < 0.3 * ceiling and sd.mean() > 0.3 * ceiling


def test_augmentation_moves_the_nearest_depths_with_the_image_and_leaves_the_rest_alone():
    from training.augment import augment

    depth = torch.rand(6, 30, 40) + 1.0
    labels = torch.randint(0, 4, (6, 30, 40))
    args = (torch.ones_like(depth), labels)
    plain = augment(depth.clone(), *args, torch.Generator().manual_seed(5), noise_level=0.0)
    both = augment(depth.clone(), *args, torch.Generator().manual_seed(5), noise_level=0.0,
                   nearest=depth.clone())
    # Without noise the nearest depths are the depths, moved and scaled the same way; and the
    # other outputs are those of a run without them (the random stream is unchanged).
    assert plain.nearest is None and torch.equal(both.nearest, both.depth)
    for got, want in zip(both[:3], plain[:3]):
        assert torch.equal(got, want)
    noisy = augment(depth.clone(), *args, torch.Generator().manual_seed(5), noise_level=1.0,
                    nearest=depth.clone())
    assert not torch.equal(noisy.nearest, noisy.depth)   # noise drawn on its own


def test_a_runs_augmentations_come_field_for_field_from_its_config():
    """``Augmentations.of_config`` is what links a run's ``aug_*`` options to its batches;
    five of its fields are interchangeable floats, so each is given a value of its own."""
    from training.augment import Augmentations

    cfg = TrainConfig(aug_holes=0.1, aug_roll_deg=2.0, aug_islands=3e-4,
                      aug_islands_discs=True, aug_range_limit=0.4)
    assert Augmentations.of_config(cfg, 0.7) == Augmentations(
        noise_level=0.7, holes=0.1, roll_deg=2.0, islands=3e-4, island_discs=True,
        range_limit=0.4)


def test_augmentation_noise_level_zero_adds_no_noise():
    from training.augment import augment

    depth = torch.full((8, 120, 160), 2.0)
    out = augment(depth.clone(), torch.ones_like(depth), torch.zeros_like(depth).long(),
                  torch.Generator().manual_seed(0), noise_level=0.0).depth
    inner = out[:, 10:-10, 10:-10]
    # Only the whole-scene scale is left: every image flat, within +-4 % of 2 m.
    assert torch.allclose(inner, inner[:, :1, :1].expand_as(inner))
    assert ((inner - 2.0).abs() <= 0.08 + 1e-6).all()


def test_augmentation_holes_take_depth_and_labels_from_large_regions_and_nothing_else():
    from training.augment import augment
    from training.holes import HOLE_MAX_SHARE

    depth = torch.rand(32, 120, 160) + 1.0
    labels = torch.randint(0, 4, (32, 120, 160))
    args = (torch.ones_like(depth), labels)
    plain = augment(depth.clone(), *args, torch.Generator().manual_seed(7))
    holed = augment(depth.clone(), *args, torch.Generator().manual_seed(7), holes=0.5)
    gone = (holed.labels == 255) & (plain.labels != 255)     # ignored, not relabelled
    # Drawn last: outside the holes every output is that of a run without them.
    assert torch.equal(holed.depth, plain.depth)
    assert torch.equal(holed.valid[~gone], plain.valid[~gone])
    assert torch.equal(holed.labels[~gone], plain.labels[~gone])
    assert (holed.valid[gone] == 0).all()
    share = gone.float().mean((1, 2))
    with_holes = share > 0
    assert 8 <= with_holes.sum() <= 24                       # about half the images
    assert share.max() <= HOLE_MAX_SHARE + 0.01
    assert 0.1 < share[with_holes].mean() < 0.25             # U(0, 0.35) of each image
    # Large regions, not speckles: most lost pixels have all four neighbours lost too (0.86
    # here; scattered pixels at this density would give under 0.01).
    inner = gone[:, 1:-1, 1:-1]
    surrounded = (inner & gone[:, :-2, 1:-1] & gone[:, 2:, 1:-1] & gone[:, 1:-1, :-2]
                  & gone[:, 1:-1, 2:])
    assert surrounded.sum() > 0.6 * inner.sum()


def test_augmentation_holes_and_noise_are_refused_out_of_range_or_without_augmentation():
    with pytest.raises(ConfigError, match="aug_holes"):
        TrainConfig(aug_holes=1.5).validate()
    with pytest.raises(ConfigError, match="needs augment"):
        TrainConfig(aug_holes=0.5, augment=False).validate()
    with pytest.raises(ConfigError, match="aug_noise = 2.0 needs augment"):
        TrainConfig(aug_noise=2.0, augment=False).validate()
    TrainConfig(aug_noise=0.0, augment=False).validate()      # both off: nothing to refuse
    TrainConfig(augment=False).validate()                     # the default level, left alone
    assert TrainConfig(aug_holes=0.5).validate().aug_holes == 0.5


def test_augmentation_moves_the_intrinsics_with_the_image():
    from test_floor import _tilted_scene

    from task_outcome_ros.camera import Intrinsics
    from task_outcome_ros.floor import height_above_floor
    from training.augment import augment

    # An off-centre camera at the envelope's longest focal length, at the working size; the
    # box top at the rim height. Mirrors and shifts must keep every height right.
    camera = Intrinsics(160, 120, 590 / 4, 590 / 4, 79.5 + 2.0, 59.5 - 2.0)
    one = _tilted_scene(box_height=0.25, camera=camera)
    box = (np.abs(one - _tilted_scene(box_height=0.0, camera=camera)) > 1e-6).astype(np.int64)
    n = 16
    depth = torch.from_numpy(np.stack([one] * n))
    k = torch.from_numpy(np.stack([camera.normalised()] * n))
    out, valid, moved_box, k_out = augment(depth.clone(), torch.ones_like(depth),
                                           torch.from_numpy(np.stack([box] * n)),
                                           torch.Generator().manual_seed(3),
                                           noise_level=0.0, intrinsics=k)[:4]
    truth = torch.where(moved_box == 1, 0.25, 0.0)
    seen = (valid > 0) & (moved_box != 255)

    def worst_error(intrinsics):
        heights = height_above_floor(out, valid > 0, intrinsics=intrinsics)
        return (heights - truth).abs()[seen].max().item()

    assert worst_error(k_out) < 2e-4
    assert worst_error(k) > 1e-3                  # the intrinsics of the unmoved image
    # No whole-scene distance change with intrinsics (it would move the rim off 0.25 m): the
    # depths are the scene's own, only moved.
    assert torch.isin(out[seen], depth[0]).all()


def test_near_boundary_sample_weights_follow_the_hard_case_tags(small_run, tmp_path):
    from training.hard_cases import episode_hard_cases
    from training.train import near_boundary_sample_weights

    indices = np.arange(40)
    assert near_boundary_sample_weights(small_run, indices, 1.0) is None   # uniform: no lookup
    weights = near_boundary_sample_weights(small_run, indices, 3.0)
    cases = episode_hard_cases(small_run, set(range(40)))
    assert weights.tolist() == [3.0 if "near_boundary" in cases[i].tags else 1.0 for i in indices]
    with pytest.raises(ValueError, match="simulate"):
        near_boundary_sample_weights(tmp_path, indices, 3.0)           # a run without simulate/


def test_small_outcome_sample_weights_follow_the_outcomes_pixel_counts() -> None:
    from training.train import combined_sample_weights, small_outcome_sample_weights

    def image(episode, width, counts):
        return {"episode": episode, "camera": {"width": width, "height": width * 3 // 4},
                "present": {k: v > 0 for k, v in counts.items()}, "pixel_counts": counts}

    manifest = {"images": [
        image(0, 640, {"success": 5000, "fell_outside": 300}),   # a small fallen object
        image(1, 640, {"success": 5000, "fell_outside": 0}),     # absent is not small
        image(2, 640, {"success": 900, "fell_outside": 0}),      # over 800 px
        image(3, 320, {"success": 250, "fell_outside": 0}),      # 1,000 px at 640 x 480
        image(4, 320, {"success": 150, "fell_outside": 0}),      # 600 px at 640 x 480
    ]}
    indices = np.array([4, 3, 2, 1, 0])
    assert small_outcome_sample_weights(manifest, indices, 1.0) is None
    weights = small_outcome_sample_weights(manifest, indices, 3.0)
    assert weights.tolist() == [3.0, 1.0, 1.0, 1.0, 3.0]
    near = np.array([2.5, 1.0, 2.5, 1.0, 1.0])
    assert combined_sample_weights(near, weights).tolist() == [7.5, 1.0, 2.5, 1.0, 3.0]
    assert combined_sample_weights(None, weights).tolist() == weights.tolist()
    assert combined_sample_weights(None, None) is None
    with pytest.raises(ConfigError, match="train.small_outcome_weight"):
        TrainConfig(small_outcome_weight=0.5).validate()


def test_touching_outcomes_sample_weights_find_two_different_outcomes_side_by_side() -> None:
    from task_outcome_ros.labels import FIRST_OUTCOME_ID, FIXTURE, IGNORE
    from training.train import touching_outcome_pixels, touching_outcomes_sample_weights

    success, fallen, stuck = FIRST_OUTCOME_ID, FIRST_OUTCOME_ID + 1, FIRST_OUTCOME_ID + 2
    labels = np.zeros((5, 6, 6), np.uint8)
    labels[0, 1:3, 1:3] = stuck                  # a box stacked on another: touching
    labels[0, 3:5, 1:3] = success
    labels[1, 1:3, 1:3] = success                # two outcomes a pixel apart: not touching
    labels[1, 1:3, 4:6] = fallen
    labels[2, :, :3] = success                   # one outcome against the fixture
    labels[2, :, 3:] = FIXTURE
    labels[3, 2, 2], labels[3, 2, 3] = fallen, IGNORE   # no depth is no outcome
    labels[4, 0, 0], labels[4, 1, 0] = fallen, stuck    # one pixel pair, vertical
    assert touching_outcome_pixels(labels).tolist() == [2, 0, 0, 0, 1]
    assert touching_outcomes_sample_weights(labels, 1.0) is None
    weights = touching_outcomes_sample_weights(labels, 3.0, chunk=2)   # chunks split images
    assert weights.tolist() == [3.0, 1.0, 1.0, 1.0, 3.0]
    with pytest.raises(ConfigError, match="train.touching_outcomes_weight"):
        TrainConfig(touching_outcomes_weight=0.5).validate()


def test_objects_cast_with_ids_sit_on_their_outcomes_pixels_and_touching_is_id_adjacency(
        small_run, tmp_path):
    """The id image is the rendered frame with each object told apart: cast at the full size,
    object k's pixels carry object k's outcome in the stored labels (where the sensor left
    depth), so ids follow the objects' order; a frame counts when two ids are 4-neighbours."""
    from task_outcome_ros.labels import IGNORE
    from training.hard_cases import run_episodes
    from training.overlaps import (
        FIRST_OBJECT_ID,
        frames_with_touching_objects,
        object_id_image,
        objects_touch,
        working_camera,
    )
    from training.render import read_pair
    from training.train import touching_objects_sample_weights

    run = run_episodes(small_run, set(range(40)))
    outcomes, table = load_outcomes(small_run)
    manifest = load_manifest(small_run)
    cameras = {im["episode"]: im["camera"] for im in manifest["images"]}
    checked = 0
    for episode in run.episodes[:8]:
        index = int(episode["episode"])
        camera = working_camera(cameras[index], (cameras[index]["width"],
                                                 cameras[index]["height"]))
        ids = object_id_image(episode, outcomes[index], run.cfg.scene, table, camera)
        _, labels = read_pair(small_run, index)
        for k, outcome in enumerate(outcomes[index]):
            on_object = (ids == FIRST_OBJECT_ID + k) & (labels != IGNORE)
            if on_object.sum() >= 50:
                agree = (labels[on_object] == table.outcome_ids[outcome]).mean()
                assert agree > 0.9, (index, k, outcome, agree)
                checked += 1
    assert checked >= 5

    apart, stacked, alone = (np.zeros((4, 5), np.uint8) for _ in range(3))
    apart[1, 1], apart[1, 3] = FIRST_OBJECT_ID, FIRST_OBJECT_ID + 1     # a pixel between them
    stacked[1, 1], stacked[2, 1] = FIRST_OBJECT_ID + 2, FIRST_OBJECT_ID  # one above the other
    alone[1:3, 1:4] = FIRST_OBJECT_ID + 1                                # one object
    assert [objects_touch(a) for a in (apart, stacked, alone)] == [False, True, False]

    indices = np.arange(40)
    touching = frames_with_touching_objects(small_run, manifest, indices, (160, 120))
    assert touching.shape == (40,) and touching.dtype == bool
    single = [int(e["episode"]) for e in run.episodes if len(e["objects"]) < 2]
    assert single and not touching[single].any()       # one object cannot touch another
    assert touching.any()                              # boxes dropped together do touch
    assert touching_objects_sample_weights(small_run, manifest, indices, (160, 120), 1.0) is None
    weights = touching_objects_sample_weights(small_run, manifest, indices, (160, 120), 2.0)
    assert weights.tolist() == np.where(touching, 2.0, 1.0).tolist()
    with pytest.raises(ValueError, match="simulate"):
        frames_with_touching_objects(tmp_path, manifest, indices, (160, 120))   # no simulate/
    with pytest.raises(ConfigError, match="train.touching_objects_weight"):
        TrainConfig(touching_objects_weight=0.5).validate()


def test_object_distance_dips_to_one_along_the_seam_of_two_touching_objects(small_run,
                                                                           tmp_path):
    """The auxiliary target: each object pixel's distance to anything that is not the same
    object, so two touching boxes read 1 on both sides of their seam as against the floor,
    and an object cut by the frame's edge is not measured from it. Cast from the stored run,
    it sits on the labelled objects and is cached once beside the working-size cache."""
    from training.overlaps import (
        FIRST_OBJECT_ID,
        OBJECT_DISTANCE_CLIP_PX,
        cast_object_ids,
        object_distance,
        object_distance_cache,
    )

    ids = np.zeros((9, 14), np.uint8)
    ids[1:8, 1:7], ids[1:8, 7:13] = FIRST_OBJECT_ID, FIRST_OBJECT_ID + 1  # side by side
    dist = object_distance(ids)
    assert (dist[ids == 0] == 0).all()
    assert dist[4, 6] == dist[4, 7] == 1                 # the seam, on both sides
    assert dist[4, 3] == dist[4, 10] == 3                # each box's own middle
    edge = np.zeros((6, 6), np.uint8)
    edge[:, :3] = FIRST_OBJECT_ID                         # cut by the frame's left edge
    assert object_distance(edge)[2].tolist() == [3, 2, 1, 0, 0, 0]
    assert object_distance(np.full((40, 40), FIRST_OBJECT_ID, np.uint8)).max() \
        == OBJECT_DISTANCE_CLIP_PX

    manifest = load_manifest(small_run)
    cache = load_cache(small_run, "train", (160, 120), workers=1)
    indices, labels = cache["indices"], cache["labels"]
    distance = object_distance_cache(small_run, manifest, indices, "train", (160, 120))
    assert distance.shape == labels.shape and distance.dtype == np.uint8
    outcome = (labels >= SUCCESS) & (labels != 255)
    assert (distance[outcome] > 0).mean() > 0.9          # the cast sits on the labels' objects
    assert (distance[labels == FIXTURE] > 0).mean() < 0.05
    cast = dict(cast_object_ids(small_run, manifest, indices[:3], (160, 120)))
    for k, ids in cast.items():
        assert np.array_equal(distance[k] > 0, ids >= FIRST_OBJECT_ID)
    # Cached: read again, not cast again; a file of other images is refused.
    assert (small_run / "cache" / "train_160x120_object_distance.npz").is_file()
    assert np.array_equal(object_distance_cache(small_run, manifest, indices, "train",
                                                (160, 120)), distance)
    with pytest.raises(ValueError, match="other images, another size"):
        object_distance_cache(small_run, manifest, indices[:-1], "train", (160, 120))
    with pytest.raises(ConfigError, match="train.object_distance_weight"):
        TrainConfig(object_distance_weight=0.5, aug_roll_deg=15.0).validate()
    with pytest.raises(ConfigError, match="train.object_distance_weight"):
        TrainConfig(object_distance_weight=-1.0).validate()


def test_augmentation_moves_the_object_distances_with_the_labels():
    """Mirror and shift move the auxiliary target as they move the labels: after augmenting,
    it is non-zero exactly on the object's labelled pixels; the noise draws do not change."""
    from training.augment import augment

    labels = torch.zeros((16, 40, 60), dtype=torch.long)
    labels[:, 10:25, 5:20] = SUCCESS                      # off-centre: a mirror moves it
    distance = (labels == SUCCESS).float() * 2.0
    args = (torch.full((16, 40, 60), 2.0), torch.ones((16, 40, 60)), labels)
    plain = augment(*args, torch.Generator().manual_seed(4), holes=0.5)
    moved = augment(*args, torch.Generator().manual_seed(4), holes=0.5,
                    object_distance=distance)
    assert torch.equal(plain.depth, moved.depth) and torch.equal(plain.labels, moved.labels)
    seen = moved.labels != 255
    assert torch.equal((moved.object_distance > 0)[seen], (moved.labels == SUCCESS)[seen])
    assert not torch.equal(moved.object_distance, distance)   # some images did move


def test_object_distance_head_trains_the_features_and_stays_out_of_the_checkpoint(
        small_run, tmp_path, monkeypatch, capsys):
    """--object-distance-weight: a readout of the class head's input trained beside it; the
    shipped network is the plain one (same weights' names, loads and runs in the node's
    segmenter), and a resumed run takes the head's weights back from last.pt."""
    from task_outcome_ros import checkpoint
    from task_outcome_ros.inference import OutcomeSegmenter
    from task_outcome_ros.model import build_model
    from training import train as train_module
    from training.losses import ObjectDistanceHead, object_distance_loss
    from training.render import read_pair

    net = build_model({"in_channels": 3, "num_classes": 5, "base_width": 4, "levels": 2})
    head = ObjectDistanceHead(net)
    labels = torch.full((2, 24, 32), SUCCESS)
    net(torch.randn(2, 3, 24, 32))
    loss = object_distance_loss(head((24, 32)), torch.full((2, 24, 32), 3.0), labels, 6)
    loss.backward()
    assert net.stem[0].weight.grad.abs().sum() > 0       # the target reaches the features
    with pytest.raises(RuntimeError, match="forward first"):
        head((24, 32))                                   # one readout per forward
    head.remove()
    net(torch.randn(2, 3, 24, 32))
    assert not net.head._forward_pre_hooks and head._features is None   # detached

    run = tmp_path / "run"
    r = _cli("train", "--out", str(run), "--dataset-from", str(small_run), "--epochs", "1",
             "--batch-size", "8", "--device", "cpu", "--object-distance-weight", "0.5")
    assert r.returncode == 0, r.stderr[-2000:]
    assert (run / "cache" / "train_160x120_object_distance.npz").is_file()   # made or reused
    best = checkpoint.load(run / "train" / "best.pt")
    plain = build_model(best.model_args)
    assert set(best.model.state_dict()) == set(plain.state_dict())
    assert best.train_config["train"]["object_distance_weight"] == 0.5
    last = checkpoint.load(run / "train" / "last.pt")
    assert "object_distance_head" in last.optimizer_state
    depth, frame_labels = read_pair(small_run, 0)
    result = OutcomeSegmenter(run / "train" / "best.pt", backend="torch").segment(depth)
    assert result.labels.shape == frame_labels.shape
    # Interrupted in its second epoch (validation fails), then resumed from last.pt.
    cfg = TrainConfig(epochs=2, batch_size=8, device="cpu", object_distance_weight=0.5)
    real_validate, calls = train_module.validate, []

    def validate_once(*args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise RuntimeError("interrupted")
        return real_validate(*args, **kwargs)

    monkeypatch.setattr(train_module, "validate", validate_once)
    with pytest.raises(RuntimeError, match="interrupted"):
        train_module.train(run, cfg, out=tmp_path / "again", progress=False)
    monkeypatch.setattr(train_module, "validate", real_validate)
    saved_head = checkpoint.load(tmp_path / "again" / "last.pt").optimizer_state[
        "object_distance_head"]
    loaded = []

    class RecordingHead(ObjectDistanceHead):
        def load_state_dict(self, state, *args, **kwargs):
            loaded.append(state)
            return super().load_state_dict(state, *args, **kwargs)

    monkeypatch.setattr(train_module, "ObjectDistanceHead", RecordingHead)
    train_module.train(run, cfg, out=tmp_path / "again", progress=False)
    out = capsys.readouterr().out
    assert "resuming from" in out and "after epoch 1" in out
    assert len(loaded) == 1 and all(torch.equal(loaded[0][k], saved_head[k])
                                    for k in saved_head)     # the head's own weights, back
    assert len(json.loads((tmp_path / "again" / "history.json").read_text())) == 2


def test_relief_beneath_support_is_refused_on_a_task_without_a_table(small_run, tmp_path,
                                                                    monkeypatch):
    """The default task's container stands on the room floor: no table top to measure beneath.
    The refusal names the spec's missing table and comes before any cache or weight is made."""
    from training.train import train

    def no_cache(*args, **kwargs):
        raise AssertionError("the cache was loaded before the refusal")

    monkeypatch.setattr("training.train.load_cache", no_cache)
    cfg = TrainConfig(epochs=1, batch_size=4, device="cpu", relief_window_px=15,
                      relief_beneath_support=True)
    out = tmp_path / "refused"
    with pytest.raises(ValueError, match="table_size"):
        train(small_run, cfg, out=out, progress=False)
    assert not any(out.glob("*.pt")) and not (out / "history.json").exists()


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "training", *args], capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("train_run")
    r = _cli("dataset", "--out", str(out), "--episodes", "40", "--chunk-size", "20",
             "--seed", "3")
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def test_run_makes_the_dataset_trains_and_evaluates_in_one_command(tmp_path):
    """`run` is what `make ship` and `make train` call: dataset, train and evaluate in turn,
    on options of `dataset` and `train` alike."""
    out = tmp_path / "run"
    r = _cli("run", "--out", str(out), "--episodes", "20", "--chunk-size", "10", "--seed", "3",
             "--epochs", "1", "--batch-size", "4", "--device", "cpu")
    assert r.returncode == 0, r.stderr[-2000:]
    assert len(json.loads((out / "train" / "history.json").read_text())) == 1
    report = json.loads((out / "eval" / "eval.json").read_text())
    assert report["n_images"] == 1 and report["model"].endswith("best.pt")


def test_run_refuses_a_bad_training_option_before_making_the_dataset(tmp_path, capsys):
    from training.__main__ import main

    assert main(["run", "--out", str(tmp_path / "run"), "--lr", "-1"]) == 2
    assert "train.lr" in capsys.readouterr().err
    assert not (tmp_path / "run").exists(), "no minutes of dataset spent on a refused recipe"


def test_evaluation_of_a_known_model_gives_the_scores_the_truth_implies(small_run, tmp_path):
    """A model that says success on every valid pixel: its presence precision and recall per
    outcome follow from the manifest's truth alone, so evaluate's arithmetic is checked."""
    ckpt = make_checkpoint(tmp_path / "success_everywhere.pt", favour=SUCCESS)
    report = evaluate(ckpt, small_run, "all", tmp_path / "eval", backend="torch",
                      progress=False)
    truth = [im["present"] for im in load_manifest(small_run)["images"]]
    assert report["n_images"] == len(truth) == 40
    with_success = sum(p["success"] for p in truth)
    assert 0 < with_success < len(truth)  # the seed gives images without a success object
    assert report["success"]["presence_recall"] == 1.0
    assert report["success"]["presence_precision"] == pytest.approx(with_success / len(truth))
    for name in ("fell_outside", "stuck_on_rim"):
        support = sum(p[name] for p in truth)
        assert report[name]["support"] == support and report[name]["false_positives"] == 0
        assert report[name]["presence_recall"] == (0.0 if support else 1.0)
    only_success = sum(p == {"success": True, "fell_outside": False, "stuck_on_rim": False}
                       for p in truth)
    assert report["image_all_correct"] == pytest.approx(only_success / len(truth))
    assert "recall_by_place" not in report   # the default container stands on no table


def test_short_real_training_improves_the_loss_and_evaluates(small_run):
    r = _cli("train", "--out", str(small_run), "--epochs", "3", "--batch-size", "8",
             "--lr", "0.005", "--device", "cpu")
    assert r.returncode == 0, r.stderr[-2000:]
    history = json.loads((small_run / "train" / "history.json").read_text())
    assert len(history) == 3
    assert history[-1]["train_loss"] < history[0]["train_loss"]
    assert (small_run / "train" / "training_curves.png").stat().st_size > 0

    from task_outcome_ros import checkpoint

    ckpt = checkpoint.load(small_run / "train" / "best.pt")
    assert ckpt.train_config["train"]["epochs"] == 3
    assert ckpt.input_size == (160, 120)
    # The layout left to the machine: both timed, the faster one used and recorded.
    assert ckpt.train_config["train"]["channels_last"] == "auto"
    chosen = "channels-last" if ckpt.extra["channels_last"] else "contiguous"
    assert f"{chosen} activations (chosen: " in r.stdout

    r = _cli("evaluate", "--out", str(small_run), "--backend", "torch")
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads((small_run / "eval" / "eval.json").read_text())
    for key in ("n_images", "image_all_correct", "pixel_miou", "iou", "presence_min_pixels"):
        assert key in report
    assert report["n_images"] == 2   # 5 % of 40 episodes
    assert report["image_all_correct"] == pytest.approx(
        1 - len(report["mistakes"]) / report["n_images"])
    assert report["fragment_max_pixels"] == FRAGMENT_MAX_PIXELS
    hard = report["hard_cases"]    # tags come from the run's own simulated final states
    assert set(hard["images"]) == {"near_boundary", "across_edge"}
    val = [im["episode"] for im in load_manifest(small_run)["images"] if im["split"] == "val"]
    cases = episode_hard_cases(small_run, set(val))
    assert hard["untagged_images"] == sum(not cases[e].tags for e in val)
    assert hard["mistakes"]["untagged"] <= len(report["mistakes"])
    assert sum(hard["mistakes"].values()) >= len(report["mistakes"])  # each one counted
    assert sum(e["images"] for e in hard["by_boundary_gap"]) == report["n_images"]
    assert sum(e["mistakes"] for e in hard["by_boundary_gap"]) == len(report["mistakes"])
    assert (small_run / "eval" / "boundary_gap.png").exists()
    by_size = report["recall_by_size"]["by_outcome"]
    present = report["presence_recall"]   # every truly present outcome lands in one size bin
    for outcome, support in ((o, report[o]["support"]) for o in present):
        assert sum(e["images"] for e in by_size[outcome]) == support
    assert (small_run / "eval" / "recall_by_size.png").stat().st_size > 0
    assert (small_run / "eval" / "confusion.png").exists()

    # Resuming a finished run changes nothing, also with another time budget (how a run is
    # executed, not what it learns); a different recipe is refused, saying what differs.
    r = _cli("train", "--out", str(small_run), "--epochs", "3", "--batch-size", "8",
             "--lr", "0.005", "--device", "cpu", "--max-minutes", "30")
    assert r.returncode == 0, r.stderr[-2000:]
    assert len(json.loads((small_run / "train" / "history.json").read_text())) == 3
    r = _cli("train", "--out", str(small_run), "--epochs", "4", "--batch-size", "8",
             "--lr", "0.005", "--device", "cpu")
    assert r.returncode == 2 and "another config" in r.stderr and "epochs: 3 -> 4" in r.stderr


def test_resume_compares_the_recipe_and_the_precision_not_the_budget():
    from training.config import to_dict
    from training.train import resume_differences

    cfg = TrainConfig(amp="auto")
    saved = json.loads(json.dumps(to_dict(TrainConfig(amp="bf16", max_minutes=5.0))))
    assert resume_differences(saved, cfg, "bf16", "bf16") == []
    # Saved before near_rim_weight became near_boundary_weight: the same setting.
    renamed = {("near_rim_weight" if k == "near_boundary_weight" else k): v
               for k, v in saved.items()}
    assert resume_differences(renamed, cfg, "bf16", "bf16") == []
    # Saved before space_to_depth and full_size_head existed: every such run had neither
    # (1 and 0), the same setting.
    unfolded = {k: v for k, v in saved.items() if k not in ("space_to_depth", "full_size_head")}
    assert resume_differences(unfolded, cfg, "bf16", "bf16") == []
    headed = dataclasses.replace(cfg, space_to_depth=2, full_size_head=8)
    assert resume_differences(unfolded, headed, "bf16", "bf16") == [
        "full_size_head: 0 -> 8", "space_to_depth: 1 -> 2"]
    # Saved before object_balance_pixels existed: plain class weights, i.e. 0.
    unbalanced = {k: v for k, v in saved.items() if k != "object_balance_pixels"}
    assert resume_differences(unbalanced, cfg, "bf16", "bf16") == []
    assert resume_differences(unbalanced, dataclasses.replace(cfg, object_balance_pixels=64),
                              "bf16", "bf16") == ["object_balance_pixels: 0 -> 64"]
    # Saved before relief_window_px existed: three channels, i.e. 0.
    flat = {k: v for k, v in saved.items() if k != "relief_window_px"}
    assert resume_differences(flat, dataclasses.replace(cfg, relief_window_px=0),
                              "bf16", "bf16") == []
    assert resume_differences(flat, dataclasses.replace(cfg, relief_window_px=15),
                              "bf16", "bf16") == ["relief_window_px: 0 -> 15"]
    # Saved before relief_smoothing_px existed: the relief of the heights themselves, i.e. 0.
    rough = {k: v for k, v in saved.items() if k != "relief_smoothing_px"}
    assert resume_differences(rough, cfg, "bf16", "bf16") == []
    assert resume_differences(rough, dataclasses.replace(cfg, relief_window_px=15,
                                                         relief_smoothing_px=3),
                              "bf16", "bf16") == ["relief_smoothing_px: 0 -> 3",
                                                  "relief_window_px: 0 -> 15"]
    # Saved before nearest_height existed: no such channel, i.e. False.
    far = {k: v for k, v in saved.items() if k != "nearest_height"}
    assert resume_differences(far, cfg, "bf16", "bf16") == []
    assert resume_differences(far, dataclasses.replace(cfg, nearest_height=True),
                              "bf16", "bf16") == ["nearest_height: False -> True"]
    assert resume_differences(saved, cfg, "bf16", "fp32") == ["precision: bf16 -> fp32"]
    old = {k: v for k, v in saved.items() if k != "lovasz_weight"}     # predates the field
    assert resume_differences(old, cfg, "bf16", "bf16") == [
        "lovasz_weight: '<not recorded>' -> 0.5"]
    # A run saved with another floor fit sees other heights: not resumable.
    now = check_normalisation(DEFAULT_NORMALISATION)
    before = check_normalisation({k: v for k, v in now.items() if k != "floor_fit"})
    assert resume_differences(saved, cfg, "bf16", "bf16", now, now) == []
    assert resume_differences(saved, cfg, "bf16", "bf16", before, now) == [
        f"normalisation floor_fit: 1 -> {now['floor_fit']}"]


def test_fp32_contiguous_training_runs_and_its_checkpoint_loads(small_run, tmp_path):
    """The defaults are channels-last and, on a CPU with native bf16, bf16 autocast; the plain
    fp32 / NCHW path (every other CPU, or by choice) must keep working and say what it used."""
    run = tmp_path / "run"
    # The object-balanced cross-entropy and the relief and near-side channels ride along:
    # its weights and the extra input channels go through the real loop (and the nearest
    # depths through their own cache); the run trains on the small run's dataset, linked
    # (--dataset-from), as a second recipe on the same images would.
    r = _cli("train", "--out", str(run), "--dataset-from", str(small_run), "--epochs", "1",
             "--batch-size", "8", "--device", "cpu", "--amp", "off", "--no-channels-last",
             "--object-balance-pixels", "64", "--relief-window-px", "5",
             "--relief-smoothing-px", "3", "--nearest-height")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "train: cpu, fp32, contiguous activations" in r.stdout
    assert f"train: on the dataset of {small_run}" in r.stdout
    assert (run / "manifest.json").resolve() == (small_run / "manifest.json").resolve()
    from task_outcome_ros import checkpoint

    ckpt = checkpoint.load(run / "train" / "best.pt")
    assert ckpt.train_config["train"]["object_balance_pixels"] == 64
    assert ckpt.normalisation["relief_window_px"] == 5 and ckpt.normalisation["nearest_height"]
    assert ckpt.normalisation["relief_smoothing_px"] == 3
    assert ckpt.model_args["in_channels"] == 5
    assert (run / "cache" / "val_160x120_nearest.npz").is_file()
    assert ckpt.train_config["train"]["channels_last"] is False
    assert ckpt.train_config["train"]["amp"] == "off"
    assert ckpt.extra["precision"] == "fp32"
    x = torch.zeros(1, ckpt.model_args["in_channels"], 120, 160)
    assert torch.isfinite(ckpt.model(x)).all()
    # The node's path makes the extra channels from a full-size frame by itself.
    from task_outcome_ros.inference import OutcomeSegmenter
    from training.render import read_pair

    depth, labels = read_pair(small_run, 0)
    result = OutcomeSegmenter(run / "train" / "best.pt", backend="torch").segment(depth)
    assert result.labels.shape == labels.shape


def test_training_on_crops_of_a_finer_size_gives_a_whole_image_model(small_run, tmp_path):
    """--train-crop: the network trains on crops of the --input-size cache and its checkpoint
    runs on the whole image at that size, in evaluation and in the node's segmenter."""
    run = tmp_path / "run"
    r = _cli("train", "--out", str(run), "--dataset-from", str(small_run), "--epochs", "1",
             "--batch-size", "8", "--device", "cpu", "--input-size", "192", "144",
             "--train-crop", "96", "72", "--aug-holes", "0.5", "--aug-roll", "15")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "fitting the support planes of" in r.stdout and "for 96 x 72 crops" in r.stdout
    from task_outcome_ros import checkpoint

    ckpt = checkpoint.load(run / "train" / "best.pt")
    assert ckpt.input_size == (192, 144)
    assert tuple(ckpt.train_config["train"]["train_crop"]) == (96, 72)
    assert 0.0 <= ckpt.metrics["image_all_correct"] <= 1.0   # validated on whole images
    from task_outcome_ros.inference import OutcomeSegmenter
    from training.render import read_pair

    depth, labels = read_pair(small_run, 0)
    result = OutcomeSegmenter(run / "train" / "best.pt", backend="torch").segment(depth)
    assert result.labels.shape == labels.shape


def test_a_run_links_another_runs_dataset_once_and_never_mixes_two(tmp_path):
    from training.dataset import link_dataset

    source, run = tmp_path / "source", tmp_path / "run"
    (source / "images").mkdir(parents=True)
    for name in ("manifest.json", "config.json"):
        (source / name).write_text("{}")
    assert link_dataset(source, run) == ["config.json", "images", "manifest.json"]
    assert (run / "images").is_symlink() and (run / "images").resolve() == source / "images"
    assert link_dataset(source, run) == ["config.json", "images", "manifest.json"]  # again
    other = tmp_path / "other"
    (other / "config.json").parent.mkdir()
    (other / "config.json").write_text("{}")
    with pytest.raises(ValueError, match="not a link to"):
        link_dataset(source, other)
    with pytest.raises(FileNotFoundError, match="no manifest.json"):
        link_dataset(tmp_path / "nothing", tmp_path / "run2")


def test_the_schedule_is_fitted_to_the_budget_after_the_first_epoch(small_run, tmp_path,
                                                                   monkeypatch, capsys):
    import itertools
    import shutil
    from types import SimpleNamespace

    from training import train as train_module
    from training.train import fitted_epochs

    assert fitted_epochs(13, 240.0, 58.0) == 13        # 52 min: fits
    assert fitted_epochs(13, 480.0, 58.0) == 7          # twice as slow: 7 epochs in 56 min
    assert fitted_epochs(13, 7200.0, 58.0) == 1         # never below one epoch
    run = tmp_path / "run"
    shutil.copytree(small_run, run, ignore=shutil.ignore_patterns("train", "eval"))
    # The trainer's clock, read at: start; epoch 1 start, end, budget check; epoch 2 start,
    # end. Each epoch takes a minute, so three overrun a 2.5 minute budget: it spans two.
    readings = itertools.chain([0.0, 0.0, 60.0, 60.0, 60.0, 120.0], itertools.repeat(120.0))
    monkeypatch.setattr(train_module, "time",
                        SimpleNamespace(perf_counter=lambda: next(readings)))
    # The layout pinned: timing the two layouts would read the mocked clock too.
    cfg = TrainConfig(epochs=3, batch_size=8, device="cpu", max_minutes=2.5,
                      channels_last=True)
    train_module.train(run, cfg, progress=False)
    assert "the schedule now spans 2 epochs" in capsys.readouterr().out
    assert [h["epoch"] for h in json.loads((run / "train" / "history.json").read_text())] \
        == [1, 2]
    from task_outcome_ros import checkpoint

    last = checkpoint.load(run / "train" / "last.pt")
    assert last.extra["schedule_epochs"] == 2 and last.train_config["train"]["epochs"] == 3
    train_module.train(run, cfg, progress=False)        # resumed: the fitted run is finished
    assert len(json.loads((run / "train" / "history.json").read_text())) == 2


def test_layout_timing_times_both_layouts_and_leaves_the_random_stream_alone():
    from training.train import autocast_factory, build_model, layout_step_seconds

    cfg = TrainConfig(base_width=4)
    args = {**cfg.model_args, "in_channels": 3}
    x, labels = torch.rand(2, 3, 32, 48), torch.randint(0, 5, (2, 32, 48))
    torch.manual_seed(3)
    before = torch.rand(4)
    torch.manual_seed(3)
    seconds = layout_step_seconds(args, x, labels, None, autocast_factory("fp32", "cpu"),
                                  None, cfg)
    assert set(seconds) == {True, False} and all(0 < s < 60 for s in seconds.values())
    assert torch.equal(torch.rand(4), before)       # the run's own draws do not move
    assert isinstance(build_model(args), torch.nn.Module)


def test_auto_precision_is_mixed_only_where_the_hardware_is_native(monkeypatch):
    from training import train

    assert train.resolve_precision("off", "cuda") == "fp32"
    assert train.resolve_precision("bf16", "cpu") == "bf16"
    assert train.resolve_precision("auto", "cuda") == "fp16"
    monkeypatch.setattr(train, "cpu_has_native_bf16", lambda: True)
    assert train.resolve_precision("auto", "cpu") == "bf16"
    monkeypatch.setattr(train, "cpu_has_native_bf16", lambda: False)
    assert train.resolve_precision("auto", "cpu") == "fp32"


def test_shipped_checkpoint_labels_a_fresh_scene_sensibly(tmp_path):
    """Proof of life, not a figure: a scene the model never saw (new seed), rendered with the
    geometric rule as truth, gets the container and the objects' outcomes right."""
    from task_outcome_ros.camera import Intrinsics
    from task_outcome_ros.inference import OutcomeSegmenter, default_model_path

    if not default_model_path().exists():
        pytest.skip(f"no shipped model at {default_model_path()} (make ship trains one)")
    from training.config import DatasetConfig
    from training.geometry import geometric_outcome, object_measurements
    from training.render import render_episode
    from training.simulate import World, simulate_episode

    cfg = DatasetConfig()
    world = World(cfg.scene)
    seg = OutcomeSegmenter(backend="auto")
    agree, container_iou = 0, []
    for i in range(8):
        episode = simulate_episode(world, 987_654, i)
        outcomes = [task_word(geometric_outcome(object_measurements(o, episode, cfg.scene)))
                    for o in episode["objects"]]
        shot = render_episode(episode, outcomes, cfg, 987_654, DEFAULT_TABLE)
        # With the camera the image was rendered with, as camera_info gives it to the node.
        result = seg.segment(shot["depth"], Intrinsics.from_record(shot["record"]["camera"]))
        assert result.labels.shape == shot["labels"].shape
        agree += result.present == outcomes_present(shot["labels"])
        truth_c, pred_c = shot["labels"] == FIXTURE, result.labels == FIXTURE
        container_iou.append((truth_c & pred_c).sum() / max(1, (truth_c | pred_c).sum()))
    world.close()
    assert agree >= 6, f"only {agree}/8 images with all outcomes right"
    assert np.mean(container_iou) > 0.8


def test_weight_average_follows_the_ema_formula():
    from training.train import WeightAverage

    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Conv2d(1, 2, 1), torch.nn.BatchNorm2d(2))
    average = WeightAverage(model, decay=0.9)
    start = model[0].weight.detach().clone()
    with torch.no_grad():
        model[0].weight.add_(1.0)
    average.update(model)               # first update: decay ramps to min(0.9, 2 / 11)
    d = 2 / 11
    torch.testing.assert_close(average.module[0].weight, d * start + (1 - d) * (start + 1.0))
    assert not any(p.requires_grad for p in average.module.parameters())
    copy = WeightAverage(model, decay=0.0)
    with torch.no_grad():
        model[0].weight.mul_(3.0)
    copy.update(model)                  # decay 0: a plain copy of the current weights
    torch.testing.assert_close(copy.module[0].weight, model[0].weight)


def test_robustness_re_renders_the_dataset_then_sweeps_each_factor(small_run, tmp_path):
    """With no stress the suite's frame is the dataset's own image (same depth to the mm,
    same labels); each factor changes what it should; the report and its plot are written."""
    from training.chunks import load_chunks
    from training.config import dataset_config_from_dict, load_json
    from training.render import drawn_empty, read_pair
    from training.robustness import Stress, run_robustness, stressed_frame

    cfg = dataset_config_from_dict(load_json(small_run / "config.json"))
    episodes = load_chunks(small_run / "simulate", cfg.episodes, cfg.chunk_size)
    outcomes, table = load_outcomes(small_run)
    # The stored frame is whole (the suite renders every scene whole, the spec's empty cells too).
    assert not drawn_empty(cfg.scene, cfg.seed, 5)
    depth, labels, k = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed, Stress(), table)
    stored_depth, stored_labels = read_pair(small_run, 5)
    np.testing.assert_array_equal(labels, stored_labels)
    both = np.isfinite(depth) & np.isfinite(stored_depth)
    assert np.array_equal(np.isfinite(depth), np.isfinite(stored_depth))
    assert np.abs(depth[both] - stored_depth[both]).max() <= 0.0005 + 1e-6  # PNG: whole mm
    small, _, k_small = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                       Stress(resolution="320x240", focal_error=0.08), table)
    assert small.shape == (240, 320) and k_small.fx == pytest.approx(k.fx / 2 * 1.08)
    assert stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                          Stress(camera_info=False), table)[2] is None
    tilted, _, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                  Stress(support_tilt_deg=6.0), table)
    assert not np.allclose(np.nan_to_num(tilted), np.nan_to_num(depth))
    holed, holed_labels, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                            Stress(lost_depth_share=0.3), table)
    lost = np.isfinite(depth) & ~np.isfinite(holed)       # 30 % of the frame, minus old holes
    assert 0.2 < lost.mean() <= 0.3 + 1e-3 and (holed_labels[lost] == 255).all()
    islanded, islanded_labels, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                                  Stress(outlier_islands=3e-4), table)
    moved = np.isfinite(depth) & np.isfinite(islanded) & (np.abs(islanded - depth) > 0.01)
    assert 0.001 < moved.mean() < 0.05                     # small patches of wrong depth
    np.testing.assert_array_equal(islanded_labels[np.isfinite(islanded)],
                                  labels[np.isfinite(islanded)])
    kept = np.isfinite(holed)
    np.testing.assert_array_equal(holed[kept], depth[kept])
    np.testing.assert_array_equal(holed_labels[kept], labels[kept])
    emptied, emptied_labels, k_emptied = stressed_frame(episodes[5], outcomes[5], cfg,
                                                        cfg.seed, Stress(scene_emptied=True),
                                                        table)
    assert k_emptied == k                                   # the same camera draw
    assert set(np.unique(emptied_labels)) <= {0, 255}       # nothing but background left
    floor = (labels == 0) & np.isfinite(depth) & np.isfinite(emptied)
    # The same floor, up to the sensor's noise (drawn again on a frame of other content).
    assert np.median(np.abs(emptied[floor] - depth[floor])) < 0.05
    stood = (labels == 1) & np.isfinite(depth) & np.isfinite(emptied)   # where the walls were
    assert stood.sum() > 1000 and np.median(emptied[stood] - depth[stood]) > 0.05  # floor behind

    ckpt = make_checkpoint(tmp_path / "success_everywhere.pt", favour=SUCCESS)
    tof, _, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                               Stress(sensor_model="tof"), table)
    kinect, _, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                  Stress(sensor_model="kinect_v1"), table)
    assert not np.allclose(np.nan_to_num(tof), np.nan_to_num(kinect))
    stereo, _, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed,
                                  Stress(sensor_model="active_stereo"), table)
    assert not np.allclose(np.nan_to_num(stereo), np.nan_to_num(kinect))
    assert not np.allclose(np.nan_to_num(stereo), np.nan_to_num(tof))
    sweeps = {"camera_roll_deg": (0.0, 10.0), "resolution": ("640x480", "320x240"),
              "resolution_same_depth_error": ("320x240",),
              "sensor_model": ("", "tof", "active_stereo"), "lost_depth_share": (0.0, 0.3),
              "outlier_islands": (3e-4,), "scene_emptied": (True,)}
    report = run_robustness(ckpt, small_run, tmp_path / "rob", images=2, sweeps=sweeps,
                            progress=False)
    saved = load_json(tmp_path / "rob" / "robustness.json")
    assert saved == json.loads(json.dumps(report))
    assert saved["images"] == 2 and set(saved["factors"]) == set(sweeps)
    manifest = load_json(small_run / "manifest.json")
    val = [im["episode"] for im in manifest["images"] if im["split"] == "val"][:2]
    for factor, values in sweeps.items():
        entry = saved["factors"][factor]
        assert entry["values"] == list(values)
        for k, (value, got) in enumerate(zip(values, entry["image_all_correct"])):
            # The success-everywhere model is right exactly where only success is true.
            truths = [outcomes_present(stressed_frame(episodes[i], outcomes[i], cfg, cfg.seed,
                                                      Stress(**{factor: value}), table)[1],
                                       table=table)
                      for i in val]
            only_success = {name: name == "success" for name in table.outcome_names}
            wrong = [i for i, t in zip(val, truths) if t != only_success]
            assert got == pytest.approx(1 - len(wrong) / len(val)), (factor, value)
            assert entry["mistakes"][k] == wrong, (factor, value)
            low, high = entry["ci95"][k]
            assert 0.0 <= low <= got <= high <= 1.0 and high - low > 0.3  # 2 images: wide
    assert (tmp_path / "rob" / "robustness.png").stat().st_size > 5000


def test_resolution_same_depth_error_keeps_the_sensors_error_in_metres(small_run):
    """At half the size the plain ``resolution`` point keeps the sensor's pixel-unit errors (so
    twice the depth error); ``resolution_same_depth_error`` halves them, and its frame lies
    nearer the full-size frame (each 2 x 2 block's median) than the plain one does."""
    from training.chunks import load_chunks
    from training.config import NoiseConfig, dataset_config_from_dict, load_json
    from training.robustness import Stress, same_depth_error, stressed_frame

    noise = NoiseConfig(sigma_disparity_px=(0.04, 0.1), bias_disparity_px=0.1,
                        lowfreq_disparity_px=0.08, lateral_sigma_px=0.5,
                        disparity_subpixel=(6, 10), speckle_rate=4e-4)
    half = same_depth_error(noise, 0.5)
    assert half.sigma_disparity_px == pytest.approx((0.02, 0.05))
    assert (half.bias_disparity_px, half.lowfreq_disparity_px) == pytest.approx((0.05, 0.04))
    assert half.lateral_sigma_px == pytest.approx(0.25)
    assert half.disparity_subpixel == (12, 20)           # the same steps in metres
    assert half.speckle_rate == noise.speckle_rate and half.validate() == half
    assert same_depth_error(noise, 2.0).disparity_subpixel == (3, 5)

    cfg = dataset_config_from_dict(load_json(small_run / "config.json"))
    cfg = dataclasses.replace(cfg, tof=dataclasses.replace(cfg.tof, share=0.0))
    episodes = load_chunks(small_run / "simulate", cfg.episodes, cfg.chunk_size)
    outcomes, table = load_outcomes(small_run)
    full, _, _ = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed, Stress(), table)
    blocks = full.reshape(240, 2, 320, 2).transpose(0, 2, 1, 3).reshape(240, 320, 4)
    with warnings.catch_warnings():   # blocks with no valid depth stay NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        reference = np.nanmedian(blocks, axis=2)
    gaps = {}
    for stress in (Stress(resolution="320x240"), Stress(resolution_same_depth_error="320x240")):
        small, labels, k = stressed_frame(episodes[5], outcomes[5], cfg, cfg.seed, stress, table)
        assert small.shape == labels.shape == (240, 320) and (k.width, k.height) == (320, 240)
        both = np.isfinite(small) & np.isfinite(reference)
        gaps[stress] = float(np.median(np.abs(small[both] - reference[both])))
    plain, same = gaps.values()
    assert same < 0.8 * plain, gaps   # about 12 against 37 mm on this frame


def test_robustness_command_sweeps_only_the_factors_asked_for(small_run, tmp_path, capsys):
    from training.__main__ import main
    from training.config import load_json

    ckpt = make_checkpoint(tmp_path / "success_everywhere.pt", favour=SUCCESS)
    common = ["robustness", "--out", str(small_run), "--checkpoint", str(ckpt), "--images", "1"]
    assert main(common + ["--factors", "tilt", "--eval-out", str(tmp_path / "bad")]) == 2
    assert "unknown factor(s) tilt" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "rob"
    assert main(common + ["--factors", "camera_info", "--eval-out", str(out)]) == 0
    factors = load_json(out / "robustness.json")["factors"]
    assert list(factors) == ["camera_info"] and factors["camera_info"]["values"] == [True, False]
    from training.robustness import run_robustness

    with pytest.raises(ValueError, match="no factor"):
        run_robustness(ckpt, small_run, tmp_path / "none", images=1, sweeps={}, progress=False)
    with pytest.raises(ValueError, match="unknown factor"):
        run_robustness(ckpt, small_run, tmp_path / "none", images=1,
                       sweeps={"noise": (1.0, 2.0)}, progress=False)
    assert not (tmp_path / "none").exists()


def test_the_independent_set_is_cast_by_pybullet_and_scored_by_evaluate(small_run, tmp_path):
    """Its clean images agree with the analytic renderer on the same view (same geometry,
    another caster), its noise is its own, and evaluate scores it like any run."""
    from training.chunks import load_chunks
    from training.config import dataset_config_from_dict, load_json
    from training.fixture import episode_fixture
    from training.independent import RayWorld, draw_view, make_independent_set
    from training.render import Camera, read_pair, render, scene_boxes

    cfg = dataset_config_from_dict(load_json(small_run / "config.json"))
    episodes = load_chunks(small_run / "simulate", cfg.episodes, cfg.chunk_size)
    outcomes, table = load_outcomes(small_run)
    fixture = episode_fixture(episodes[1], cfg.scene)
    view = draw_view(cfg, fixture, np.random.default_rng(3))
    world = RayWorld()
    try:
        theirs, their_labels, _ = world.cast(view, world.build(episodes[1], outcomes[1],
                                                               cfg.scene, table))
    finally:
        world.close()
    camera = Camera(view["width"], view["height"], view["fx"], view["fy"], view["cx"],
                    view["cy"], np.array(view["position"]), np.array(view["rotation"]))
    ours, our_labels, _ = render(scene_boxes(episodes[1], outcomes[1], cfg.scene, table),
                                 fixture.room_floor_z, camera)
    assert np.mean(our_labels == their_labels) > 0.98
    both = np.isfinite(ours) & np.isfinite(theirs)
    assert both.mean() > 0.95 and np.median(np.abs(ours[both] - theirs[both])) < 1e-3

    out = tmp_path / "independent"
    manifest = make_independent_set(small_run, out, 3, seed=1, workers=1)
    assert [im["split"] for im in manifest["images"]] == ["val"] * 3
    for im in manifest["images"]:
        depth, labels = read_pair(out, im["episode"])
        assert depth.shape == (cfg.camera.height, cfg.camera.width)
        assert 0.02 < np.isnan(depth).mean() < 0.5 and (labels[np.isnan(depth)] == 255).all()
        assert abs(im["camera_info"]["fx"] / im["camera"]["fx"] - 1) <= 0.02
    ckpt = make_checkpoint(tmp_path / "success_everywhere.pt", favour=SUCCESS)
    report = evaluate(ckpt, out, "val", tmp_path / "eval_independent", backend="torch",
                      progress=False)
    assert report["n_images"] == 3 and report["data"] == str(out)
    again = make_independent_set(small_run, out, 3, seed=1, workers=1)   # resumes: all done
    assert again["images"] == manifest["images"]
    with pytest.raises(ValueError, match="another independent set"):
        make_independent_set(small_run, out, 3, seed=2, workers=1)


def test_class_weights_count_a_large_cache_in_chunks():
    """Counted 256 images at a time (a whole-cache bincount held 8 bytes a pixel and was
    killed for memory at 320 x 240): the same weights as one count over everything."""
    from training.train import class_weights

    rng = np.random.default_rng(0)
    labels = rng.choice(5, size=(600, 6, 8), p=[0.6, 0.2, 0.1, 0.07, 0.03]).astype(np.uint8)
    labels[:, 0, 0] = 4
    counts = np.bincount(labels.ravel(), minlength=5).astype(np.float64)
    expected = (counts.sum() / counts) ** 0.3
    got = class_weights(labels, 0.3, 5).numpy()
    np.testing.assert_allclose(got, expected / expected.mean(), rtol=1e-6)
    assert got[0] < got[1] < got[2] < got[3] < got[4]
