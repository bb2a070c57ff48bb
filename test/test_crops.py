"""Training on crops of a finer working size (training/crops.py): a crop's heights are the
whole image's, its noise moves depth and height along the same rays, its labels stay on
its objects, and the option is refused where it cannot act."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from task_outcome_ros.floor import backproject, support_plane
from task_outcome_ros.labels import FIRST_OUTCOME_ID, IGNORE
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    INTRINSICS_FROM_CAMERA_INFO,
    check_normalisation,
    network_input,
)
from training.config import ConfigError, TrainConfig
from training.crops import (
    HEIGHT_KEY,
    PLANE_OFFSET_KEY,
    crop_batch,
    crop_origins,
    measure_heights,
    move_along_rays,
)
from training.render import Camera, SceneBox, look_at, render

pytestmark = pytest.mark.unit

NORM = check_normalisation({**DEFAULT_NORMALISATION, "intrinsics": INTRINSICS_FROM_CAMERA_INFO})


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


def test_measured_heights_are_the_whole_images_height_channel():
    arrays = scene_arrays()
    measure_heights(arrays, NORM)
    depth, valid, intrinsics = tensors(arrays)
    fitted = network_input(depth, valid, NORM, intrinsics)
    given = network_input(depth, valid, NORM, height_m=torch.from_numpy(arrays[HEIGHT_KEY]))
    assert torch.equal(fitted[:, :2], given[:, :2])
    # float16 storage: heights under 1 m keep 0.5 mm
    assert (fitted[:, 2] - given[:, 2]).abs().max() < 0.0005 / NORM["height_scale_m"]
    box = torch.from_numpy(arrays["labels"] == 2)
    assert fitted[:, 2][box].max() * NORM["height_scale_m"] == pytest.approx(0.2, abs=0.01)


def test_precomputed_heights_are_refused_where_the_channel_is_not_the_plain_height():
    arrays = scene_arrays(1)
    depth, valid, _ = tensors(arrays)
    relief = {**NORM, "relief_window_px": 15}
    with pytest.raises(ValueError, match="plain height channel"):
        network_input(depth, valid, relief, height_m=torch.zeros_like(depth))
    with pytest.raises(ValueError, match="shape"):
        network_input(depth, valid, NORM, height_m=torch.zeros(1, 60, 80))


def test_noise_moves_the_height_as_a_refit_on_the_same_plane_would():
    arrays = scene_arrays()
    measure_heights(arrays, NORM)
    depth, valid, intrinsics = tensors(arrays)
    has = valid > 0
    dz = 0.02 * torch.randn(depth.shape, generator=torch.Generator().manual_seed(1)) * has
    moved_depth, moved_height = move_along_rays(
        depth, has, torch.from_numpy(arrays[HEIGHT_KEY]).float(),
        torch.from_numpy(arrays[PLANE_OFFSET_KEY])[:, None, None], dz)
    normal, offset = support_plane(backproject(depth, NORM["focal_over_width"], intrinsics), has,
                                   NORM["floor_fit"])
    points = backproject(moved_depth, NORM["focal_over_width"], intrinsics)
    want = (points * normal[:, None, None]).sum(-1) - offset[:, None, None]
    assert torch.equal(moved_depth, depth + dz)
    assert (moved_height - want)[has].abs().max() < 0.001      # the float16 heights' own error
    assert (moved_height - torch.from_numpy(arrays[HEIGHT_KEY]).float())[has].abs().mean() > 0.005
    assert (moved_height[~has] == 0).all()


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
    measure_heights(arrays, NORM)
    depth, valid, intrinsics = tensors(arrays)
    whole = network_input(depth, valid, NORM, intrinsics)
    labels = torch.from_numpy(arrays["labels"]).long()
    gen = torch.Generator().manual_seed(5)
    same_draws = torch.Generator().set_state(gen.get_state())
    origins = crop_origins(arrays["labels"], (96, 72), same_draws)
    x, got_labels = crop_batch(arrays, np.arange(3), (96, 72), gen, 0.0, NORM)
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
        assert (x[i, 2][kept] - cut[2][kept]).abs().max() < 0.001


def test_the_crop_is_refused_larger_than_the_working_size_or_with_what_moves_heights():
    base = TrainConfig(input_size=(320, 240), train_crop=(160, 120)).validate()
    assert base.train_crop == (160, 120)
    for bad, match in (({"train_crop": (400, 120)}, r"train_crop\[0\]"),
                       ({"train_crop": (160, 16)}, r"train_crop\[1\]"),
                       ({"aug_roll_deg": 15.0}, "aug_roll_deg"),
                       ({"aug_holes": 0.5}, "aug_holes"),
                       ({"relief_window_px": 15}, "relief_window_px"),
                       ({"augment": False, "aug_noise": 0.0}, "augment")):
        with pytest.raises(ConfigError, match=match):
            dataclasses.replace(base, **bad).validate()
