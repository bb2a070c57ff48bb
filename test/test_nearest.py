"""The near-point height input channel (model.nearest_depth): a rim about one working pixel
wide keeps its true height at the working size, where the area resize averages it away."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from task_outcome_ros.floor import FOCAL_OVER_WIDTH
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    NEAREST_HEIGHT,
    check_normalisation,
    input_channels,
    nearest_depth,
    network_input,
    preprocess,
    preprocess_batch,
    resize_depth,
)

pytestmark = pytest.mark.unit

NEAREST_NORMALISATION = {**DEFAULT_NORMALISATION, NEAREST_HEIGHT: True}
WALL_HEIGHT = 0.2


def _floor_with_a_thin_wall(h: int = 480, w: int = 640) -> np.ndarray:
    """Depth of a floor seen from 1.5 m, pitched down 60 degrees (the nominal camera), with a
    wall 4 input pixels wide and ``WALL_HEIGHT`` tall down the middle, placed so that it
    straddles two working pixels of the 4x smaller working size."""
    a = math.radians(60.0)
    normal = np.array([0.0, -math.cos(a), -math.sin(a)])
    f = FOCAL_OVER_WIDTH * w
    u, v = (np.arange(w) - (w - 1) / 2) / f, (np.arange(h) - (h - 1) / 2) / f
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1)
    top = np.zeros((h, w))
    top[:, 322:326] = WALL_HEIGHT               # working columns 80 (320-323) and 81 (324-327)
    return ((top - 1.5) / (rays @ normal)).astype(np.float32)


def test_near_depth_is_a_blocks_quarter_nearest_valid_depth_and_zero_without_one() -> None:
    gen = torch.Generator().manual_seed(0)
    depth = torch.rand(2, 48, 64, generator=gen) + 1.0
    valid = torch.rand(2, 48, 64, generator=gen) > 0.3
    valid[1, :4, :4] = False                    # a block with nothing valid
    valid[1, 4:8, :4] = False
    valid[1, 4, 0] = valid[1, 5, 1] = True      # and one with two valid pixels
    got = nearest_depth(depth, valid, (16, 12)).numpy()
    blocks = np.where(valid, depth, np.inf).reshape(2, 12, 4, 16, 4).transpose(0, 1, 3, 2, 4)
    ordered = np.sort(blocks.reshape(2, 12, 16, 16), axis=-1)
    count = np.isfinite(ordered).sum(-1)
    # The 4th nearest of 16, or the farthest valid one when fewer than 4 are valid.
    want = np.take_along_axis(ordered, np.clip(np.minimum(count, 4) - 1, 0, None)[..., None],
                              -1)[..., 0]
    np.testing.assert_array_equal(got, np.where(count > 0, want, 0).astype(np.float32))
    assert got[1, 0, 0] == 0.0
    assert got[1, 1, 0] == max(depth[1, 4, 0].item(), depth[1, 5, 1].item())
    # Other factors (resampled to the next multiple first) and no resize at all work too.
    assert nearest_depth(depth, valid, (20, 15)).shape == (2, 15, 20)
    assert nearest_depth(depth, valid, (100, 80)).shape == (2, 80, 100)
    same = nearest_depth(depth, valid, (64, 48))
    assert torch.equal(same, torch.where(valid, depth, torch.zeros_like(depth)))


def test_three_stray_near_returns_in_a_block_do_not_move_its_near_depth() -> None:
    depth = torch.full((1, 8, 8), 2.0)
    depth[0, 1, 1] = depth[0, 2, 3] = depth[0, 0, 2] = 0.5      # three in the first block
    got = nearest_depth(depth, torch.ones_like(depth, dtype=torch.bool), (2, 2))
    assert torch.equal(got, torch.full((1, 2, 2), 2.0))
    depth[0, 3, 0] = 0.5                                          # a fourth: a quarter of it
    got = nearest_depth(depth, torch.ones_like(depth, dtype=torch.bool), (2, 2))
    assert got[0, 0, 0].item() == 0.5 and got[0, 1, 1].item() == 2.0


def test_a_thin_wall_keeps_its_height_in_the_nearest_channel_not_in_the_mean_one() -> None:
    depth = _floor_with_a_thin_wall()
    x = preprocess(depth, (160, 120), NEAREST_NORMALISATION)
    assert x.shape == (4, 120, 160)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    mean_height, nearest_height = x[2, 10:110] * scale, x[3, 10:110] * scale
    # Each of the two working columns holds half the wall: the average reads about half its
    # height, the near points all of it (to a few mm: the fitted floor and the slant).
    assert np.abs(mean_height[:, 80:82] - WALL_HEIGHT / 2).max() < 0.03
    assert np.abs(nearest_height[:, 80:82] - WALL_HEIGHT).max() < 0.005
    # Elsewhere the two channels tell the same floor, within the slant of a block.
    floor = np.r_[0:70, 90:160]
    assert np.abs(nearest_height[:, floor]).max() < 0.01
    assert np.abs(mean_height[:, floor]).max() < 0.005


def test_numpy_and_torch_preprocessing_agree_with_the_nearest_channel() -> None:
    depths = np.stack([_floor_with_a_thin_wall(), _floor_with_a_thin_wall()[::-1].copy()])
    depths[0, :40, :60] = np.nan                # invalid: neither path may use it
    one = np.stack([preprocess(d, (160, 120), NEAREST_NORMALISATION) for d in depths])
    batch = preprocess_batch(torch.from_numpy(depths), (160, 120), NEAREST_NORMALISATION)
    np.testing.assert_allclose(batch.numpy(), one, atol=1e-5)


def test_the_channel_is_declared_by_the_normalisation_and_required_by_network_input() -> None:
    assert input_channels(NEAREST_NORMALISATION) == 4
    assert input_channels({**NEAREST_NORMALISATION, "relief_window_px": 9}) == 5
    assert check_normalisation(NEAREST_NORMALISATION)[NEAREST_HEIGHT] is True
    for bad in ({**NEAREST_NORMALISATION, NEAREST_HEIGHT: 1},
                {k: v for k, v in NEAREST_NORMALISATION.items()
                 if k not in ("height_scale_m", "focal_over_width", "floor_fit")}):
        with pytest.raises(ValueError, match=NEAREST_HEIGHT):
            check_normalisation(bad)
    depth, frac = resize_depth(_floor_with_a_thin_wall(), (160, 120))
    with pytest.raises(ValueError, match="nearest-point depth"):
        network_input(torch.from_numpy(depth)[None], torch.from_numpy(frac)[None],
                      NEAREST_NORMALISATION)
