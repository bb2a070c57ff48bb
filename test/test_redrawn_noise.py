"""Re-drawn training noise and dropout (training/redrawn_noise.py): the level follows the
working size as area-averaging does, the noise grows with z^2, the dropout stays within its
share, and each helper's draws depend only on the generator."""

from __future__ import annotations

import math

import pytest
import torch

from training.redrawn_noise import (
    MAX_DROPOUT_SHARE,
    SENSOR_NOISE_PER_Z2,
    axial_noise,
    drop_pixels,
    noise_levels,
)

pytestmark = pytest.mark.unit


def test_noise_levels_lie_in_the_drawn_range_and_halve_per_halved_side():
    full = noise_levels(4000, (480, 640), 2.0, torch.Generator().manual_seed(0))
    half = noise_levels(4000, (240, 320), 2.0, torch.Generator().manual_seed(0))
    assert full.shape == (4000, 1, 1)
    assert float(full.min()) >= 0.0 and float(full.max()) <= 2.0 * SENSOR_NOISE_PER_Z2
    assert float(full.max()) > 1.9 * SENSOR_NOISE_PER_Z2  # U(0, 2x) reaches near its top
    # A 2 x 2 average of independent noise has half its sd: the same draws, halved.
    assert torch.allclose(half, full / 2)
    assert float(noise_levels(8, (120, 160), 0.0, torch.Generator()).abs().max()) == 0.0


def test_axial_noise_grows_with_the_square_of_depth():
    depth = torch.cat([torch.full((1, 200, 200), 1.0), torch.full((1, 200, 200), 3.0)])
    level = torch.full((2, 1, 1), 0.001)
    noise = axial_noise(depth, level, torch.Generator().manual_seed(1))
    sd_near, sd_far = float(noise[0].std()), float(noise[1].std())
    assert sd_near == pytest.approx(0.001, rel=0.05)
    assert sd_far == pytest.approx(0.009, rel=0.05)  # 0.001 * 3^2
    assert abs(float(noise.mean())) < 1e-3


def test_drop_pixels_removes_at_most_its_share_and_only_sets_zeros():
    valid = torch.rand(300, 60, 80, generator=torch.Generator().manual_seed(2)) * 0.5 + 0.5
    dropped = drop_pixels(valid, torch.Generator().manual_seed(3))
    gone = (dropped == 0) & (valid > 0)
    share = gone.flatten(1).float().mean(1)
    assert float(share.max()) <= MAX_DROPOUT_SHARE + 0.01  # binomial slack on 4,800 pixels
    assert float(share.mean()) == pytest.approx(MAX_DROPOUT_SHARE / 2, rel=0.15)
    kept = dropped != 0
    assert torch.equal(dropped[kept], valid[kept])
    again = drop_pixels(valid, torch.Generator().manual_seed(3))
    assert torch.equal(again, dropped)  # the generator alone decides


def test_each_helper_draws_the_same_numbers_as_the_formula_it_replaced():
    """The draw order the runs of shelf model 0.16.0 and earlier used: level, noise, dropout."""
    depth = 1.5 + torch.rand(3, 24, 32, generator=torch.Generator().manual_seed(4))
    valid = torch.ones(3, 24, 32)
    gen = torch.Generator().manual_seed(5)
    level = noise_levels(3, (24, 32), 1.5, gen)
    noisy = depth + axial_noise(depth, level, gen)
    kept = drop_pixels(valid, gen)

    ref = torch.Generator().manual_seed(5)
    per_pixel = SENSOR_NOISE_PER_Z2 * math.sqrt(24 * 32 / (640 * 480))
    ref_level = per_pixel * 1.5 * torch.rand(3, 1, 1, generator=ref)
    ref_noisy = depth + torch.randn(depth.shape, generator=ref) * ref_level * depth ** 2
    drop = torch.rand(depth.shape, generator=ref) < 0.03 * torch.rand(3, 1, 1, generator=ref)
    assert torch.equal(level, ref_level) and torch.equal(noisy, ref_noisy)
    assert torch.equal(kept, torch.where(drop, torch.zeros_like(valid), valid))
