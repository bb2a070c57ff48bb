"""The local-relief input channel (relief.local_relief): a small object reads its own height
above whatever surface it lies on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from task_outcome_ros.floor import heights_beneath_support
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    check_normalisation,
    input_channels,
    preprocess,
    preprocess_batch,
)
from task_outcome_ros.relief import (
    local_noise_sd,
    local_relief,
    majority_valid,
    square_median_torch,
    square_median_u8,
    square_sum,
    valid_mean,
)

pytestmark = pytest.mark.unit

RELIEF_NORMALISATION = {**DEFAULT_NORMALISATION, "relief_window_px": 9}


def _table_and_floor() -> tuple[torch.Tensor, torch.Tensor]:
    """A table top (height 0, left half) beside a room floor 0.75 m below (right half), a 3 cm
    box on each, and an invalid strip along the bottom of the table."""
    height = torch.zeros(1, 40, 60)
    height[:, :, 30:] = -0.75
    height[:, 10:13, 40:43] += 0.03   # on the floor
    height[:, 10:13, 10:13] += 0.03   # on the table
    valid = torch.ones_like(height, dtype=torch.bool)
    valid[:, 34:, :30] = False
    return height, valid


def test_a_small_box_reads_its_height_on_the_table_and_on_the_floor_below_it() -> None:
    height, valid = _table_and_floor()
    relief = local_relief(height, valid, 9)
    assert relief[0, 11, 41].item() == pytest.approx(0.03, abs=1e-6)
    assert relief[0, 11, 11].item() == pytest.approx(0.03, abs=1e-6)
    # The table's edge, 0.75 m above the floor beside it, is a surface wider than the window:
    # it reads 0 up to its last pixel, and so does every surface around the boxes.
    boxes = torch.zeros_like(valid)
    boxes[:, 10:13, 40:43] = boxes[:, 10:13, 10:13] = True
    assert relief[~boxes].abs().max().item() == 0.0
    # Invalid pixels read 0, and do not pull the surface around them down.
    assert torch.all(relief[~valid] == 0)


def test_a_window_without_valid_pixels_and_an_empty_image_read_zero() -> None:
    height = torch.randn(2, 20, 20)
    valid = torch.zeros_like(height, dtype=torch.bool)
    valid[0, :2, :2] = True
    relief = local_relief(height, valid, 5)
    assert torch.isfinite(relief).all() and torch.all(relief[1] == 0)
    assert torch.all(relief[0, 10:, 10:] == 0)


def _relief_by_max_pool(height: torch.Tensor, valid: torch.Tensor, window: int,
                        smoothing: int) -> torch.Tensor:
    """The relief written another way, for the test below: torch's max-pool over the heights
    padded with +-inf beyond the frame, on the torch twin of the valid mean."""
    pad = window // 2

    def square_max(x: torch.Tensor, beyond: float) -> torch.Tensor:
        padded = torch.nn.functional.pad(x[:, None], (pad, pad, pad, pad), value=beyond)
        return torch.nn.functional.max_pool2d(padded, window, stride=1)[:, 0]

    if smoothing > 1:
        height = valid_mean(height, valid, smoothing)
    eroded = -square_max(torch.where(valid, -height, -float("inf")), float("inf"))
    eroded = torch.where(torch.isinf(eroded), -float("inf"), eroded)
    relief = height - square_max(eroded, -float("inf"))
    return torch.where(valid & torch.isfinite(relief), relief.clamp_min(0.0), 0.0)


@pytest.mark.parametrize("window, smoothing", [(3, 1), (9, 3), (15, 3), (15, 5)])
def test_the_relief_equals_the_same_opening_written_with_torch_pooling(window, smoothing):
    """The numpy / OpenCV relief against max-pools padded with +-inf: the same values to the
    last bit, at the frame's border and around invalid pixels too."""
    gen = torch.Generator().manual_seed(window * 10 + smoothing)
    height = torch.randn(3, 25, 31, generator=gen) * 0.05
    valid = torch.rand(3, 25, 31, generator=gen) > 0.2
    valid[1, :, :4] = False    # an invalid band at the border
    valid[2] = False           # nothing valid: no relief anywhere
    expected = _relief_by_max_pool(height, valid, window, smoothing)
    relief = local_relief(height, valid, window, smoothing)
    assert relief.dtype == torch.float32 and relief.shape == height.shape
    assert torch.equal(relief, expected)
    assert relief[0].gt(0).any() and torch.all(relief[2] == 0)


