"""The near-side height input channel (model.nearest_depth): a rim about one working pixel
wide keeps its true height at the working size, where the area resize averages it away."""

from __future__ import annotations

import math
import warnings

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


def test_near_depth_is_the_nearest_of_a_blocks_four_cell_means_and_zero_without_one() -> None:
    rng = np.random.default_rng(0)
    depth = (rng.random((48, 64)) + 1.0).astype(np.float32)
    depth[rng.random((48, 64)) < 0.3] = np.nan
    depth[:4, :4] = np.nan                      # a block with nothing valid
    depth[4:8, :4] = np.nan
    depth[4, 0] = 1.5                           # and one with a single valid pixel
    got = nearest_depth(depth, (16, 12))
    cells = depth.reshape(24, 2, 32, 2)
    with warnings.catch_warnings():           # empty cells and blocks: NaN, meant
        warnings.simplefilter("ignore", RuntimeWarning)
        means = np.nanmean(cells, axis=(1, 3))                     # (24, 32) cell means
        want = np.nanmin(means.reshape(12, 2, 16, 2), axis=(1, 3))
    np.testing.assert_allclose(got, np.nan_to_num(want, nan=0.0), rtol=1e-6)
    assert got[0, 0] == 0.0 and got[1, 0] == 1.5
    # Other sizes (smaller, larger) work through the same NaN-aware area resize.
    assert nearest_depth(depth, (20, 15)).shape == (15, 20)
    assert nearest_depth(depth, (100, 80)).shape == (80, 100)


def test_a_stray_near_return_is_averaged_with_its_cell_while_a_full_cell_counts() -> None:
    depth = np.full((8, 8), 2.0, np.float32)
    depth[1, 1] = 0.5                                 # one stray return in the first block
    got = nearest_depth(depth, (2, 2))
    assert got[0, 0] == pytest.approx((0.5 + 3 * 2.0) / 4) and got[1, 1] == 2.0
    depth[:2, 2:4] = 0.5                              # a whole cell of it: a thin edge
    assert nearest_depth(depth, (2, 2))[0, 0] == pytest.approx(0.5)


def test_a_thin_wall_keeps_its_height_in_the_nearest_channel_not_in_the_mean_one() -> None:
    depth = _floor_with_a_thin_wall()
    x = preprocess(depth, (160, 120), NEAREST_NORMALISATION)
    assert x.shape == (4, 120, 160)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    mean_height, nearest_height = x[2, 10:110] * scale, x[3, 10:110] * scale
    # Each of the two working columns holds half the wall: the average reads about half its
    # height, the near side all of it (to a few mm: the fitted floor and the slant).
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
    with pytest.raises(ValueError, match="near-side depth"):
        network_input(torch.from_numpy(depth)[None], torch.from_numpy(frac)[None],
                      NEAREST_NORMALISATION)
