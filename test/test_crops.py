"""Training on crops of a finer working size (training/crops.py): a crop's heights are the
whole image's, they follow its depths through noise and roll, its labels stay on its objects,
and the option is refused where it cannot act."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from task_outcome_ros.labels import FIRST_OUTCOME_ID, IGNORE
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    INTRINSICS_FROM_CAMERA_INFO,
    check_normalisation,
    network_input,
)
from training.augment import Augmentations
from training.config import ConfigError, TrainConfig
from training.crops import (
    PLANE_NORMAL_KEY,
    PLANE_OFFSET_KEY,
    crop_batch,
    crop_origins,
    heights_along_rays,
    image_intrinsics,
    measure_planes,
    roll_margins,
)
from training.render import Camera, SceneBox, look_at, render
from training.roll import roll_sources

pytestmark = pytest.mark.unit

NORM = check_normalisation({**DEFAULT_NORMALISATION, "intrinsics": INTRINSICS_FROM_CAMERA_INFO})
QUIET = Augmentations(noise_level=0.0)          # no re-drawn noise: the crops are comparable
HOLED = Augmentations(noise_level=0.0, holes=0.5)


def scene_arrays(n: int = 3) -> dict:
    """``n`` cached-like images of a box on a tilted floor from cameras 1.6-2.2 m away, each
    with its own off-centre principal point."""
    depths, labels, intrinsics = [], [], []
    for i in range(n):
        position = np.array([-1.2 - 0.2 * i, 0.3, 1.3])
        camera = Camera(160, 120, 138.0 + 3 * i, 133.0, 82.0 - i, 58.0 + i, position,
                        look_at(position, np.zeros(3), 0.0, 4.0 * i))
        box = SceneBox(np.array([0.2, 0.12, 0.1]), np.array([0.05, -0.1, 0.1]), np.eye(3), 2)
        depth, label, _ = render([box], 0.0, camera)
        depths.append(depth)
        labels.append(label)
        intrinsics.append(camera.normalised())
    depth = np.stack(depths)
    valid = np.isfinite(depth)
    return {"depth": np.where(valid, depth, 0.0).astype(np.float16),
            "valid": valid.astype(np.float16), "labels": np.stack(labels).astype(np.uint8),
            "intrinsics": np.stack(intrinsics).astype(np.float32), "indices": np.arange(n)}


def tensors(arrays: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (torch.from_numpy(arrays["depth"].astype(np.float32)),
            torch.from_numpy(arrays["valid"].astype(np.float32)),
            torch.from_numpy(arrays["intrinsics"]))


def whole_heights(arrays: dict, norm: dict) -> torch.Tensor:
    """``heights_along_rays`` over every pixel of the whole images, with the camera ``norm``
    says the heights use."""
    depth, valid, _ = tensors(arrays)
    n, h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32),
                          torch.arange(w, dtype=torch.float32), indexing="ij")
    return heights_along_rays(depth, valid > 0, u.expand(n, h, w), v.expand(n, h, w), (w, h),
                              torch.from_numpy(arrays[PLANE_NORMAL_KEY]),
                              torch.from_numpy(arrays[PLANE_OFFSET_KEY]),
                              image_intrinsics(arrays, slice(None), norm),
                              norm["focal_over_width"])


@pytest.mark.parametrize("norm", [NORM, check_normalisation(DEFAULT_NORMALISATION)],
                         ids=["camera_info", "nominal camera"])
def test_heights_along_the_rays_are_the_whole_images_height_channel(norm):
    arrays = scene_arrays()
    measure_planes(arrays, norm)
    depth, valid, intrinsics = tensors(arrays)
    fitted = network_input(depth, valid, norm, intrinsics)
    given = network_input(depth, valid, norm, height_m=whole_heights(arrays, norm))
    assert torch.equal(fitted[:, :2], given[:, :2])
    assert (fitted[:, 2] - given[:, 2]).abs().max() < 1e-5
    box = torch.from_numpy(arrays["labels"] == 2)
    if norm is NORM:  # the true camera: the box's top at its true 0.2 m
        assert fitted[:, 2][box].max() * NORM["height_scale_m"] == pytest.approx(0.2, abs=0.01)


def test_precomputed_heights_are_refused_where_the_channel_is_not_the_plain_height():
    arrays = scene_arrays(1)
    depth, valid, _ = tensors(arrays)
    relief = {**NORM, "relief_window_px": 15}
    with pytest.raises(ValueError, match="plain height channel"):
        network_input(depth, valid, relief, height_m=torch.zeros_like(depth))
    with pytest.raises(ValueError, match="shape"):
        network_input(depth, valid, NORM, height_m=torch.zeros(1, 60, 80))


def test_crops_lie_inside_the_image_and_mostly_on_an_outcome():
    labels = np.zeros((200, 96, 128), np.uint8)
    labels[:, 70:80, 100:110] = FIRST_OUTCOME_ID          # one small object in a corner
    labels[:, 0:5, :] = IGNORE
    labels[150:] = 0                                       # 50 images without an outcome
    first = crop_origins(labels, (64, 48), torch.Generator().manual_seed(0))
    again = crop_origins(labels, (64, 48), torch.Generator().manual_seed(0))
    assert np.array_equal(first, again)                    # seeded
    x, y = first[:, 0], first[:, 1]
    assert (x >= 0).all() and (x <= 128 - 64).all() and (y >= 0).all() and (y <= 96 - 48).all()
    holds = np.array([(labels[i, yi:yi + 48, xi:xi + 64] == FIRST_OUTCOME_ID).any()
                      for i, (xi, yi) in enumerate(first)])
    # 75 % centred on it (give or take the draw); those anywhere hold it a quarter of the time
    assert 0.65 < holds[:150].mean() < 0.95
    assert not holds[150:].any()
    assert len(np.unique(first[150:], axis=0)) > 20        # images without one: anywhere


def test_a_crop_batch_is_the_whole_images_input_cut_out_and_mirrored():
    arrays = scene_arrays()
    measure_planes(arrays, NORM)
    depth, valid, intrinsics = tensors(arrays)
    whole = network_input(depth, valid, NORM, intrinsics)
    labels = torch.from_numpy(arrays["labels"]).long()
    gen = torch.Generator().manual_seed(5)
    same_draws = torch.Generator().set_state(gen.get_state())
    origins = crop_origins(arrays["labels"], (96, 72), same_draws)
    x, got_labels = crop_batch(arrays, np.arange(3), (96, 72), gen, NORM, QUIET)
    assert x.shape == (3, 3, 72, 96) and got_labels.shape == (3, 72, 96)
    for i, (cx, cy) in enumerate(origins):
        cut = whole[i, :, cy:cy + 72, cx:cx + 96]
        cut_labels = labels[i, cy:cy + 72, cx:cx + 96]
        if not torch.equal(got_labels[i], cut_labels):     # mirrored
            cut, cut_labels = cut.flip(-1), cut_labels.flip(-1)
        assert torch.equal(got_labels[i], cut_labels)
        kept = x[i, 1] > 0                                   # the 0-3 % dropped lose depth only
        assert kept.float().mean() > 0.9
        assert torch.equal(x[i, :2][:, kept], cut[:2][:, kept])
        assert (x[i, 2][kept] - cut[2][kept]).abs().max() < 1e-5


def test_a_turned_crop_keeps_its_heights_and_labels_on_the_box():
    arrays = scene_arrays()
    measure_planes(arrays, NORM)
    gen = torch.Generator().manual_seed(2)
    plain, plain_labels = crop_batch(arrays, np.arange(3), (96, 72), gen, NORM, QUIET)
    gen = torch.Generator().manual_seed(2)
    x, labels = crop_batch(arrays, np.arange(3), (96, 72), gen, NORM,
                           dataclasses.replace(QUIET, roll_deg=20.0))
    for mirrored in (plain_labels, plain_labels.flip(-1)):   # the mirror is drawn after it
        turned = (labels != mirrored) & (labels != IGNORE) & (mirrored != IGNORE)
        assert turned.float().mean() > 0.01                # it did turn
    scale = NORM["height_scale_m"]
    for i in range(3):
        box, floor = labels[i] == 2, (labels[i] == 0) & (x[i, 1] > 0.99)
        assert int(box.sum()) == pytest.approx(int((plain_labels[i] == 2).sum()), rel=0.15)
        assert x[i, 2][box].max() * scale == pytest.approx(0.2, abs=0.01)   # its top, 0.2 m
        assert (x[i, 2][floor] * scale).abs().quantile(0.99) < 0.01         # the floor, 0 m


def test_islands_on_crops_move_depths_and_heights_and_keep_the_labels():
    arrays = scene_arrays()
    measure_planes(arrays, NORM)
    plain, plain_labels = crop_batch(arrays, np.arange(3), (96, 72),
                                     torch.Generator().manual_seed(3), NORM, HOLED)
    off, off_labels = crop_batch(arrays, np.arange(3), (96, 72),
                                 torch.Generator().manual_seed(3), NORM,
                                 dataclasses.replace(HOLED, islands=0.0))
    assert torch.equal(off, plain) and torch.equal(off_labels, plain_labels)  # 0: as before
    x, labels = crop_batch(arrays, np.arange(3), (96, 72), torch.Generator().manual_seed(3),
                           NORM, dataclasses.replace(HOLED, islands=1e-3))
    assert torch.equal(labels, plain_labels) and torch.equal(x[:, 1], plain[:, 1])
    moved = (x[:, 0] - plain[:, 0]).abs() > 1e-6
    assert 0 < int(moved.sum()) < 0.05 * moved.numel()
    assert not moved[plain[:, 1] == 0].any()                  # never where there is no depth
    height_moved = (x[:, 2] - plain[:, 2]).abs() > 1e-6        # heights follow, only there
    assert not height_moved[~moved].any() and height_moved[moved].float().mean() > 0.9


def test_islands_on_crops_are_drawn_at_the_whole_images_density_and_focal(monkeypatch):
    import training.crops as crops

    arrays = scene_arrays()
    measure_planes(arrays, NORM)
    seen = {}

    def spy(depth, valid, intrinsics, max_rate, gen, image_width=None, discs=False):
        seen.update(shape=tuple(depth.shape), intrinsics=intrinsics, image_width=image_width,
                    discs=discs)
        return depth

    monkeypatch.setattr(crops, "working_islands", spy)
    crop_batch(arrays, np.array([2, 0]), (96, 72), torch.Generator().manual_seed(3), NORM,
               dataclasses.replace(QUIET, islands=1e-3, island_discs=True))
    assert seen["shape"] == (2, 72, 96) and seen["image_width"] == 160   # the cache's width
    assert seen["discs"]
    np.testing.assert_array_equal(seen["intrinsics"].numpy(), arrays["intrinsics"][[2, 0]])


def test_the_range_limit_band_on_crops_counts_readings_at_the_whole_images_size(monkeypatch):
    import training.crops as crops

    arrays = scene_arrays()
    measure_planes(arrays, NORM)
    seen = {}

    def spy(depth, valid, level, share, gen, size=None):
        seen.update(shape=tuple(depth.shape), share=share, size=size)
        return depth, valid

    monkeypatch.setattr(crops, "range_limit_band", spy)
    x, labels = crop_batch(arrays, np.array([2, 0]), (96, 72), torch.Generator().manual_seed(3),
                           NORM, Augmentations(range_limit=0.5))
    assert seen == {"shape": (2, 72, 96), "share": 0.5, "size": (120, 160)}
    assert x.shape[0] == 2 and labels.shape == (2, 72, 96)


def test_the_roll_margins_hold_the_turned_crop():
    for crop, deg in (((160, 120), 15.0), ((96, 72), 45.0), ((64, 128), 5.0)):
        mx, my = roll_margins(crop, deg)
        window = (crop[0] + 2 * mx, crop[1] + 2 * my)
        centre = torch.tensor([[(window[0] - 1) / 2, (window[1] - 1) / 2]] * 2)
        angles = torch.tensor([math.radians(deg), -math.radians(deg)])
        source = roll_sources(angles, centre, torch.ones(2, 2), window[1], window[0])
        inner = source[:, my:my + crop[1], mx:mx + crop[0]]
        assert inner[..., 0].min() >= 0 and inner[..., 0].max() <= window[0] - 1
        assert inner[..., 1].min() >= 0 and inner[..., 1].max() <= window[1] - 1


def test_the_crop_is_refused_larger_than_the_working_size_or_with_other_height_channels():
    base = TrainConfig(input_size=(320, 240), train_crop=(160, 120)).validate()
    assert base.train_crop == (160, 120)
    assert dataclasses.replace(base, aug_roll_deg=15.0, aug_holes=0.5).validate()
    for bad, match in (({"train_crop": (400, 120)}, r"train_crop\[0\]"),
                       ({"train_crop": (160, 16)}, r"train_crop\[1\]"),
                       ({"nearest_height": True}, "nearest_height"),
                       ({"relief_window_px": 15}, "relief_window_px"),
                       ({"augment": False, "aug_noise": 0.0}, "augment")):
        with pytest.raises(ConfigError, match=match):
            dataclasses.replace(base, **bad).validate()
