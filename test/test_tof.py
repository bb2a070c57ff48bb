"""The time-of-flight sensor model (training/tof.py) and the structured-light model's drift."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from sensor_helpers import H, W, step_scene

from task_outcome_ros.labels import IGNORE
from training.config import ConfigError, NoiseConfig, TofConfig
from training.noise import apply_kinect_noise, calibration_drift
from training.tof import apply_tof_noise

pytestmark = pytest.mark.unit


def test_flying_pixels_sit_between_the_surfaces_at_depth_edges_only() -> None:
    depth, labels, cos = step_scene()
    cfg = TofConfig(share=1.0, sigma_1m=0.0, flying_pixel_rate=1.0, multipath_gain=0.0,
                    dropout_rate=0.0, amplitude_cutoff=0.0, amplitude_soft=0.0)
    z, lab = apply_tof_noise(depth, labels, cos, cfg, np.random.default_rng(0))
    between = (z > 1.71) & (z < 1.99)
    cols = np.flatnonzero(between.any(0))
    assert set(cols) <= {59, 60, 99, 100} and len(cols) == 4   # the edges' two sides
    assert between.mean() > 0.02
    assert np.array_equal(lab, labels)                        # labels stay their surface's


def test_tof_has_no_projector_shadow_where_structured_light_has_one() -> None:
    depth, labels, cos = step_scene()
    quiet = TofConfig(share=1.0, flying_pixel_rate=0.0, dropout_rate=0.0)
    z, _ = apply_tof_noise(depth, labels, cos, quiet, np.random.default_rng(1))
    assert np.isfinite(z).all()
    kinect = NoiseConfig(speckle_rate=0.0, lateral_sigma_px=0.0)
    zk, _ = apply_kinect_noise(depth, labels, cos, 557.5, kinect, np.random.default_rng(1))
    assert np.isnan(zk[:, 40:60]).any()                       # the band left of the box


def test_amplitude_dropout_takes_far_grazing_surfaces_first() -> None:
    depth = np.full((H, W), 1.0, np.float32)
    depth[:, W // 2:] = 4.0
    cos = np.full((H, W), 0.3, np.float32)
    cfg = TofConfig(share=1.0, amplitude_cutoff=0.02, amplitude_soft=0.01,
                    flying_pixel_rate=0.0, dropout_rate=0.0)
    z, lab = apply_tof_noise(depth, np.zeros((H, W), np.uint8), cos, cfg,
                             np.random.default_rng(2))
    assert np.isfinite(z[:, : W // 2 - 2]).all()              # amplitude 0.3: kept
    assert np.isnan(z[:, W // 2 + 2:]).all()                  # 0.3 / 16 < 0.02: dropped
    assert (lab[np.isnan(z)] == IGNORE).all()


def test_tof_noise_grows_with_range_and_is_seeded() -> None:
    cfg = TofConfig(share=1.0, sigma_1m=0.003, flying_pixel_rate=0.0, dropout_rate=0.0,
                    multipath_gain=0.0, amplitude_cutoff=0.0, amplitude_soft=0.0)
    spreads = []
    for z0 in (1.0, 2.0):
        depth = np.full((H, W), z0, np.float32)
        z, _ = apply_tof_noise(depth, np.zeros((H, W), np.uint8), np.ones((H, W), np.float32),
                               cfg, np.random.default_rng(3))
        spreads.append(float(np.std(z)))
    assert spreads[0] == pytest.approx(0.003, rel=0.1)
    assert spreads[1] == pytest.approx(0.012, rel=0.1)        # z^2
    depth, labels, cos = step_scene()
    a = apply_tof_noise(depth, labels, cos, TofConfig(share=1.0), np.random.default_rng(4))
    b = apply_tof_noise(depth, labels, cos, TofConfig(share=1.0), np.random.default_rng(4))
    assert np.array_equal(a[0], b[0], equal_nan=True) and np.array_equal(a[1], b[1])


def test_multipath_pushes_concave_corners_away() -> None:
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, :40] = 1.8                                       # a wall nearer on the left
    cfg = TofConfig(share=1.0, sigma_1m=0.0, flying_pixel_rate=0.0, dropout_rate=0.0,
                    amplitude_cutoff=0.0, amplitude_soft=0.0, multipath_gain=0.5,
                    multipath_window_px=15)
    z, _ = apply_tof_noise(depth, np.zeros((H, W), np.uint8), np.ones((H, W), np.float32),
                           cfg, np.random.default_rng(5))
    assert z[60, 41] > 2.02                                   # next to the nearer wall
    assert z[60, 120] == pytest.approx(2.0)                   # open floor unchanged


def test_tof_config_validates_its_ranges() -> None:
    TofConfig(share=0.3, sigma_1m=(0.001, 0.004), multipath_window_px=(9, 25)).validate()
    with pytest.raises(ConfigError, match="tof.share"):
        TofConfig(share=1.5).validate()
    with pytest.raises(ConfigError, match="sigma_1m"):
        TofConfig(sigma_1m=(0.004, 0.001)).validate()
    with pytest.raises(ConfigError, match="multipath_window_px"):
        TofConfig(multipath_window_px=(9.5, 25)).validate()
    drawn = TofConfig(sigma_1m=(0.001, 0.004)).draw(np.random.default_rng(0))
    assert 0.001 <= drawn.sigma_1m <= 0.004


def test_calibration_drift_draws_nothing_when_off_and_is_smooth_when_on() -> None:
    rng = np.random.default_rng(6)
    state = rng.bit_generator.state
    assert calibration_drift((H, W), NoiseConfig(), rng) == 0
    assert rng.bit_generator.state == state                  # no draws: old frames unchanged
    cfg = dataclasses.replace(NoiseConfig(), lowfreq_disparity_px=0.1)
    field = calibration_drift((H, W), cfg, np.random.default_rng(7))
    assert field.shape == (H, W) and 0.03 < field.std() < 0.2
    assert np.abs(np.diff(field, axis=1)).max() < 0.01       # smooth, not per-pixel noise
