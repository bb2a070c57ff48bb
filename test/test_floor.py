"""Height above the floor (floor.py), the network's third channel, on analytic scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from task_outcome_ros.camera import Intrinsics
from task_outcome_ros.floor import (
    FLOOR_FIT,
    FOCAL_OVER_WIDTH,
    LEGACY_FLOOR_FIT,
    FloorTracker,
    _plane_scores,
    _refine,
    backproject,
    fit_floor,
    height_above_floor,
)
from task_outcome_ros.model import (
    DEFAULT_NORMALISATION,
    INTRINSICS_FROM_CAMERA_INFO,
    check_normalisation,
    input_channels,
    preprocess,
)

pytestmark = pytest.mark.unit

# The normalisation of checkpoints from before the height channel: depth and validity only.
TWO_CHANNEL_NORMALISATION = {k: v for k, v in DEFAULT_NORMALISATION.items()
                             if k not in ("height_scale_m", "focal_over_width", "floor_fit")}


def _tilted_scene(h: int = 120, w: int = 160, camera_height: float = 1.5,
                  elevation_deg: float = 50.0, box_height: float = 0.3,
                  camera: Intrinsics | None = None) -> np.ndarray:
    """Depth of a floor seen from ``camera_height`` m, pitched down ``elevation_deg``, with a
    flat-topped box (top at ``box_height`` m) filling a patch in the middle of the image.
    ``camera``: the pinhole camera that sees it (None: the nominal one, centred)."""
    a = math.radians(elevation_deg)
    # Floor normal (towards the camera) in the optical frame (y down, z forward).
    normal = np.array([0.0, -math.cos(a), -math.sin(a)])
    camera = camera or Intrinsics(w, h, FOCAL_OVER_WIDTH * w, FOCAL_OVER_WIDTH * w,
                                  (w - 1) / 2, (h - 1) / 2)
    u = (np.arange(w) - camera.cx) / camera.fx
    v = (np.arange(h) - camera.cy) / camera.fy
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1)
    along = rays @ normal                       # < 0: the ray goes down towards the floor
    plane_height = np.zeros((h, w))
    plane_height[h // 3: h // 2, w // 3: w // 2] = box_height
    return ((plane_height - camera_height) / along).astype(np.float32)


def test_floor_and_box_heights_are_recovered() -> None:
    depth = torch.from_numpy(_tilted_scene())[None]
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[0, :5, :7] = False                    # some holes
    height = height_above_floor(depth, valid)[0].numpy()
    box = np.zeros(height.shape, bool)
    box[40:60, 53:80] = True
    assert abs(np.median(height[box]) - 0.3) < 0.005
    assert np.abs(height[~box & valid[0].numpy()]).max() < 0.005
    assert np.all(height[~valid[0].numpy()] == 0)


def test_heights_are_deterministic_and_batch_independent() -> None:
    a = torch.from_numpy(_tilted_scene(elevation_deg=45))
    b = torch.from_numpy(_tilted_scene(elevation_deg=62, box_height=0.1))
    both = torch.stack([a, b])
    valid = torch.ones_like(both, dtype=torch.bool)
    together = height_above_floor(both, valid)
    alone = height_above_floor(b[None], valid[1:])
    torch.testing.assert_close(together[1:], alone)
    torch.testing.assert_close(height_above_floor(both, valid), together)


@pytest.mark.parametrize("version", [1, 2, 3])
def test_hypothesis_scores_are_the_exact_vote_counts(version) -> None:
    """numpy's counts on the CPU against the votes written out in torch: +1 within the band,
    -1 beneath it (version 1: within only), NaN (a point not scored) never counted; points
    right on the band's edges and integer ties included."""
    band = 0.008
    gen = torch.Generator().manual_seed(version)
    signed = torch.randn(3, 128, 1200, generator=gen) * 0.02
    signed[:, :, :40] = torch.tensor([-band, band, 0.0, -2 * band])[torch.randint(
        0, 4, (3, 128, 40), generator=gen)]
    signed[:, :, -100:] = float("nan")
    if version == 1:
        expected = (signed.abs() < band).sum(-1)
    else:
        expected = torch.where(signed < -band, -1, (signed < band).long()).sum(-1)
    scores = _plane_scores(signed, band, version)
    assert torch.equal(scores.long(), expected)
    assert scores.shape == (3, 128)


