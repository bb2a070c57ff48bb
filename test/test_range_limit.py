"""The range limit's band re-drawn on training images (training/range_limit.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from sensor_helpers import augment_with_and_without

from training.config import ConfigError, TrainConfig
from training.range_limit import draw_limits, range_limit_band, truncate_at_limit

pytestmark = pytest.mark.unit


def flat(z: float, shape=(1, 120, 160)) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.full(shape, z), torch.ones(shape)


def test_a_floor_at_the_limit_keeps_half_its_readings_and_reads_nearer_by_the_truncated_mean(
) -> None:
    depth, valid = flat(4.0, (4, 120, 160))
    per_z2 = torch.full((4, 1, 1), 0.004)                # sd 6.4 cm at 4 m
    out, kept = truncate_at_limit(depth, valid, torch.full((4, 1, 1), 4.0), per_z2,
                                  torch.Generator().manual_seed(0))
    sd = 0.004 * 16.0
    assert abs(float(kept.mean()) - 0.5) < 0.01          # Phi(0) of 16 readings a pixel
    some = kept > 0
    # The survivors' mean: z - sd phi(0) / Phi(0) = z - 0.798 sd.
    expected = 4.0 - sd * math.sqrt(2 / math.pi)
    assert abs(float(out[some].mean()) - expected) < 0.002
    assert (out[~some] == 0).all()                       # none survived: no depth
    # Each working pixel keeps 0, 1/16, ... 16/16 of its readings.
    assert torch.allclose(kept * 16, torch.round(kept * 16))


def test_pixels_well_inside_the_range_and_images_without_a_limit_stay_exactly_as_they_were(
) -> None:
    depth, valid = flat(2.0)
    valid[:, :, :20] = 0.25
    per_z2 = torch.full((1, 1, 1), 0.004)
    near, near_valid = truncate_at_limit(depth, valid, torch.full((1, 1, 1), 4.0), per_z2,
                                         torch.Generator().manual_seed(1))
    assert torch.equal(near, depth) and torch.equal(near_valid, valid)     # 2 m: 12 sds in
    none, none_valid = truncate_at_limit(depth, valid, torch.full((1, 1, 1), math.inf),
                                         per_z2, torch.Generator().manual_seed(1))
    assert torch.equal(none, depth) and torch.equal(none_valid, valid)


def test_pixels_without_depth_never_gain_any() -> None:
    depth, valid = flat(4.0)
    depth[:, :10], valid[:, :10] = 0.0, 0.0
    out, kept = truncate_at_limit(depth, valid, torch.full((1, 1, 1), 4.0),
                                  torch.full((1, 1, 1), 0.004), torch.Generator().manual_seed(2))
    assert (out[:, :10] == 0).all() and (kept[:, :10] == 0).all()


def test_limits_fall_in_the_far_quarter_of_each_chosen_image() -> None:
    rows = torch.linspace(1.0, 4.0, 120)[:, None].expand(120, 160)
    depth = rows.expand(8, 120, 160).clone()
    valid = torch.ones_like(depth)
    valid[3] = 0                                          # an image without depth: no limit
    limits = draw_limits(depth, valid, 1.0, torch.Generator().manual_seed(3))
    finite = torch.isfinite(limits.flatten())
    assert finite.tolist() == [True, True, True, False, True, True, True, True]
    assert ((limits[finite] >= 3.24) & (limits[finite] <= 4.0)).all()
    assert torch.isinf(draw_limits(depth, valid, 0.0, torch.Generator().manual_seed(3))).all()


def test_more_noise_makes_a_nearer_band() -> None:
    rows = torch.linspace(3.0, 4.2, 120)[:, None].expand(120, 160)
    depth = rows.expand(16, 120, 160).clone()
    valid = torch.ones_like(depth)
    bias = []
    for level in (0.0, 0.0008):                          # 0 and ~2x the sensor's at 160 x 120
        out, kept = range_limit_band(depth, valid, torch.full((16, 1, 1), level), 1.0,
                                     torch.Generator().manual_seed(4))
        some = kept > 0
        bias.append(float((depth - out)[some].mean()))
    assert 0.0 < bias[0] < bias[1]


def test_augment_with_the_band_keeps_labels_and_without_it_draws_as_before() -> None:
    rows = torch.linspace(2.5, 4.5, 120)[:, None].expand(120, 160)
    depth = rows.expand(4, 120, 160).clone()
    labels = torch.randint(0, 5, (4, 120, 160), generator=torch.Generator().manual_seed(5))
    plain, off, on = augment_with_and_without(depth, torch.ones_like(depth), labels,
                                              range_limit=1.0)
    assert torch.equal(plain.depth, off.depth) and torch.equal(plain.valid, off.valid)
    assert torch.equal(on.labels, plain.labels)
    assert (on.valid < plain.valid).any()                 # far readings lost
    assert not torch.equal(on.depth, plain.depth)


def test_aug_range_limit_is_checked() -> None:
    TrainConfig(aug_range_limit=0.5).validate()
    TrainConfig(aug_range_limit=0.5, input_size=(320, 240), train_crop=(160, 120)).validate()
    with pytest.raises(ConfigError, match="aug_range_limit"):
        TrainConfig(aug_range_limit=1.5).validate()
    with pytest.raises(ConfigError, match="aug_range_limit.*augment"):
        TrainConfig(aug_range_limit=0.5, augment=False).validate()
    with pytest.raises(ConfigError, match="aug_range_limit.*nearest_height"):
        TrainConfig(aug_range_limit=0.5, nearest_height=True,
                    relief_window_px=0).validate()


def test_a_batch_of_the_default_size_comes_back_whole_and_finite() -> None:
    depth = torch.from_numpy(np.linspace(1.0, 4.5, 120 * 160, dtype=np.float32)
                             .reshape(1, 120, 160)).expand(32, 120, 160).clone()
    valid = torch.ones_like(depth)
    out, kept = range_limit_band(depth, valid, torch.full((32, 1, 1), 4e-4), 0.5,
                                 torch.Generator().manual_seed(7))
    assert out.shape == depth.shape and kept.shape == valid.shape
    assert torch.isfinite(out).all()
