"""Scene specs (training/scene.py): loading, validation and round trip, without simulating.

Every refusal must name the file, the field and what is allowed, before anything runs.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml

from training.__main__ import main
from training.config import (
    NOISE_PARAMETERS,
    ConfigError,
    DatasetConfig,
    dataset_config_from_dict,
    to_dict,
)
from training.scene import SCENES_DIR, bundled_scenes, load_scene, read_spec

pytestmark = pytest.mark.unit


def _spec(tmp_path: Path, data: dict, name: str = "cell.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def _tote_with(tmp_path: Path, section: str, field: str, value) -> Path:
    data = yaml.safe_load((SCENES_DIR / "tote.yaml").read_text())
    data.setdefault(section, {})[field] = value
    return _spec(tmp_path, data)


def test_bundled_specs_load_and_default_is_the_default_task():
    assert {"default", "tote"} <= set(bundled_scenes())
    default, nominal = load_scene("default"), DatasetConfig()
    # The default spec is the nominal scene with what real cells vary randomised: without
    # its tilt, roll, calibration error, second sensor and empty cells it is the configs'
    # defaults, and every sensor range holds the nominal value.
    assert dataclasses.replace(default.scene, support_tilt_deg=(0.0, 0.0),
                               empty_cell_share=0.0) == nominal.scene
    assert 0 < default.scene.empty_cell_share <= 0.1     # a few empty cells, most frames judged
    assert dataclasses.replace(default.camera, roll_deg=(0.0, 0.0), info_focal_error=0.0,
                               info_principal_error_px=0.0) == nominal.camera
    assert default.tof.share > 0 and nominal.tof.share == 0
    assert default.discover == nominal.discover
    for name in NOISE_PARAMETERS:
        lo, hi = default.noise.bounds(name)
        assert lo <= getattr(nominal.noise, name) <= hi, name
    assert any(isinstance(getattr(default.noise, n), tuple) for n in NOISE_PARAMETERS)
    tote = load_scene("tote")
    assert tote.task == "tote" and tote.scene.table_size is not None
    assert 0 < tote.scene.empty_cell_share <= 0.1        # as the default: a few empty cells
    assert set(tote.scene.shapes) == {"box", "cylinder"}
    assert tote.scene.inner_size_x == (0.30, 0.80) and tote.scene.inner_size_y == (0.25, 0.60)
    assert tote.camera.distance == (0.5, 1.3) and tote.camera.elevation_deg == (45.0, 90.0)


@pytest.mark.parametrize("name", ["default", "tote"])
def test_a_resolved_spec_round_trips_through_the_run_folder_json(name):
    cfg = load_scene(name, episodes=12, seed=4)
    assert dataset_config_from_dict(json.loads(json.dumps(to_dict(cfg)))) == cfg


def test_a_spec_may_leave_fields_to_the_default_task(tmp_path):
    cfg = load_scene(_spec(tmp_path, {"name": "wide", "scene": {"inner_size_x": [1.2, 1.4]}}))
    assert cfg.task == "wide" and cfg.scene.inner_size_x == (1.2, 1.4)
    assert cfg.scene.inner_size_y == DatasetConfig().scene.inner_size_y
    assert cfg.camera == DatasetConfig().camera


@pytest.mark.parametrize("section,field,value,says", [
    ("scene", "wal_height", [0.1, 0.2], ["SceneConfig", "wal_height"]),
    ("scene", "wall_height", [0.3, 0.1], ["scene.wall_height", "min must not exceed max"]),
    ("scene", "wall_height", [0.0, 0.2], ["scene.wall_height[0]", "[0.05, 1.0]"]),
    ("scene", "friction", "high", ["scene.friction", "(min, max) pair"]),
    ("scene", "max_objects", 2.5, ["scene.max_objects", "whole number"]),
    ("scene", "shape_weights", {"box": 1.0, "torus": 1.0}, ["shape_weights", "torus"]),
    ("scene", "table_size", [0.6, 0.6], ["scene.table_size", "along x", "make it at least"]),
    ("scene", "table_size", [[1.0, 0.9], [0.7, 1.5]], ["scene.table_size.x", "min must not"]),
    ("scene", "table_size", [[0.9, 2.0]], ["scene.table_size", "(x_min, x_max)"]),
    ("scene", "table_offset", 0.05, ["table_edge_margin", "leave table_offset at 0"]),
    ("scene", "table_edge_margin", 0.1, ["scene.table_size", "along x", "smallest table"]),
    ("camera", "distance", [0.2, 1.3], ["camera.distance", "0.3-3.5 m", "could not see"]),
    ("camera", "elevation_deg", [45.0, 95.0], ["camera.elevation_deg[1]", "[5.0, 90.0]"]),
    ("camera", "target_offset", 0.2, ["camera.target_offset", "could leave the fixture"]),
    ("noise", "model", "tof", ["noise.model", "kinect_v1", "the tof section"]),
    ("tof", "share", 1.5, ["tof.share", "[0.0, 1.0]"]),
    ("tof", "max_range", 1.0, ["camera.distance", "ToF sensor", "could not see"]),
    ("stereo", "share", 1.5, ["stereo.share", "[0.0, 1.0]"]),
    ("stereo", "share", 0.9, ["tof.share = 0.35", "stereo.share = 0.9", "together at most 1"]),
    ("stereo", "window_px", 4.5, ["stereo.window_px", "whole number"]),
    ("camera", "info_focal_error", 0.5, ["camera.info_focal_error", "[0.0, 0.2]"]),
    ("noise", "sigma_disparity_px", [0.1, 0.03], ["noise.sigma_disparity_px", "min must not"]),
    ("noise", "sigma_disparity_px", [0.03, 3.0], ["noise.sigma_disparity_px[1]", "[0.0, 2.0]"]),
    ("noise", "speckle_max_radius_px", [1, 2.5], ["speckle_max_radius_px[1]", "whole number"]),
    ("noise", "max_range", [0.2, 4.5], ["noise.max_range", "must exceed min_range"]),
    ("noise", "enabled", "yes", ["noise.enabled", "true or false"]),
])
def test_bad_fields_are_refused_naming_file_field_and_range(tmp_path, section, field, value,
                                                           says):
    path = _tote_with(tmp_path, section, field, value)
    with pytest.raises(ConfigError) as exc:
        load_scene(path)
    assert str(path) in str(exc.value)
    for text in says:
        assert text in str(exc.value), f"{text!r} missing from: {exc.value}"


@pytest.mark.parametrize("text,says", [
    ("scene: [unclosed", "not valid YAML"),
    ("- just\n- a list\n", "a scene spec is a mapping"),
    ("scene: {}\nlighting: {}\n", "unknown section(s) ['lighting']"),
    ("name: ''\n", "name must be a non-empty string"),
    ("name: ../cell\n", "letters, digits, _ and -"),
])
def test_malformed_files_are_refused_naming_the_file(tmp_path, text, says):
    path = tmp_path / "broken.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        read_spec(path)
    assert str(path) in str(exc.value) and says in str(exc.value)


def test_a_missing_spec_names_itself_and_the_bundled_ones(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_scene(tmp_path / "nowhere.yaml")
    assert "nowhere.yaml" in str(exc.value) and "tote" in str(exc.value)


def test_the_cli_refuses_a_bad_spec_before_anything_runs(tmp_path, capsys):
    bad = _tote_with(tmp_path, "scene", "inner_size_x", [0.9, 0.3])
    out = tmp_path / "run"
    assert main(["simulate", "--out", str(out), "--scene", str(bad), "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "scene.inner_size_x" in err
    assert not out.exists()


def test_a_run_folder_refuses_another_spec_but_resumes_its_own(tmp_path, capsys):
    from training.__main__ import build_parser, resolve_dataset_config
    from training.dataset import save_run_config

    out = tmp_path / "run"
    args = build_parser().parse_args(["simulate", "--out", str(out), "--scene", "tote",
                                      "--episodes", "3"])
    save_run_config(out, resolve_dataset_config(args))
    again = build_parser().parse_args(["simulate", "--out", str(out), "--scene", "tote"])
    assert resolve_dataset_config(again).episodes == 3  # the run's own size
    assert resolve_dataset_config(build_parser().parse_args(
        ["discover", "--out", str(out)])).task == "tote"  # no --scene: the run's own spec
    for stage in ("simulate", "discover", "render"):
        assert main([stage, "--out", str(out), "--scene", "default"]) == 2
        err = capsys.readouterr().err
        assert "made with scene 'tote'" in err and "leave --scene out" in err, err