def test_the_refit_is_the_least_squares_plane_of_the_inliers() -> None:
    """A plane with 2 mm noise and outliers far off it: the refit's normal and offset are the
    inliers' principal axis in float64, kept on the incoming normal's side; an image with
    under three inliers keeps its plane."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (2000, 2))
    normal_true = np.array([0.1, -0.8, -0.5]) / np.linalg.norm([0.1, -0.8, -0.5])
    # points on n . p = -1.5 (a floor 1.5 m from the camera), noise along the normal
    basis = np.linalg.svd(normal_true[None])[2][1:]
    on_plane = -1.5 * normal_true + xy @ basis
    points = on_plane + rng.normal(0, 0.002, (2000, 1)) * normal_true
    points[:100] += 0.5 * normal_true                     # outliers 0.5 m off the plane
    flat = torch.from_numpy(points.astype(np.float32))[None]
    valid = torch.ones(1, 2000, dtype=torch.bool)
    start = torch.from_numpy((normal_true + [0.004, 0, 0]).astype(np.float32))[None]
    start = start / start.norm()
    normal, offset = _refine(flat, valid, start, torch.tensor([-1.5]), 0.008)
    # the inliers of the incoming plane, chosen as the refit chooses them (float32)
    near = np.abs(flat[0].numpy() @ start[0].numpy() - np.float32(-1.5)) < 0.008
    assert 1500 < near.sum() < 1900 and not near[:100].any()
    inliers = points[near]
    centred = inliers - inliers.mean(0)
    axis = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    axis = axis if axis @ normal_true > 0 else -axis
    np.testing.assert_allclose(normal[0].numpy(), axis, atol=1e-6)
    assert offset[0].item() == pytest.approx(float(axis @ inliers.mean(0)), abs=1e-6)
    assert float(normal[0].numpy() @ normal_true) > 0.99999   # the plane it was drawn from
    few = torch.zeros(1, 2000, dtype=torch.bool)
    few[0, 100:102] = True                                # two inliers: the plane is kept
    kept = _refine(flat, few, start, torch.tensor([-1.5]), 0.008)
    assert torch.equal(kept[0], start) and kept[1].item() == -1.5


def test_a_batch_fits_each_image_as_it_fits_alone() -> None:
    """The numpy steps run image by image inside a batch: the same planes as one at a time."""
    scenes = [_tilted_scene(elevation_deg=e, box_height=b) for e, b in ((45, 0.3), (62, 0.1),
                                                                         (55, 0.2))]
    depth = torch.from_numpy(np.stack(scenes))
    points = backproject(depth)
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[1, :30] = False
    normal, offset = fit_floor(points, valid)
    for i in range(3):
        alone = fit_floor(points[i:i + 1], valid[i:i + 1])
        assert torch.equal(normal[i:i + 1], alone[0]) and torch.equal(offset[i:i + 1], alone[1])


def test_all_invalid_image_gives_zero_heights() -> None:
    depth = torch.zeros(1, 12, 16)
    height = height_above_floor(depth, torch.zeros_like(depth, dtype=torch.bool))
    assert torch.all(height == 0) and torch.isfinite(height).all()


def test_backproject_centre_ray_is_the_optical_axis() -> None:
    points = backproject(torch.full((1, 3, 5), 2.0))
    torch.testing.assert_close(points[0, 1, 2], torch.tensor([0.0, 0.0, 2.0]))


def test_preprocess_third_channel_is_scaled_height() -> None:
    assert input_channels(DEFAULT_NORMALISATION) == 3
    x = preprocess(_tilted_scene(h=480, w=640), (160, 120))
    box_height = np.median(x[2, 45:55, 60:75]) * DEFAULT_NORMALISATION["height_scale_m"]
    assert abs(box_height - 0.3) < 0.01
    assert input_channels(TWO_CHANNEL_NORMALISATION) == 2
    assert preprocess(_tilted_scene(), (16, 12), TWO_CHANNEL_NORMALISATION).shape[0] == 2


# A camera at the edge of the envelope (docs/interface.md §4): fx = fy = 590 px at 640 x 480
# and the principal point 8 px off the centre in both axes.
EDGE_CAMERA = Intrinsics(640, 480, 590.0, 590.0, 319.5 + 8.0, 239.5 - 8.0)


def _box_height(height: np.ndarray) -> float:
    """Median height of the box patch of ``_tilted_scene`` (a margin inside its edges)."""
    h, w = height.shape
    return float(np.median(height[h // 3 + h // 40: h // 2 - h // 40,
                                  w // 3 + w // 40: w // 2 - w // 40]))


def test_own_intrinsics_recover_a_rim_height_the_nominal_camera_misses() -> None:
    # The box top at the rim's 0.25 m: a few mm decide success or stuck_on_rim.
    depth = torch.from_numpy(_tilted_scene(h=480, w=640, box_height=0.25, camera=EDGE_CAMERA))
    valid = torch.ones_like(depth, dtype=torch.bool)[None]
    own = height_above_floor(depth[None], valid,
                             intrinsics=torch.from_numpy(EDGE_CAMERA.normalised())[None])
    nominal = height_above_floor(depth[None], valid)
    assert abs(_box_height(own[0].numpy()) - 0.25) < 0.001
    assert abs(_box_height(nominal[0].numpy()) - 0.25) > 0.003


def test_normalised_intrinsics_hold_at_the_working_size() -> None:
    # The camera is given for the 640 x 480 image; the heights are computed at 160 x 120.
    depth = _tilted_scene(h=480, w=640, box_height=0.25, camera=EDGE_CAMERA)
    norm = dict(DEFAULT_NORMALISATION, intrinsics=INTRINSICS_FROM_CAMERA_INFO)
    x = preprocess(depth, (160, 120), norm, EDGE_CAMERA.normalised())
    assert abs(_box_height(x[2]) * norm["height_scale_m"] - 0.25) < 0.002
    # A network trained on nominal heights gets nominal heights, intrinsics or not.
    nominal = preprocess(depth, (160, 120))
    np.testing.assert_array_equal(
        preprocess(depth, (160, 120), DEFAULT_NORMALISATION, EDGE_CAMERA.normalised()), nominal)
    assert abs(_box_height(nominal[2]) * norm["height_scale_m"] - 0.25) > 0.003


def test_intrinsics_k_round_trips_through_camera_info_fields() -> None:
    assert Intrinsics.from_k(640, 480, EDGE_CAMERA.k()) == EDGE_CAMERA


def _container_floor_scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """A noisy floor seen at 42 deg from 1.8 m, half of it behind a raised inner floor 0.02 m
    up (the container's, docs/interface.md §2) and its far rows out of range. Returns depth
    (1, h, w), validity (1, h, w) and the true outer-floor mask."""
    h, w = 120, 160
    depth = _tilted_scene(h, w, camera_height=1.8, elevation_deg=42.0, box_height=0.0)
    raised = np.zeros((h, w), bool)
    raised[30:90, w // 6: 5 * w // 6] = True
    depth = _tilted_scene(h, w, camera_height=1.8 - 0.02, elevation_deg=42.0,
                          box_height=0.0) * raised + depth * ~raised
    noise = np.random.default_rng(seed).normal(0.0, 0.002, depth.shape) * (depth / 2) ** 2
    valid = np.ones((h, w), bool)
    valid[:18] = False
    outer = ~raised & valid
    return (torch.from_numpy((depth + noise).astype(np.float32))[None],
            torch.from_numpy(valid)[None], outer)


def test_floor_fit_is_not_pulled_towards_the_container_inner_floor() -> None:
    depth, valid, outer = _container_floor_scene()
    fixed = height_above_floor(depth, valid)[0].numpy()
    assert abs(np.median(fixed[outer])) < 0.0005
    # Fit version 1 (models up to 0.1.7) settles on a plane tilted through both floors.
    legacy = height_above_floor(depth, valid, version=LEGACY_FLOOR_FIT)[0].numpy()
    assert abs(np.median(legacy[outer])) > 0.003


def test_floor_fit_version_is_recorded_and_validated() -> None:
    assert check_normalisation(DEFAULT_NORMALISATION)["floor_fit"] == FLOOR_FIT
    older = {k: v for k, v in DEFAULT_NORMALISATION.items() if k != "floor_fit"}
    assert check_normalisation(older)["floor_fit"] == LEGACY_FLOOR_FIT
    for bad in (0, 4, 2.0, True, "2"):
        with pytest.raises(ValueError, match="floor_fit"):
            check_normalisation(dict(DEFAULT_NORMALISATION, floor_fit=bad))
    with pytest.raises(ValueError, match="floor fit version"):
        height_above_floor(torch.ones(1, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool),
                           version=7)


def _table_scene(h: int = 120, w: int = 160) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """A table top 0.75 m above the room floor in the lower 55 % of the view, the room floor
    above it (farther away, enough of it to be the lowest plane's winner), and a 0.2 m box
    on the table."""
    a = math.radians(45.0)
    normal = np.array([0.0, -math.cos(a), -math.sin(a)])
    f = FOCAL_OVER_WIDTH * w
    u = (np.arange(w) - (w - 1) / 2) / f
    v = (np.arange(h) - (h - 1) / 2) / f
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1)
    along = rays @ normal
    surface = np.zeros((h, w))            # height above the room floor of what each ray sees
    table = np.zeros((h, w), bool)
    table[int(0.45 * h):, :] = True
    surface[table] = 0.75
    box = np.zeros((h, w), bool)
    box[int(0.6 * h): int(0.75 * h), w // 3: w // 2] = True
    surface[box] = 0.95
    depth = (surface - 2.0) / along
    return (torch.from_numpy(depth.astype(np.float32))[None],
            torch.ones(1, h, w, dtype=torch.bool), table & ~box)


def test_a_table_task_measures_heights_from_the_table_top_not_the_room_floor() -> None:
    depth, valid, table = _table_scene()
    from_floor = height_above_floor(depth, valid)[0].numpy()
    assert abs(np.median(from_floor[table]) - 0.75) < 0.01   # the lowest plane: the room floor
    from_table = height_above_floor(depth, valid, support_above_floor=(0.7, 0.8))[0].numpy()
    assert abs(np.median(from_table[table])) < 0.002
    # Seen without the room floor, the lowest plane is already the table: nothing changes.
    only_table = valid.clone()
    only_table[0, : int(0.45 * depth.shape[1])] = False
    a = height_above_floor(depth, only_table)[0].numpy()
    b = height_above_floor(depth, only_table, support_above_floor=(0.7, 0.8))[0].numpy()
    assert np.array_equal(a, b) and abs(np.median(a[table])) < 0.002


def test_support_band_is_validated_and_kept_by_the_normalisation() -> None:
    norm = dict(DEFAULT_NORMALISATION, support_above_floor=[0.7, 0.8])
    assert check_normalisation(norm)["support_above_floor"] == [0.7, 0.8]
    for bad in ([0.8, 0.7], [0.0, 0.5], 0.75, "table"):
        with pytest.raises(ValueError, match="support_above_floor"):
            check_normalisation(dict(DEFAULT_NORMALISATION, support_above_floor=bad))


def _noisy(depth: np.ndarray, seed: int, sd_m: float = 0.002) -> torch.Tensor:
    """The same view again with fresh axial noise: the next frame of a static camera."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(depth + rng.normal(0.0, sd_m, depth.shape).astype(np.float32))[None]


def test_floor_tracker_keeps_a_static_cameras_plane_and_refits_when_it_moves() -> None:
    scene = _tilted_scene()
    valid = torch.ones(1, *scene.shape, dtype=torch.bool)
    tracker = FloorTracker()
    fresh, kept = [], []
    for seed in range(4):
        frame = _noisy(scene, seed)
        fresh.append(height_above_floor(frame, valid)[0].numpy())
        kept.append(height_above_floor(frame, valid, tracker=tracker)[0].numpy())
    assert (tracker.refits, tracker.reused) == (1, 3)
    # A kept plane is one frame's fit: its heights agree with a fresh fit within the noise.
    box = np.zeros(scene.shape, bool)
    box[45:55, 58:75] = True
    for a, b in zip(fresh, kept, strict=True):
        assert abs(np.median(a[box]) - np.median(b[box])) < 0.002
        assert abs(np.median(b[box]) - 0.3) < 0.005
    # The camera drops 2 cm (more than the inlier band): the kept plane no longer fits.
    lower = _noisy(_tilted_scene(camera_height=1.48), 9)
    moved = height_above_floor(lower, valid, tracker=tracker)[0].numpy()
    assert tracker.refits == 2 and abs(np.median(moved[box]) - 0.3) < 0.005
    # New intrinsics refit without a check, even for the same depth.
    k = torch.tensor([[FOCAL_OVER_WIDTH * 1.02, FOCAL_OVER_WIDTH * 160 / 120 * 1.02, 0, 0]])
    height_above_floor(lower, valid, intrinsics=k, tracker=tracker)
    assert tracker.refits == 3
    with pytest.raises(ValueError, match="one image at a time"):
        height_above_floor(torch.cat([lower, lower]), valid.expand(2, -1, -1),
                           tracker=tracker)


def test_floor_tracker_refits_when_a_table_top_leaves_the_view() -> None:
    depth, valid, table = _table_scene()
    tracker = FloorTracker()
    band = (0.7, 0.8)
    first = height_above_floor(depth, valid, support_above_floor=band, tracker=tracker)
    assert abs(np.median(first[0].numpy()[table])) < 0.002
    # Most of the table top now invalid (e.g. covered): its plane no longer holds the share
    # of checked pixels it had, so the next frame is fitted afresh.
    covered = valid.clone()
    covered[0, :, : int(0.9 * depth.shape[2])] &= ~torch.from_numpy(table)[:, : int(
        0.9 * depth.shape[2])]
    height_above_floor(depth, covered, support_above_floor=band, tracker=tracker)
    assert tracker.refits == 2 and tracker.reused == 0


def _wall_behind_a_floor_strip(elevation_deg: float = 30.0) -> tuple[torch.Tensor, torch.Tensor,
                                                                    np.ndarray]:
    """A camera 1.5 m up, looking down at 30 degrees at a wall 2 m ahead: the wall fills most
    of the frame, the floor only its bottom rows (a shelf hung on a wall). Returns depth,
    validity and the floor's pixels."""
    h, w, f = 120, 160, 140.0
    el = np.radians(elevation_deg)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f, np.ones_like(u)], -1)
    # Camera frame -> world: x right, forward horizontal, z up.
    forward = np.array([0.0, np.cos(el), -np.sin(el)])
    down = np.array([0.0, -np.sin(el), -np.cos(el)])
    world = rays[..., 0:1] * np.array([1.0, 0, 0]) + rays[..., 1:2] * down \
        + rays[..., 2:3] * forward
    t_floor = np.where(world[..., 2] < 0, 1.5 / -world[..., 2], np.inf)
    t_wall = np.where(world[..., 1] > 0, 2.0 / world[..., 1], np.inf)
    t = np.minimum(t_floor, t_wall)
    depth = t * rays[..., 2]
    floor = t_floor < t_wall
    assert 0.1 < floor.mean() < 0.5  # the wall is the larger plane
    valid = np.isfinite(depth)
    return (torch.from_numpy(np.where(valid, depth, 0).astype(np.float32))[None],
            torch.from_numpy(valid)[None], floor)


def test_a_wall_facing_the_camera_is_never_the_support() -> None:
    depth, valid, floor = _wall_behind_a_floor_strip()
    intrinsics = torch.tensor([[140.0 / 160, 140.0 / 120, 0.0, 0.0]])
    heights = height_above_floor(depth, valid, intrinsics=intrinsics)[0].numpy()
    assert np.abs(heights[floor]).max() < 0.002            # measured from the floor
    # Version 2 took the wall (most pixels, nothing beneath it) for the floor.
    old = height_above_floor(depth, valid, intrinsics=intrinsics, version=2)[0].numpy()
    assert np.abs(old[floor]).max() > 0.2
