"""Outlier islands (training/islands.py): the suite's full-resolution ones and training's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from sensor_helpers import AUGMENT_SEED, augment_with_and_without

from training.config import ConfigError, TrainConfig
from training.islands import ISLAND_MAX_RADIUS_PX, add_islands, disc_kernels, working_islands

pytestmark = pytest.mark.unit


def test_islands_move_small_patches_nearer_and_farther_and_keep_the_rest() -> None:
    depth = np.full((240, 320), 2.0, np.float32)
    depth[:10] = np.nan                                      # no depth stays no depth
    out = add_islands(depth, 280.0, 1e-3, np.random.default_rng(0))
    moved = np.isfinite(out) & (np.abs(out - 2.0) > 1e-4)
    assert 0.002 < moved.mean() < 0.05
    assert (out[moved] < 2.0).any() and (out[moved] > 2.0).any()
    # Up to 4 px of disparity at 280 px x 0.075 m: 2 m reads between 1.14 and 8.4 m.
    assert out[moved].min() > 1.1 and out[moved].max() < 8.5
    assert np.isnan(out[:10]).all()
    np.testing.assert_array_equal(add_islands(depth, 280.0, 0.0, np.random.default_rng(0)),
                                  depth)


def test_training_islands_change_a_few_valid_working_pixels_and_draw_a_fixed_amount() -> None:
    depth = torch.full((4, 120, 160), 1.5)
    valid = torch.ones_like(depth)
    valid[:, :, :40] = 0
    gen = torch.Generator().manual_seed(1)
    out = working_islands(depth, valid, None, 3e-4, gen)
    changed = (out - depth).abs() > 1e-6
    assert not changed[:, :, :40].any()                      # never where there is no depth
    assert 0 < int(changed.sum()) < 4 * 100                  # at most ~92 an image
    assert (out[changed] < 1.5).any() and (out[changed] > 1.5).any()
    # The same number of draws whatever the rate: a run's stream after them is the same.
    a, b = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    working_islands(depth, valid, None, 3e-4, a)
    working_islands(depth, valid, None, 1e-5, b)
    assert torch.equal(torch.rand(3, generator=a), torch.rand(3, generator=b))


def test_augment_without_islands_draws_as_before_and_with_them_keeps_the_labels() -> None:
    from training.augment import augment

    depth = 1.5 + 0.1 * torch.rand(2, 120, 160, generator=torch.Generator().manual_seed(3))
    valid = torch.ones_like(depth)
    labels = torch.randint(0, 5, (2, 120, 160), generator=torch.Generator().manual_seed(4))
    plain, off, on = augment_with_and_without(depth, valid, labels, islands=3e-4)
    assert torch.equal(plain.depth, off.depth) and torch.equal(plain.labels, off.labels)
    assert torch.equal(on.labels, plain.labels) and torch.equal(on.valid, plain.valid)
    differs = (on.depth - plain.depth).abs() > 1e-6
    assert 0 < int(differs.sum()) < 200
    discs = augment(depth, valid, labels, torch.Generator().manual_seed(AUGMENT_SEED),
                    holes=0.5, islands=3e-4, island_discs=True)
    assert torch.equal(discs.labels, plain.labels)
    assert int(((discs.depth - plain.depth).abs() > 1e-6).sum()) >= int(differs.sum())


def test_islands_on_a_crop_are_as_dense_as_on_the_whole_image() -> None:
    # A 160 x 120 crop of a 320 x 240 image: a working pixel stands for 4 pixels at 640 x 480,
    # not the 16 it would as a whole 160 x 120 image, so about a quarter of the islands.
    depth = torch.full((64, 120, 160), 1.5)
    valid = torch.ones_like(depth)

    def changed(image_width: int | None) -> int:
        out = working_islands(depth, valid, None, 3e-4, torch.Generator().manual_seed(6),
                              image_width=image_width)
        return int(((out - depth).abs() > 1e-6).sum())

    whole, crop = changed(None), changed(320)
    assert crop > 0 and 2.5 < whole / crop < 6.0
    assert changed(160) == whole                               # its own width: the same


def test_aug_islands_is_checked_and_taken_on_crops() -> None:
    TrainConfig(aug_islands=3e-4).validate()
    TrainConfig(aug_islands=3e-4, input_size=(320, 240), train_crop=(160, 120)).validate()
    with pytest.raises(ConfigError, match="aug_islands"):
        TrainConfig(aug_islands=0.5).validate()
    with pytest.raises(ConfigError, match="aug_islands.*augment"):
        TrainConfig(aug_islands=3e-4, augment=False).validate()


def test_disc_kernels_cover_each_islands_area_in_working_pixels() -> None:
    for scale in (0.25, 0.5):
        kernels = disc_kernels(scale)
        areas = [(1.0 + math.pi * r * r) * scale ** 2 for r in range(ISLAND_MAX_RADIUS_PX + 1)]
        np.testing.assert_allclose(kernels.sum((1, 2, 3)).numpy(), areas, rtol=0.06)
        assert float(kernels.max()) <= 1.0


def test_disc_islands_span_several_pixels_at_320_x_240_and_draw_as_one_pixel_islands() -> None:
    depth = torch.full((16, 240, 320), 2.0)
    valid = torch.ones_like(depth)
    valid[:, :, :100] = 0

    def islands(discs: bool) -> tuple[torch.Tensor, torch.Tensor]:
        gen = torch.Generator().manual_seed(7)
        out = working_islands(depth, valid, None, 3e-4, gen, discs=discs)
        return (out - depth).abs() > 1e-3, torch.rand(3, generator=gen)

    (pixel, after_pixel), (disc, after_disc) = islands(False), islands(True)
    assert torch.equal(after_pixel, after_disc)              # the same draws either way
    assert not disc[:, :, :100].any()                        # never where there is no depth
    assert 2.5 < disc.sum() / pixel.sum() < 8.0              # a median island covers ~5 pixels


def test_aug_islands_discs_needs_islands() -> None:
    TrainConfig(aug_islands=3e-4, aug_islands_discs=True).validate()
    with pytest.raises(ConfigError, match="aug_islands_discs"):
        TrainConfig(aug_islands_discs=True).validate()