def test_an_object_cut_by_the_frame_reads_its_height_and_a_surface_at_the_edge_reads_zero():
    height = torch.full((1, 30, 40), -0.75)
    height[:, :, 30:] = 0.0                    # a table top reaching the right edge
    # A box cut by the left edge, 6 x 20 pixels in view: it fills every in-frame window of
    # its border pixels, which would make it a surface if the frame's edge were support.
    height[:, 5:25, :6] += 0.03
    relief = local_relief(height, torch.ones_like(height, dtype=torch.bool), 9)
    assert torch.allclose(relief[:, 5:25, :6], torch.tensor(0.03))
    assert relief[:, :, 30:].abs().max().item() == 0.0


def test_the_relief_channel_is_a_fourth_channel_and_agrees_across_preprocess_paths() -> None:
    assert input_channels(RELIEF_NORMALISATION) == 4
    # Seen straight down from 2 m: a floor, and a 10 cm box of 5 x 5 working pixels.
    depth = np.full((480, 640), 2.0, np.float32)
    depth[200:220, 300:320] = 1.9
    x = preprocess(depth, (160, 120), RELIEF_NORMALISATION)
    assert x.shape == (4, 120, 160)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    assert x[3, 51, 76] * scale == pytest.approx(0.1, abs=0.01)
    assert np.abs(x[3, :40]).max() == 0.0           # the floor around it
    batch = preprocess_batch(torch.from_numpy(depth), (160, 120), RELIEF_NORMALISATION)
    np.testing.assert_allclose(batch[0].numpy(), x, atol=1e-5)


@pytest.mark.parametrize("window", [4, 1, 65, 9.0, True, "9"])
def test_a_bad_relief_window_is_refused(window) -> None:
    with pytest.raises(ValueError, match="relief_window_px"):
        check_normalisation({**DEFAULT_NORMALISATION, "relief_window_px": window})


def test_relief_needs_the_height_channel() -> None:
    two = {k: v for k, v in DEFAULT_NORMALISATION.items()
           if k not in ("height_scale_m", "focal_over_width", "floor_fit")}
    with pytest.raises(ValueError, match="height channel"):
        check_normalisation({**two, "relief_window_px": 9})


def test_an_empty_batch_gives_an_empty_relief() -> None:
    empty = torch.zeros(0, 12, 16)
    assert local_relief(empty, empty > 0, 5).shape == (0, 12, 16)


def test_smoothing_keeps_a_box_and_narrows_the_relief_a_noisy_flat_surface_reads() -> None:
    """The erosion is a minimum over the window, so on a noisy floor it sits in the noise's
    low tail and the floor reads relief; the mean over 3 x 3 valid pixels narrows that tail
    (for independent noise a third of its spread), while a 5 x 5 box keeps its height at
    its centre."""
    generator = torch.Generator().manual_seed(0)
    height = 0.01 * torch.randn(1, 60, 80, generator=generator)   # 1 cm of noise on a floor
    valid = torch.ones_like(height, dtype=torch.bool)
    raw = local_relief(height, valid, 15)
    smoothed = local_relief(height, valid, 15, smoothing=3)
    assert raw.mean().item() > 0.01           # the floor reads more than its noise's spread
    assert smoothed.mean().item() < 0.45 * raw.mean().item()
    boxed = height.clone()
    boxed[:, 20:25, 30:35] += 0.05
    relief = local_relief(boxed, valid, 15, smoothing=3)
    assert relief[0, 22, 32].item() == pytest.approx(0.05, abs=0.012)


