"""Camera roll as a training augmentation (training/roll.py): a turned image is what a rolled
camera renders, labels and depths move together, and the option is refused where it cannot
act."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from task_outcome_ros.labels import BACKGROUND, IGNORE
from training.config import ConfigError, TrainConfig
from training.render import Camera, SceneBox, look_at, render
from training.roll import depth_edges, pixel_noise, principal_points, roll_images, roll_sources

pytestmark = pytest.mark.unit


def rendered(roll_deg: float) -> tuple[np.ndarray, np.ndarray, Camera]:
    """Clean depth and labels of a box on a floor, from a camera 2 m away looking down at 45°
    with an off-centre principal point and fx != fy, rolled by ``roll_deg``."""
    target = np.zeros(3)
    position = np.array([-1.4, 0.3, 1.4])
    camera = Camera(160, 120, 140.0, 132.0, 83.0, 57.0, position,
                    look_at(position, target, 0.0, roll_deg))
    box = SceneBox(np.array([0.2, 0.12, 0.1]), np.array([0.05, -0.1, 0.1]), np.eye(3), 2)
    depth, labels, _ = render([box], 0.0, camera)
    return depth, labels, camera


def as_batch(depth: np.ndarray, labels: np.ndarray):
    valid = np.isfinite(depth)
    return (torch.from_numpy(np.where(valid, depth, 0.0)[None].astype(np.float32)),
            torch.from_numpy(valid[None].astype(np.float32)),
            torch.from_numpy(labels[None].astype(np.int64)))


def test_a_turned_image_is_what_the_rolled_camera_renders():
    plain_depth, plain_labels, camera = rendered(0.0)
    want_depth, want_labels, _ = rendered(15.0)
    intrinsics = torch.from_numpy(camera.normalised()[None])
    scores = {}
    for sign in (1, -1):
        depth, valid, labels, _ = roll_images(torch.tensor([sign * math.radians(15.0)]),
                                              intrinsics, *as_batch(plain_depth, plain_labels))
        seen = (labels[0] != IGNORE).numpy()
        got_box, want_box = labels[0].numpy()[seen] == 2, want_labels[seen] == 2
        scores[sign] = (got_box & want_box).sum() / (got_box | want_box).sum()  # box IoU
        if sign == 1:
            both = seen & (valid[0].numpy() > 0) & np.isfinite(want_depth)
            error = np.abs(depth[0].numpy()[both] - want_depth[both])
            assert both.mean() > 0.8                 # corners out of view, the rest measured
            assert np.median(error) < 0.0005         # same depths, only moved
            assert want_box.sum() > 300
    # Render's sense of roll, at nearest-pixel precision; the opposite turn is clearly off.
    assert scores[1] > 0.95 and scores[-1] < 0.8


def mixed_pixels(depth: torch.Tensor, valid: torch.Tensor) -> tuple[int, int]:
    """(pixels between the two sides, pixels) over row neighbours more than 5 cm apart."""
    full = valid > 0.99
    before, mid, after = depth[:, :, :-2], depth[:, :, 1:-1], depth[:, :, 2:]
    low, high = torch.minimum(before, after), torch.maximum(before, after)
    step = full[:, :, :-2] & full[:, :, 1:-1] & full[:, :, 2:] & (high - low > 0.05)
    margin = 0.1 * (high - low)
    between = step & (mid > low + margin) & (mid < high - margin)
    return int(between.sum()), int(step.sum())


def test_a_turn_keeps_depth_edges_as_sharp_as_rendered_and_blends_the_floor():
    plain_depth, plain_labels, camera = rendered(0.0)
    want_depth, want_labels, _ = rendered(15.0)
    depth, valid, labels = as_batch(plain_depth, plain_labels)
    edges = depth_edges(depth, valid, pixel_noise(depth, valid))[0].numpy()
    assert edges[plain_labels == 2].sum() > 20                 # the box's outline
    near_box = cv2.dilate((plain_labels == 2).astype(np.uint8), np.ones((3, 3))) > 0
    assert not edges[~near_box].any()                          # none on the slanted floor
    out_depth, out_valid, out_labels, _ = roll_images(
        torch.tensor([math.radians(15.0)]), torch.from_numpy(camera.normalised()[None]),
        depth, valid, labels)
    # Mixed pixels across the box's edges: as many as the rolled camera renders (a blend
    # everywhere made 113 of 171, the render 50 of 137).
    got_mixed, got_steps = mixed_pixels(out_depth, out_valid)
    want_mixed, want_steps = mixed_pixels(*as_batch(want_depth, want_labels)[:2])
    assert got_mixed / got_steps < want_mixed / want_steps + 0.05
    # The floor away from the box and from the frame's border (where not all four neighbours
    # are in view) stays blended: nearest pixels would be off by 3.5 mm (median), 13 mm
    # (95th percentile).
    box = cv2.dilate((want_labels == 2).astype(np.uint8), np.ones((9, 9))) > 0
    inside = cv2.erode((out_labels[0] != IGNORE).numpy().astype(np.uint8), np.ones((5, 5)))
    floor = (out_labels[0] == BACKGROUND).numpy() & (inside > 0) & ~box
    error = np.abs(out_depth[0].numpy() - want_depth)[floor & np.isfinite(want_depth)]
    assert floor.sum() > 5000 and error.max() < 0.0005


def test_on_a_noisy_image_the_box_outline_keeps_its_step_and_the_blend_draws_noise_again():
    plain_depth, plain_labels, camera = rendered(0.0)
    gen = torch.Generator().manual_seed(5)
    depth, valid, labels = as_batch(plain_depth, plain_labels)
    depth = depth + 0.0006 * depth**2 * torch.randn(depth.shape, generator=gen)
    edges = depth_edges(depth, valid, pixel_noise(depth, valid))[0].numpy()
    near_box = cv2.dilate((plain_labels == 2).astype(np.uint8), np.ones((3, 3))) > 0
    assert edges[plain_labels == 2].sum() > 20 and not edges[~near_box].any()
    angle, intrinsics = torch.tensor([math.radians(15.0)]), camera.normalised()[None]
    out_depth, _, out_labels, _ = roll_images(angle, torch.from_numpy(intrinsics), depth,
                                              valid, labels, gen=gen)
    # Where the turned box's outline is a step (not where its side meets the floor), each
    # depth is its nearest source pixel's but for the blend of a steep face (a blend
    # everywhere was off by up to 23 cm, 55 of 91 pixels by over 1 cm).
    box = (out_labels[0] == 2).numpy().astype(np.uint8)
    turned = out_depth[0].numpy()
    spread = cv2.dilate(turned, np.ones((3, 3))) - cv2.erode(turned, np.ones((3, 3)))
    rows, cols = np.nonzero((box > 0) & (cv2.erode(box, np.ones((3, 3))) == 0) & (spread > 0.05))
    centre, focal = principal_points(torch.from_numpy(intrinsics), 1, 120, 160)
    source = roll_sources(angle, centre.float(), focal.float(), 120, 160)[0].round().long()
    nearest = depth[0, source[rows, cols, 1], source[rows, cols, 0]].numpy()
    off = np.abs(turned[rows, cols] - nearest)
    assert len(rows) > 40 and off.max() < 0.05 and (off > 0.01).mean() < 0.1
    # Inside, the blend with its noise drawn again: few depths are one of the image's own
    # (28 of 322, along the crease between the box's faces, which bends the inverse depth).
    inner = cv2.erode(box, np.ones((5, 5))) > 0
    assert inner.sum() > 100 and np.isin(turned[inner], depth.numpy()).mean() < 0.15


def test_the_corners_that_come_into_view_have_no_depth_and_no_label():
    depth = torch.full((2, 60, 80), 2.0)
    labels = torch.full((2, 60, 80), BACKGROUND)
    labels[:, 20:40, 30:50] = 3
    angles = torch.tensor([0.0, math.radians(20.0)])
    out_depth, out_valid, out_labels, nearest = roll_images(
        angles, None, depth, torch.ones_like(depth), labels, depth.clone())
    assert torch.equal(out_depth[0], depth[0]) and torch.equal(out_labels[0], labels[0])
    gone = out_labels[1] == IGNORE
    assert gone[0, 0] and gone[-1, -1] and not gone[30, 40]     # corners, not the centre
    assert (out_valid[1][gone] == 0).all() and (out_depth[1][gone] == 0).all()
    assert torch.allclose(out_depth[1][~gone], torch.tensor(2.0))  # no blend with the void
    assert torch.equal(nearest, out_depth)                      # moved like the depths
    kept = out_labels[1][~gone]
    assert set(kept.unique().tolist()) == {BACKGROUND, 3}        # labels stay labels
    assert abs(int((kept == 3).sum()) - 400) < 40                # the object keeps its area


def test_pixel_noise_reads_the_noise_of_a_sloped_floor_and_none_on_a_clean_one():
    gen = torch.Generator().manual_seed(11)
    z = torch.linspace(1.5, 3.0, 120)[None, :, None].expand(4, 120, 160).contiguous()
    sd = 0.0006                                                             # per z^2
    noisy = z + sd * z**2 * torch.randn(z.shape, generator=gen)
    valid = torch.ones_like(z)
    assert torch.allclose(pixel_noise(noisy, valid), torch.tensor(sd), rtol=0.05)
    assert (pixel_noise(z, valid) < 0.05 * sd).all()
    assert (pixel_noise(noisy, torch.zeros_like(z)) == 0).all()             # nothing to read


def test_the_turn_puts_back_the_noise_its_interpolation_averages_away():
    gen = torch.Generator().manual_seed(11)
    z, sd = 2.0, 0.0006
    noisy = z + sd * z**2 * torch.randn((16, 120, 160), generator=gen)     # a flat floor
    valid, labels = torch.ones_like(noisy), torch.zeros(noisy.shape, dtype=torch.long)
    angles = (torch.rand(16, generator=gen) * 2 - 1) * math.radians(15.0)
    blended = roll_images(angles, None, noisy, valid, labels)[0]
    restored = roll_images(angles, None, noisy, valid, labels, gen=gen)[0]
    centre = (slice(None), slice(30, 90), slice(40, 120))                   # off the corners

    def relative_sd(depth: torch.Tensor) -> float:
        return float((depth[centre] - z).std() / (sd * z**2))

    # The blend alone leaves two thirds of each pixel's noise; the turn with ``gen`` all of
    # it, without moving the floor.
    assert relative_sd(noisy) == pytest.approx(1.0, abs=0.02)
    assert relative_sd(blended) < 0.75
    assert relative_sd(restored) == pytest.approx(1.0, abs=0.03)
    assert abs(float(restored[centre].mean()) - z) < 1e-4


def test_augmentation_roll_turns_the_images_first_and_zero_leaves_the_stream_as_it_was():
    from training.augment import augment

    depth = torch.rand(8, 60, 80) + 1.0
    labels = torch.randint(0, 4, (8, 60, 80))
    args = (torch.ones_like(depth), labels)
    plain = augment(depth.clone(), *args, torch.Generator().manual_seed(3), holes=0.5)
    off = augment(depth.clone(), *args, torch.Generator().manual_seed(3), holes=0.5,
                  roll_deg=0.0)
    for a, b in zip(plain[:3], off[:3]):
        assert torch.equal(a, b)
    # With a roll, the angles are drawn first and the other draws act on the turned images.
    gen = torch.Generator().manual_seed(3)
    angles = (torch.rand(8, generator=gen) * 2 - 1) * math.radians(15.0)
    assert (angles.abs() <= math.radians(15.0)).all() and angles.abs().max() > 0.05
    turned = roll_images(angles, None, depth.clone(), *args, gen=gen)
    want = augment(*turned[:3], gen, holes=0.5)
    rolled = augment(depth.clone(), *args, torch.Generator().manual_seed(3), holes=0.5,
                     roll_deg=15.0)
    for a, b in zip(rolled[:3], want[:3]):
        assert torch.equal(a, b)


def test_roll_augmentation_is_refused_out_of_range_or_without_augmentation():
    with pytest.raises(ConfigError, match="aug_roll_deg"):
        TrainConfig(aug_roll_deg=60.0).validate()
    with pytest.raises(ConfigError, match="aug_roll_deg = 10.0 needs augment"):
        TrainConfig(aug_roll_deg=10.0, augment=False).validate()
    assert TrainConfig(aug_roll_deg=12.0).validate().aug_roll_deg == 12.0


def test_the_training_loop_measuring_its_images_once_turns_them_the_same(monkeypatch):
    """``augment.measure_for_roll`` caches each image's noise and edges; the turned batch is
    bitwise what measuring them in the batch gives (the same random draws included), and
    with the cache the batch measures nothing."""
    import training.roll
    from training.augment import (
        ROLL_EDGES,
        Augmentations,
        cached_edges,
        gather_batch,
        measure_for_roll,
    )

    depth, labels, camera = rendered(0.0)
    rng = np.random.default_rng(0)
    noisy = np.where(np.isfinite(depth), depth, 0.0) * (1 + 0.004 * rng.standard_normal(
        (6, *depth.shape)))
    arrays = {"depth": noisy.astype(np.float16),                       # as the cache keeps it
              "valid": np.broadcast_to(np.isfinite(depth), noisy.shape).astype(np.float16),
              "labels": np.broadcast_to(labels, noisy.shape).astype(np.uint8),
              "nearest": (0.97 * noisy).astype(np.float16),
              "intrinsics": np.repeat(camera.normalised()[None], 6, 0).astype(np.float32)}
    idx = np.array([1, 3, 4])
    turned = gather_batch(arrays, idx, torch.Generator().manual_seed(7),
                          Augmentations(roll_deg=15.0))
    measure_for_roll(arrays, chunk=4)                # chunks that split the batch's images
    assert arrays[ROLL_EDGES].shape == (6, 120, 20)   # 8 pixels a byte
    _, edges = training.roll.measure_images(torch.from_numpy(noisy[idx].astype(np.float16)
                                                             .astype(np.float32)),
                                            torch.from_numpy(arrays["valid"][idx]
                                                             .astype(np.float32)))
    assert edges.any() and torch.equal(cached_edges(arrays, idx), edges)

    def measured_again(*args):
        raise AssertionError("the batch measured its images again")

    monkeypatch.setattr(training.roll, "measure_images", measured_again)
    cached = gather_batch(arrays, idx, torch.Generator().manual_seed(7),
                          Augmentations(roll_deg=15.0))
    for got, want in zip(cached, turned):
        assert (got is None and want is None) or torch.equal(got, want)


def test_cached_edges_come_back_as_measured_for_any_image_width():
    """The packed edges unpack to the same bool images, also when the width is not a whole
    number of bytes (13 pixels: 2 bytes a row, 3 bits of padding)."""
    from training.augment import ROLL_EDGES, cached_edges

    edges = np.random.default_rng(3).random((4, 5, 13)) < 0.3
    arrays = {"depth": np.zeros(edges.shape, np.float16),
              ROLL_EDGES: np.packbits(edges, axis=-1)}
    assert arrays[ROLL_EDGES].shape == (4, 5, 2)
    idx = np.array([0, 2, 3])
    got = cached_edges(arrays, idx)
    assert got.dtype == torch.bool and torch.equal(got, torch.from_numpy(edges[idx]))


def test_the_near_side_depth_turns_with_the_depth_at_edges_and_between_them():
    """Every plane keeps its role in the stacked turn: a near-side depth that is 0.9 x the
    depth comes out 0.9 x the turned depth, on the blended pixels and on those taken from
    the nearest pixel next to the box's edges alike."""
    depth, labels, camera = rendered(0.0)
    depth_t, valid_t, labels_t = as_batch(depth, labels)
    out_depth, out_valid, _, out_near = roll_images(
        torch.tensor([math.radians(12.0)]), torch.from_numpy(camera.normalised()[None]),
        depth_t, valid_t, labels_t, 0.9 * depth_t)
    seen = out_valid > 0
    edges = depth_edges(depth_t, valid_t, pixel_noise(depth_t, valid_t))
    assert edges.any() and seen.sum() > 10_000
    assert torch.allclose(out_near[seen], 0.9 * out_depth[seen], rtol=1e-5)
    assert (out_near[~seen] == 0).all()
