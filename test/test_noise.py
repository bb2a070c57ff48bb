"""The Kinect-v1 noise model (training/noise.py): statistics, geometry, determinism."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from task_outcome_ros.labels import BACKGROUND, DEFAULT_TABLE, IGNORE
from training.config import NoiseConfig
from training.noise import (
    apply_kinect_noise,
    nguyen_sigma_z,
    projector_shadow,
    quantisation_step,
    save_clean_vs_noisy_figure,
    sigma_z,
    speckle_holes,
)

# The default task's outcome ids (docs/interface.md §3).
SUCCESS, FELL_OUTSIDE, STUCK_ON_RIM = (DEFAULT_TABLE.outcome_ids[name] for name in
                                      DEFAULT_TABLE.outcome_names)

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
H, W = 480, 640
FX = 570.0
DEFAULT = NoiseConfig()
# Only the projector shadows left: no jitter, no axial noise, no holes, no grazing dropout.
SHADOWS_ONLY = dataclasses.replace(DEFAULT, lateral_sigma_px=0.0, sigma_disparity_px=0.0,
                                   grazing_sigma=0.0, speckle_rate=0.0,
                                   grazing_start_deg=90.0, grazing_full_deg=90.0)
BOX_ROWS, BOX_COLS = (150, 330), (250, 390)


def _plane(z: float, cos: float = 1.0, h: int = H, w: int = W):
    depth = np.full((h, w), z, np.float32)
    return depth, np.zeros((h, w), np.uint8), np.full((h, w), cos, np.float32)


def _wall_and_box(wall: float = 2.0, box: float = 1.5):
    """Fronto-parallel wall (background) with a box face (success) in front, NaN sky on top."""
    depth, labels, cos = _plane(wall)
    (r0, r1), (c0, c1) = BOX_ROWS, BOX_COLS
    depth[r0:r1, c0:c1] = box
    labels[r0:r1, c0:c1] = SUCCESS
    depth[:20] = np.nan
    cos[:20] = np.nan
    return depth, labels, cos


def _run(depth, labels, cos, cfg=DEFAULT, seed=0, fx=FX):
    return apply_kinect_noise(depth, labels, cos, fx, cfg, np.random.default_rng(seed))


@pytest.mark.parametrize("z", [1.0, 3.0])
def test_plane_spread_matches_sigma_z(z):
    noisy, _ = _run(*_plane(z), cfg=dataclasses.replace(DEFAULT, speckle_rate=0.0))
    values = noisy[np.isfinite(noisy)].astype(np.float64)
    assert values.size == H * W
    expected = float(sigma_z(z, FX, DEFAULT, include_quantisation=True))
    assert np.std(values) == pytest.approx(expected, rel=0.15)
    assert abs(np.mean(values) - z) < 0.1 * expected      # unbiased
    # The noise-only formula is Khoshelham's first-order disparity propagation.
    assert float(sigma_z(z, FX, DEFAULT)) == pytest.approx(
        z * z * DEFAULT.sigma_disparity_px / (FX * DEFAULT.baseline))


@pytest.mark.parametrize("fx", [525.0, 590.0])
def test_default_sigma_is_in_nguyens_range(fx):
    for z, rel in [(1.0, 0.25), (2.0, 0.15), (3.0, 0.15)]:
        model = float(sigma_z(z, fx, DEFAULT, include_quantisation=True))
        assert model == pytest.approx(float(nguyen_sigma_z(z)), rel=rel), (fx, z)


@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_depth_levels_are_spaced_by_the_quantisation_step(z):
    noisy, _ = _run(*_plane(z))
    levels = np.unique(noisy[np.isfinite(noisy)]).astype(np.float64)
    assert levels.size >= 3
    midpoints = (levels[1:] + levels[:-1]) / 2
    np.testing.assert_allclose(np.diff(levels), quantisation_step(midpoints, FX, DEFAULT),
                               rtol=2e-3)


def test_without_noise_depth_is_only_quantised():
    z = 2.0
    noisy, _ = _run(*_plane(z), cfg=SHADOWS_ONLY)
    assert np.unique(noisy).size == 1
    assert abs(float(noisy[0, 0]) - z) <= quantisation_step(z, FX, DEFAULT) / 2 + 1e-6


def test_invalid_is_nan_and_ignore_and_labels_stay_aligned():
    depth, labels, cos = _wall_and_box()
    noisy, lab = _run(depth, labels, cos)
    assert noisy.dtype == np.float32 and lab.dtype == np.uint8
    assert noisy.shape == lab.shape == (H, W)
    invalid = np.isnan(noisy)
    assert np.array_equal(invalid, lab == IGNORE)
    assert invalid[:18].all()                # no hit stays invalid (jitter may move the edge)
    assert 0 < invalid[20:].mean() < 0.05
    assert set(np.unique(lab[~invalid])) == {BACKGROUND, SUCCESS}
    # Jitter moves depth and labels together: the box's label goes with the box's depth.
    assert np.array_equal(lab[~invalid] == SUCCESS, noisy[~invalid] < 1.75)


def test_box_casts_a_shadow_on_the_projector_side_only():
    depth, labels, cos = _wall_and_box(wall=2.0, box=1.5)
    noisy, _ = _run(depth, labels, cos, cfg=SHADOWS_ONLY)
    shadow = np.isnan(noisy)
    shadow[:20] = False                                     # the sky, not a shadow
    (r0, r1), c0 = BOX_ROWS, BOX_COLS[0]
    width = FX * DEFAULT.baseline * (1 / 1.5 - 1 / 2.0)      # disparity jump, 7.1 px
    rows, cols = np.nonzero(shadow)
    assert rows.min() == r0 and rows.max() == r1 - 1
    # A band on the wall just left of the box (projector on the camera's right), none elsewhere.
    assert cols.max() == c0 - 1 and cols.min() >= c0 - math.ceil(width) - 1
    per_row = shadow[r0:r1].sum(axis=1)
    assert np.all(np.abs(per_row - width) <= 1.5)


def test_with_all_noise_the_shadow_stays_on_the_left():
    depth, labels, cos = _wall_and_box()
    noisy, _ = _run(depth, labels, cos, cfg=dataclasses.replace(DEFAULT, speckle_rate=0.0))
    invalid = np.isnan(noisy)
    (r0, r1), (c0, c1) = BOX_ROWS, BOX_COLS
    assert invalid[r0 + 5:r1 - 5, c0 - 5:c0 - 1].mean() > 0.9
    assert invalid[r0:r1, c1 + 2:c1 + 12].mean() < 0.02


def _tilted(z_left: float, z_right: float):
    """A plane whose inverse depth varies linearly along the rows (and a little down them)."""
    u = np.linspace(0.0, 1.0, W, dtype=np.float32)[None, :]
    v = np.linspace(0.0, 1.0, H, dtype=np.float32)[:, None]
    inv = (1 / z_left) + u * (1 / z_right - 1 / z_left) + 0.05 * v
    return (1.0 / inv).astype(np.float32)


@pytest.mark.parametrize("depth", [np.full((H, W), 2.0, np.float32), _tilted(1.2, 3.5),
                                   _tilted(3.5, 1.2)], ids=["flat", "receding", "approaching"])
def test_a_plane_casts_no_shadow(depth):
    _, labels, cos = _plane(1.0)
    noisy, _ = _run(depth, labels, cos, cfg=dataclasses.replace(DEFAULT, speckle_rate=0.0))
    assert not np.isnan(noisy).any()
    assert not projector_shadow(FX * DEFAULT.baseline / depth).any()


@pytest.mark.parametrize("angle_deg, dropped", [(30.0, 0.0), (70.0, 0.4), (88.0, 1.0)])
def test_grazing_surfaces_drop_out(angle_deg, dropped):
    noisy, _ = _run(*_plane(2.0, cos=math.cos(math.radians(angle_deg))),
                    cfg=dataclasses.replace(DEFAULT, speckle_rate=0.0))
    ramp = (angle_deg - DEFAULT.grazing_start_deg) / (
        DEFAULT.grazing_full_deg - DEFAULT.grazing_start_deg)
    assert dropped == pytest.approx(min(max(ramp, 0.0), 1.0))
    assert np.isnan(noisy).mean() == pytest.approx(dropped, abs=0.01)


def test_grazing_surfaces_are_noisier_as_nguyen_reports():
    z, theta = 2.0, math.radians(75.0)
    cfg = dataclasses.replace(DEFAULT, speckle_rate=0.0, grazing_start_deg=90.0,
                              grazing_full_deg=90.0)
    facing, _ = _run(*_plane(z, cos=1.0), cfg=cfg)
    grazing, _ = _run(*_plane(z, cos=math.cos(theta)), cfg=cfg)
    # Nguyen's angular term is added to the disparity-model sigma, then quantised.
    extra = float(nguyen_sigma_z(z, theta) - nguyen_sigma_z(z))
    expected = math.hypot(float(sigma_z(z, FX, cfg)) + extra,
                          float(quantisation_step(z, FX, cfg)) / math.sqrt(12))
    assert np.std(grazing) == pytest.approx(expected, rel=0.1)
    assert np.std(grazing) > 1.2 * np.std(facing)


def test_near_90_degrees_without_dropout_the_noise_stays_bounded():
    cfg = dataclasses.replace(DEFAULT, speckle_rate=0.0, grazing_start_deg=90.0,
                              grazing_full_deg=90.0)
    noisy, _ = _run(*_plane(2.0, cos=math.cos(math.radians(89.9))), cfg=cfg)
    assert np.isfinite(noisy).all()
    assert np.abs(noisy - 2.0).max() < 0.25                 # Nguyen's term capped at 85 deg


def test_nan_incidence_on_a_hit_is_not_dropped():
    noisy, _ = _run(*_plane(2.0, cos=float("nan")), cfg=dataclasses.replace(
        DEFAULT, speckle_rate=0.0))
    assert not np.isnan(noisy).any()


@pytest.mark.parametrize("z, valid", [(0.45, False), (0.6, True), (4.0, True), (4.7, False)])
def test_range_limits(z, valid):
    noisy, lab = _run(*_plane(z), cfg=dataclasses.replace(DEFAULT, speckle_rate=0.0))
    assert np.isfinite(noisy).all() if valid else np.isnan(noisy).all()
    assert (lab != IGNORE).all() if valid else (lab == IGNORE).all()


def test_speckle_holes_cover_the_expected_area():
    rate, radius = 4e-4, 3
    holes = speckle_holes((H, W), rate, radius, np.random.default_rng(1))
    disc = np.mean([cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)).sum()
                    for r in range(radius + 1)])
    assert holes.mean() == pytest.approx(rate * disc, rel=0.15)
    assert not speckle_holes((H, W), 0.0, radius, np.random.default_rng(1)).any()


def test_same_seed_same_bytes_other_seed_differs():
    scene = _wall_and_box()
    a_depth, a_lab = _run(*scene, seed=7)
    b_depth, b_lab = _run(*scene, seed=7)
    assert a_depth.tobytes() == b_depth.tobytes() and a_lab.tobytes() == b_lab.tobytes()
    c_depth, _ = _run(*scene, seed=8)
    assert a_depth.tobytes() != c_depth.tobytes()


@pytest.mark.parametrize("lateral", [0.0, 0.5])
def test_inputs_are_not_modified(lateral):
    depth, labels, cos = _wall_and_box()
    cos[200:220] = 0.05                                      # grazing strip
    copies = depth.copy(), labels.copy(), cos.copy()
    _run(depth, labels, cos, cfg=dataclasses.replace(DEFAULT, lateral_sigma_px=lateral))
    for before, after in zip(copies, (depth, labels, cos)):
        np.testing.assert_array_equal(before, after)


def test_disabled_noise_passes_depth_through():
    depth, labels, cos = _wall_and_box()
    noisy, lab = _run(depth, labels, cos, cfg=dataclasses.replace(DEFAULT, enabled=False))
    np.testing.assert_array_equal(noisy, depth)
    assert np.array_equal(lab == IGNORE, np.isnan(depth))


def test_other_image_sizes_and_strided_views_work():
    depth, labels, cos = _plane(2.0, h=61, w=97)
    noisy, lab = _run(depth, labels, cos)
    assert noisy.shape == lab.shape == (61, 97)
    depth, labels, cos = _wall_and_box()
    noisy, lab = _run(depth[:, ::2], labels[:, ::2], cos[:, ::2])
    assert noisy.shape == lab.shape == (H, W // 2)


def test_bad_inputs_name_the_argument():
    depth, labels, cos = _plane(2.0)
    with pytest.raises(ValueError, match="labels"):
        _run(depth, labels.astype(np.int32), cos)
    with pytest.raises(ValueError, match="cos_incidence"):
        _run(depth, labels, cos[:-1])
    with pytest.raises(ValueError, match="fx"):
        _run(depth, labels, cos, fx=0.0)


def test_figure_is_written(tmp_path):
    depth, labels, cos = _wall_and_box()
    noisy, lab = _run(depth, labels, cos)
    out = tmp_path / "preview" / "noise.png"
    save_clean_vs_noisy_figure(out, depth, noisy, lab)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_noise_imports_neither_torch_nor_rclpy():
    code = ("import sys, training.noise; "
            "bad = {'torch', 'rclpy'} & set(sys.modules); assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)