def test_the_valid_mean_ignores_invalid_pixels_and_the_frame_outside() -> None:
    x = torch.arange(20.0).reshape(1, 4, 5)
    valid = torch.ones_like(x, dtype=torch.bool)
    valid[0, 1, 1] = False
    x_invalid = x.clone()
    x_invalid[0, 1, 1] = 1e6                  # an invalid pixel's value never leaks in
    mean = valid_mean(x_invalid, valid, 3)
    assert mean[0, 0, 0].item() == pytest.approx((0 + 1 + 5) / 3)   # corner: 3 valid in frame
    assert mean[0, 1, 1].item() == 1e6                           # invalid keeps its value
    assert mean[0, 2, 2].item() == pytest.approx((x[0, 1:4, 1:4].sum() - 6) / 8)
    plain = torch.nn.functional.avg_pool2d(x[:, None], 3, 1, 1, count_include_pad=True)[:, 0]
    assert torch.allclose(square_sum(x, 3), plain * 9)


def test_the_relief_smoothing_is_stored_checked_and_the_same_on_both_paths() -> None:
    smooth = {**RELIEF_NORMALISATION, "relief_smoothing_px": 3}
    assert input_channels(smooth) == 4
    depth = np.full((480, 640), 2.0, np.float32)
    depth[200:220, 300:320] = 1.9
    x = preprocess(depth, (160, 120), smooth)
    batch = preprocess_batch(torch.from_numpy(depth), (160, 120), smooth)
    np.testing.assert_allclose(batch[0].numpy(), x, atol=1e-5)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    assert x[3, 52, 77] * scale == pytest.approx(0.1, abs=0.01)   # the box's centre
    for bad in (2, 1, 17, 3.0, True):
        with pytest.raises(ValueError, match="relief_smoothing_px"):
            check_normalisation({**smooth, "relief_smoothing_px": bad})
    with pytest.raises(ValueError, match="needs 'relief_window_px'"):
        check_normalisation({**DEFAULT_NORMALISATION, "relief_smoothing_px": 3})


def test_a_wider_base_keeps_a_box_and_reads_less_relief_on_a_noisy_floor() -> None:
    """``relief_base_px``: the surface found on a wider mean than each pixel's own height."""
    gen = torch.Generator().manual_seed(0)
    floor = 0.01 * torch.randn(1, 60, 80, generator=gen)   # a flat floor, 1 cm noise
    box = floor.clone()
    box[:, 20:24, 30:34] += 0.05
    valid = torch.ones_like(floor, dtype=torch.bool)
    same = local_relief(floor, valid, 15, 3)
    wider = local_relief(floor, valid, 15, 3, 7)
    assert wider.mean().item() < 0.7 * same.mean().item()   # the erosion's tail narrowed
    assert local_relief(floor, valid, 15, 3, None).equal(same)
    on_box = local_relief(box, valid, 15, 3, 7)[0, 21:23, 31:33]
    assert on_box.min().item() > 0.03                          # the box still stands out
    smooth = {**RELIEF_NORMALISATION, "relief_smoothing_px": 3, "relief_base_px": 7}
    assert check_normalisation(smooth)["relief_base_px"] == 7
    for bad in (2, 17, 7.0):
        with pytest.raises(ValueError, match="relief_base_px"):
            check_normalisation({**smooth, "relief_base_px": bad})
    with pytest.raises(ValueError, match="needs 'relief_window_px'"):
        check_normalisation({**DEFAULT_NORMALISATION, "relief_base_px": 7})


