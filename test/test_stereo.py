"""The active-stereo sensor model (training/stereo.py) and its place among the sensor models."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from sensor_helpers import H, W, step_scene

from task_outcome_ros.labels import DEFAULT_TABLE, IGNORE
from training.config import ConfigError, DatasetConfig, StereoConfig, TofConfig
from training.islands import disparity_islands
from training.stereo import (
    STEREO_MODEL,
    apply_stereo_noise,
    block_noise,
    fatten_foreground,
)

pytestmark = pytest.mark.unit

FX = 557.5
QUIET = StereoConfig(share=1.0, sigma_disparity_px=0.0, mismatch_rate=0.0, speckle_rate=0.0,
                     disparity_subpixel=64)


def test_the_foreground_bleeds_over_the_background_and_takes_its_label_there() -> None:
    depth, labels, cos = step_scene()
    z, lab = apply_stereo_noise(depth, labels, cos, FX, dataclasses.replace(QUIET,
                                                                           fattening_px=2),
                                np.random.default_rng(0))
    # Right of the box: two columns read the box's depth and label, the third the plane's.
    np.testing.assert_allclose(z[:, 100:102], 1.7, atol=0.002)
    assert (lab[:, 100:102] == 2).all()
    np.testing.assert_allclose(z[:, 102], 2.0, atol=0.002)
    assert (lab[:, 102] == 0).all()
    # Left of it the right camera's occlusion, about the 2.5 px the disparity steps by there:
    # no match, as the projector's shadow in noise.py.
    assert np.isnan(z[:, 58:60]).all() and (lab[:, 58:60] == IGNORE).all()
    assert np.isfinite(z[:, :58]).all()
    plain, plain_lab = apply_stereo_noise(depth, labels, cos, FX, dataclasses.replace(
        QUIET, fattening_px=0), np.random.default_rng(0))
    np.testing.assert_allclose(plain[:, 100:102], 2.0, atol=0.002)
    assert (plain_lab[:, 100:102] == 0).all()


def test_slopes_are_not_fattened_only_steps_are() -> None:
    rows = np.linspace(1.6, 2.4, H, dtype=np.float32)[:, None]
    depth = np.repeat(rows, W, axis=1)                       # a floor receding row by row
    disparity = (FX * 0.05 / depth).astype(np.float32)
    labels = np.zeros((H, W), np.uint8)
    valid = np.ones((H, W), bool)
    fattened, lab = fatten_foreground(disparity, labels, valid, 3)
    np.testing.assert_array_equal(fattened, disparity)
    np.testing.assert_array_equal(lab, labels)


def test_disparity_noise_is_correlated_over_a_block_at_the_stated_deviation() -> None:
    noise = block_noise((240, 320), 7, np.random.default_rng(1))
    assert 0.85 < noise.std() < 1.15
    neighbours = np.corrcoef(noise[:, :-1].ravel(), noise[:, 1:].ravel())[0, 1]
    far = np.corrcoef(noise[:, :-8].ravel(), noise[:, 8:].ravel())[0, 1]
    assert neighbours > 0.7 and abs(far) < 0.05
    white = block_noise((240, 320), 1, np.random.default_rng(1))
    assert abs(np.corrcoef(white[:, :-1].ravel(), white[:, 1:].ravel())[0, 1]) < 0.05
    # In depth: sigma_z = z^2 sigma_d / (fx b) on a plane, as for the structured-light model.
    depth = np.full((H, W), 2.0, np.float32)
    cfg = dataclasses.replace(QUIET, sigma_disparity_px=0.1, window_px=3)
    z, _ = apply_stereo_noise(depth, np.zeros((H, W), np.uint8), np.ones((H, W), np.float32),
                              FX, cfg, np.random.default_rng(2))
    expected = 2.0 ** 2 * 0.1 / (FX * 0.05)
    assert 0.8 * expected < np.nanstd(z) < 1.2 * expected


def test_mismatched_islands_read_wrong_depth_and_keep_the_truth_as_labels() -> None:
    depth = np.full((H, W), 2.0, np.float32)
    labels = np.ones((H, W), np.uint8)
    cfg = dataclasses.replace(QUIET, mismatch_rate=2e-3, mismatch_max_radius_px=2,
                              mismatch_disparity_px=4.0)
    z, lab = apply_stereo_noise(depth, labels, np.ones((H, W), np.float32), FX, cfg,
                                np.random.default_rng(3))
    off = np.isfinite(z) & (np.abs(z - 2.0) > 0.05)
    assert 0.001 < off.mean() < 0.05
    assert (z[off] < 2.0).any() and (z[off] > 2.0).any()     # nearer and farther
    assert (lab[np.isfinite(z)] == 1).all()
    rng = np.random.default_rng(4)
    state = rng.bit_generator.state
    assert disparity_islands((H, W), 0.0, 3, 4.0, rng) == 0
    assert rng.bit_generator.state == state                  # draws nothing when off


def test_the_same_seed_gives_the_same_frame() -> None:
    depth, labels, cos = step_scene()
    cfg = StereoConfig(share=1.0)
    a = apply_stereo_noise(depth, labels, cos, FX, cfg, np.random.default_rng(5))
    b = apply_stereo_noise(depth, labels, cos, FX, cfg, np.random.default_rng(5))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    c = apply_stereo_noise(depth, labels, cos, FX, cfg, np.random.default_rng(6))
    assert not np.array_equal(np.nan_to_num(a[0]), np.nan_to_num(c[0]))


def test_stereo_config_validates_its_ranges_and_the_shares_together() -> None:
    StereoConfig(share=0.3, sigma_disparity_px=(0.05, 0.12), window_px=(5, 9)).validate()
    with pytest.raises(ConfigError, match="stereo.share"):
        StereoConfig(share=1.5).validate()
    with pytest.raises(ConfigError, match="fattening_px"):
        StereoConfig(fattening_px=(1, 2.5)).validate()
    with pytest.raises(ConfigError, match="grazing_full_deg"):
        StereoConfig(grazing_start_deg=80.0, grazing_full_deg=70.0).validate()
    drawn = StereoConfig(window_px=(5, 9)).draw(np.random.default_rng(0))
    assert drawn.window_px in range(5, 10) and isinstance(drawn.window_px, int)
    with pytest.raises(ConfigError, match="together at most 1"):
        DatasetConfig(tof=TofConfig(share=0.6), stereo=StereoConfig(share=0.5)).validate()


def test_a_share_of_frames_gets_the_stereo_sensor_and_the_others_are_unchanged() -> None:
    from training.render import render_episode

    episode = {"episode": 0, "container_yaw": 0.2, "floor_z": 0.0, "objects": []}
    before = DatasetConfig(tof=TofConfig(share=0.5)).validate()
    after = dataclasses.replace(before, stereo=StereoConfig(share=0.25)).validate()
    models = []
    for k in range(16):
        old = render_episode({**episode, "episode": k}, [], before, 2, DEFAULT_TABLE)
        new = render_episode({**episode, "episode": k}, [], after, 2, DEFAULT_TABLE)
        was, now = old["record"]["sensor"]["model"], new["record"]["sensor"]["model"]
        models.append(now)
        if now == was:   # the same draw picked the same model: the same frame, byte for byte
            np.testing.assert_array_equal(old["depth"], new["depth"])
            assert old["record"]["sensor"] == new["record"]["sensor"]
        else:            # only frames of the noise section's sensor may turn stereo
            assert (was, now) == ("kinect_v1", STEREO_MODEL)
            assert new["record"]["sensor"]["window_px"] == 7
    assert set(models) == {"tof", "kinect_v1", STEREO_MODEL}