def test_lowering_by_the_measured_noise_makes_a_noisy_floor_read_as_flat_as_a_quiet_one():
    """``noise_sds``: the relief minus that many measured deviations of the smoothed heights'
    noise. A floor's relief is the erosion's low tail, so it grows with the noise; lowered by
    five measured deviations, a floor at 1 cm and at 3 cm of noise both read (almost) none,
    while a 5 cm box keeps most of its height under 1 cm of noise."""
    gen = torch.Generator().manual_seed(0)
    unit = torch.randn(1, 60, 80, generator=gen)
    valid = torch.ones_like(unit, dtype=torch.bool)
    quiet, noisy = 0.01 * unit, 0.03 * unit
    assert local_relief(noisy, valid, 15, 3).gt(0.02).float().mean().item() > 0.3
    for floor in (quiet, noisy):
        lowered = local_relief(floor, valid, 15, 3, noise_sds=5.0)
        assert lowered.gt(0.01).float().mean().item() < 0.01
    # The measured deviation is that of the 3 x 3 mean: a third of the pixels' own.
    sd = local_noise_sd(noisy, valid_mean(noisy, valid, 3), valid, 15, 3)
    assert sd.median().item() == pytest.approx(0.01, rel=0.15)
    boxed = quiet.clone()
    boxed[:, 20:25, 30:35] += 0.05
    on_box = local_relief(boxed, valid, 15, 3, noise_sds=5.0)[0, 22, 32].item()
    assert 0.025 < on_box <= local_relief(boxed, valid, 15, 3)[0, 22, 32].item()


def test_where_a_floor_fades_out_of_range_its_isolated_pixels_read_no_lowered_relief():
    """Past a far floor's range only isolated pixels stay valid: their 3 x 3 mean is
    themselves, with no residual for the median to measure, so without the majority rule each
    reads its raw noise as relief."""
    gen = torch.Generator().manual_seed(1)
    height = 0.05 * torch.randn(1, 60, 80, generator=gen)     # a noisy far floor
    valid = torch.ones_like(height, dtype=torch.bool)
    valid[:, :20] = torch.rand(1, 20, 80, generator=gen) < 0.15  # fading out: 15 % valid
    lowered = local_relief(height, valid, 15, 3, noise_sds=5.0)
    assert lowered[:, :18].abs().max().item() == 0.0
    supported = majority_valid(valid, 3)
    assert supported[:, 25:].all() and not supported[:, :18].any()
    assert local_relief(height, valid, 15, 3)[:, :18].gt(0.02).any()   # what it prevents


def test_majority_valid_counts_the_square_within_the_frame() -> None:
    valid = torch.ones(1, 6, 6, dtype=torch.bool)
    valid[:, :, 3:] = False
    expected = torch.zeros_like(valid)
    expected[:, :, :3] = True                  # column 2: 6 of 9 valid; corners: 4 of 4
    assert torch.equal(majority_valid(valid, 3), expected)


def test_opencv_and_torch_square_median_agree_including_at_the_border() -> None:
    x = torch.randint(0, 256, (2, 25, 31), dtype=torch.uint8,
                      generator=torch.Generator().manual_seed(2))
    x[0, :, :5] = 255
    for window in (3, 9, 15):
        assert torch.equal(square_median_u8(x, window), square_median_torch(x, window))
    corner = x[1, :2, :2].float()    # window 3 at (0, 0): the replicated border counts
    nine = torch.stack([corner[0, 0]] * 4 + [corner[0, 1]] * 2 + [corner[1, 0]] * 2
                       + [corner[1, 1]])
    assert square_median_torch(x, 3)[1, 0, 0].item() == nine.median().item()


def test_the_noise_measure_ignores_invalid_pixels_and_follows_each_means_own_count() -> None:
    """A floor 40 % of whose pixels are invalid in stripes measures the noise of its valid
    ones (invalid pixels read as zero residuals would pull the median down by half), and a
    pixel whose mean has 4 valid pixels instead of 9 gets 3/2 the deviation."""
    gen = torch.Generator().manual_seed(3)
    noisy = 0.03 * torch.randn(1, 60, 80, generator=gen)
    full = torch.ones_like(noisy, dtype=torch.bool)
    striped = full.clone()
    striped[:, :, 0::5] = striped[:, :, 1::5] = False
    whole = local_noise_sd(noisy, valid_mean(noisy, full, 3), full, 15, 3)
    holed = local_noise_sd(noisy, valid_mean(noisy, striped, 3), striped, 15, 3)
    assert whole[:, 20:40, 20:60].median().item() == pytest.approx(0.01, rel=0.15)
    stripes_sd = holed[striped][holed[striped] > 0]      # pixels with 6 of 9 valid: 0.03/√6
    assert stripes_sd.median().item() == pytest.approx(0.03 / 6 ** 0.5, rel=0.2)
    sparse = full.clone()
    sparse[:, 29, 39:42] = sparse[:, 30:32, 39] = False    # (30, 40): 4 of its 9 valid
    sd = local_noise_sd(noisy, valid_mean(noisy, sparse, 3), sparse, 15, 3)
    assert (sd[0, 30, 40] / sd[0, 30, 20]).item() == pytest.approx(1.5, rel=0.2)


def test_the_relief_noise_sds_are_stored_checked_and_the_same_on_both_paths() -> None:
    lowered = {**RELIEF_NORMALISATION, "relief_smoothing_px": 3, "relief_noise_sds": 5}
    assert check_normalisation(lowered)["relief_noise_sds"] == 5.0
    depth = np.full((480, 640), 2.0, np.float32)
    depth[200:220, 300:320] = 1.9
    depth += np.random.default_rng(0).normal(0, 0.01, depth.shape).astype(np.float32)
    x = preprocess(depth, (160, 120), lowered)
    batch = preprocess_batch(torch.from_numpy(depth), (160, 120), lowered)
    np.testing.assert_allclose(batch[0].numpy(), x, atol=1e-5)
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    assert x[3, 52, 77] * scale == pytest.approx(0.1, abs=0.02)    # the box's centre
    assert np.mean(x[3, :40] * scale > 0.01) < 0.01               # the floor around it
    for bad in (0, -1.0, 10.5, True, "5"):
        with pytest.raises(ValueError, match="relief_noise_sds"):
            check_normalisation({**lowered, "relief_noise_sds": bad})
    with pytest.raises(ValueError, match="needs 'relief_smoothing_px'"):
        check_normalisation({**RELIEF_NORMALISATION, "relief_noise_sds": 5})


BENEATH_NORMALISATION = {**RELIEF_NORMALISATION, "support_above_floor": [0.7, 0.8],
                         "relief_beneath_support": True}


def _box_on_the_floor_beside_the_table() -> tuple[torch.Tensor, torch.Tensor]:
    """Heights from a table top (left, 0) beside the room floor 0.75 m below (right), a long
    16 cm box on the floor lying along the table's edge in the image (longer than the relief's
    window), and the table's edge as a column of pixels mixing the two (-0.3 m)."""
    height = torch.zeros(1, 40, 60)
    height[:, :, 31:] = -0.75
    height[:, :, 30] = -0.3                # the edge: table side or a mixed pixel
    height[:, 5:35, 31:35] = -0.75 + 0.16
    return height, torch.ones_like(height, dtype=torch.bool)


def test_beneath_the_table_heights_are_measured_from_the_room_floor() -> None:
    height, valid = _box_on_the_floor_beside_the_table()
    beneath = heights_beneath_support(height, valid, (0.7, 0.8))
    assert beneath[0, 16, 32].item() == pytest.approx(0.16, abs=1e-6)   # the box
    assert beneath[0, 5, 50].item() == pytest.approx(0.0, abs=1e-6)      # the room floor
    assert torch.all(beneath[:, :, :30] == 0)                            # the table top
    assert torch.all(beneath[:, :, 30] == 0)     # its edge: no ridge
    # No room floor in view (a tote in the middle of a big table): heights as they are.
    on_table = height.clone()
    on_table[:, :, 30:] = 0.05
    assert torch.equal(heights_beneath_support(on_table, valid, (0.7, 0.8)), on_table)
    # Invalid pixels are not measured, and do not count as floor.
    invalid_floor = valid.clone()
    invalid_floor[:, :, 31:] = False
    assert torch.equal(heights_beneath_support(height, invalid_floor, (0.7, 0.8)), height)


def test_a_box_on_the_floor_beside_the_table_reads_relief_only_beneath_the_support() -> None:
    height, valid = _box_on_the_floor_beside_the_table()
    # From the table top, the box is part of a surface the opening fits in (a window over the
    # box, the edge and the table holds no lower point): no relief ...
    assert local_relief(height, valid, 9)[0, 16, 32].item() == 0.0
    # ... from the floor beneath it, it reads its own height, and the floor and table none.
    relief = local_relief(heights_beneath_support(height, valid, (0.7, 0.8)), valid, 9)
    assert relief[0, 16, 32].item() == pytest.approx(0.16, abs=1e-6)
    box = torch.zeros_like(valid)
    box[:, 5:35, 31:35] = True
    assert relief[~box].abs().max().item() == 0.0


def test_each_image_of_a_batch_is_measured_from_its_own_room_floor() -> None:
    height, valid = _box_on_the_floor_beside_the_table()
    deeper = height.clone()
    deeper[:, :, 31:] -= 0.05                      # a higher table: its floor 0.80 m below
    on_table = torch.zeros_like(height)            # no room floor in view
    on_table[:, 10:13, 40:43] = 0.03
    batch = torch.cat([height, deeper, on_table])
    beneath = heights_beneath_support(batch, valid.expand(3, -1, -1), (0.7, 0.8))
    assert beneath[0, 16, 32].item() == pytest.approx(0.16, abs=1e-6)
    assert beneath[1, 16, 32].item() == pytest.approx(0.16, abs=1e-6)
    assert beneath[1, 5, 50].item() == pytest.approx(0.0, abs=1e-6)
    assert torch.equal(beneath[2], on_table[0])


def _camera_over_table_and_floor() -> np.ndarray:
    """A camera 1 m above a table top looking straight down, the left third of the view the
    room floor 0.75 m lower, with a long 16 cm box on it along the table's edge, narrower than
    the relief's window (5 of its 9 working pixels)."""
    depth = np.full((480, 640), 1.0, np.float32)
    depth[:, 430:] = 1.75
    depth[40:440, 432:452] = 1.75 - 0.16
    return depth


def test_the_relief_beneath_the_support_is_stored_checked_and_the_same_on_both_paths():
    assert input_channels(BENEATH_NORMALISATION) == 4
    depth = _camera_over_table_and_floor()
    x = preprocess(depth, (160, 120), BENEATH_NORMALISATION)
    batch = preprocess_batch(torch.from_numpy(depth), (160, 120), BENEATH_NORMALISATION)
    np.testing.assert_allclose(batch[0].numpy(), x, atol=1e-5)
    # The box along the table's edge reads its height only measured from the floor beneath.
    scale = DEFAULT_NORMALISATION["height_scale_m"]
    assert x[3, 60, 110] * scale == pytest.approx(0.16, abs=0.02)
    table_only = {k: v for k, v in BENEATH_NORMALISATION.items()
                  if k != "relief_beneath_support"}
    assert preprocess(depth, (160, 120), table_only)[3, 60, 110] * scale < 0.02
    assert check_normalisation(BENEATH_NORMALISATION)["relief_beneath_support"] is True
    with pytest.raises(ValueError, match="relief_beneath_support"):
        check_normalisation({**BENEATH_NORMALISATION, "support_above_floor": [0.1, 0.8]})
    for missing in ("support_above_floor", "relief_window_px"):
        with pytest.raises(ValueError, match="relief_beneath_support"):
            check_normalisation({k: v for k, v in BENEATH_NORMALISATION.items()
                                 if k != missing})
    with pytest.raises(ValueError, match="must be true"):
        check_normalisation({**BENEATH_NORMALISATION, "relief_beneath_support": 1})
