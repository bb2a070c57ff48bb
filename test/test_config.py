"""Configs of the offline pipeline (training/config.py) and the CLI's handling of bad input.

Pure functions and the CLI's argument checking: nothing here simulates or renders, so the
whole file runs in a few seconds (two subprocesses prove the real ``python -m training``).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from training.__main__ import COMMANDS, main
from training.config import (
    CameraConfig,
    ConfigError,
    DatasetConfig,
    SceneConfig,
    dataset_config_from_dict,
    save_json,
    to_dict,
)
from training.dataset import save_run_config

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]


def _replace(cfg: DatasetConfig, section: str | None, field: str, value) -> DatasetConfig:
    if section is None:
        return dataclasses.replace(cfg, **{field: value})
    return dataclasses.replace(
        cfg, **{section: dataclasses.replace(getattr(cfg, section), **{field: value})})


def _as_dict(section: str | None, field: str, value) -> dict:
    value = list(value) if isinstance(value, tuple) else value
    return {field: value} if section is None else {section: {field: value}}


# (section, field, bad value, text the message must hold: the field and the allowed range)
OUT_OF_RANGE = [
    (None, "episodes", 0, ["dataset.episodes", "[1, 10000000]"]),
    (None, "episodes", -5, ["dataset.episodes", "-5", "[1, 10000000]"]),
    (None, "workers", 0, ["dataset.workers", "[1, 256]"]),
    (None, "chunk_size", 0, ["dataset.chunk_size", "[1, 100000]"]),
    (None, "val_fraction", 0.9, ["dataset.val_fraction", "[0.0, 0.5]"]),
    ("scene", "min_objects", 0, ["scene.min_objects", "[1, 8]"]),
    ("scene", "max_objects", -1, ["scene.max_objects", "[1, 8]"]),
    ("scene", "wall_height", (0.0, 0.25), ["scene.wall_height[0]", "[0.05, 1.0]"]),
    ("scene", "inner_size_y", (0.05, 0.5), ["scene.inner_size_y[0]", "[0.1, 5.0]"]),
    ("scene", "release_orientation", "sideways", ["scene.release_orientation", "upright"]),
    ("scene", "shape_weights", (("box", 1.0), ("sphere", 1.0)),
     ["scene.shape_weights", "sphere", "cylinder"]),
    ("scene", "shape_weights", (("box", 0.0),), ["scene.shape_weights", "weight > 0"]),
    ("camera", "focal_px", (40.0, 590.0), ["camera.focal_px[0]", "40", "[50.0, 5000.0]"]),
    ("camera", "elevation_deg", (3.0, 65.0),
     ["camera.elevation_deg[0]", "3", "[5.0, 90.0]"]),
    ("camera", "distance", (1.6, 12.0), ["camera.distance[1]", "12.0", "[0.2, 10.0]"]),
    ("camera", "distance", (float("nan"), 2.0), ["camera.distance[0]", "[0.2, 10.0]"]),
    ("camera", "principal_offset_px", 130.0, ["camera.principal_offset_px", "[0.0, 120.0]"]),
    ("camera", "width", 0, ["camera.width", "[16, 4096]"]),
    # Envelopes that cannot see the fixture: beyond the sensor's range, or aimed off it.
    ("camera", "distance", (1.6, 5.0), ["camera.distance", "0.5-4.5 m", "could not see"]),
    ("camera", "target_offset", 0.6, ["camera.target_offset", "could leave the fixture"]),
]


@pytest.mark.parametrize("section,field,value,expected", OUT_OF_RANGE,
                         ids=[f"{s or 'dataset'}.{f}={v}" for s, f, v, _ in OUT_OF_RANGE])
def test_out_of_range_values_are_refused(section, field, value, expected):
    """Both the dataclass route and the dict route (config.json) refuse the value and name the
    field, the value and the allowed range."""
    with pytest.raises(ConfigError) as direct:
        _replace(DatasetConfig(), section, field, value).validate()
    with pytest.raises(ConfigError) as from_dict:
        dataset_config_from_dict(_as_dict(section, field, value))
    for exc in (direct.value, from_dict.value):
        for text in expected:
            assert text in str(exc), f"{text!r} missing from {exc}"


INVERTED = [
    ("scene", "object_edge", (0.30, 0.08)),
    ("scene", "friction", (1.0, 0.3)),
    ("camera", "focal_px", (590.0, 525.0)),
    ("camera", "distance", (2.4, 1.6)),
    ("camera", "elevation_deg", (65.0, 40.0)),
    ("scene", "inner_size_x", (0.8, 0.3)),
    ("scene", "wall_height", (0.3, 0.1)),
]


@pytest.mark.parametrize("section,field,value", INVERTED,
                         ids=[f"{s}.{f}" for s, f, _ in INVERTED])
def test_min_above_max_is_refused(section, field, value):
    with pytest.raises(ConfigError, match="min must not exceed max") as exc:
        dataset_config_from_dict(_as_dict(section, field, value))
    assert f"{section}.{field}" in str(exc.value)


def test_max_objects_below_min_objects_names_the_range():
    with pytest.raises(ConfigError) as exc:
        SceneConfig(min_objects=3, max_objects=2).validate()
    assert "scene.max_objects" in str(exc.value) and "[3, 8]" in str(exc.value)


def test_interval_must_be_a_pair():
    with pytest.raises(ConfigError, match=r"camera\.distance must be a \(min, max\) pair"):
        dataset_config_from_dict({"camera": {"distance": [1.6, 2.0, 2.4]}})


@pytest.mark.parametrize("data,cls,field", [
    ({"epsiodes": 10}, "DatasetConfig", "epsiodes"),
    ({"camera": {"focal": [530, 540]}}, "CameraConfig", "focal"),
    ({"scene": {"wal_height": 0.3}}, "SceneConfig", "wal_height"),
])
def test_unknown_fields_are_refused(data, cls, field):
    """A typo in config.json must not be silently ignored (the default would be used)."""
    with pytest.raises(ConfigError) as exc:
        dataset_config_from_dict(data)
    assert field in str(exc.value) and cls in str(exc.value)


def test_config_round_trips_through_json():
    """What a run saves (config.json) rebuilds the identical frozen config."""
    cfg = DatasetConfig(episodes=123, seed=9, workers=1, chunk_size=7,
                        camera=CameraConfig(distance=(1.7, 2.2)))
    text = json.dumps(to_dict(cfg))
    assert dataset_config_from_dict(json.loads(text)) == cfg
    assert dataset_config_from_dict({}) == DatasetConfig()


def test_defaults_are_the_contract_scene_and_camera():
    """docs/interface.md §1 and §4; every default config must also validate."""
    s = SceneConfig()
    assert s.wall_height == (0.25, 0.25)
    assert s.inner_size_x == s.inner_size_y == (1.0, 1.0)
    assert s.wall_thickness == 0.02
    assert (s.min_objects, s.max_objects) == (1, 4)
    assert s.shapes == {"box": 1.0} and s.table_size is None
    assert s.object_edge == (0.08, 0.30)
    assert s.release_height == (1.5, 1.5)
    assert s.inner_size_x[0] / 2 + s.release_margin == pytest.approx(0.6)
    assert s.release_frame == "world"
    c = CameraConfig()
    assert (c.width, c.height) == (640, 480)
    assert c.focal_px == (525.0, 590.0)
    assert c.principal_offset_px == 8.0
    assert c.distance == (1.6, 2.4)
    assert c.elevation_deg == (40.0, 65.0)
    assert c.target_offset == 0.1
    d = DatasetConfig()
    assert d.episodes == 10_000 and d.val_fraction == 0.05
    assert d.validate() is d


def test_camera_envelope_accepts_its_limits_only():
    """Fixed values and the limits themselves are allowed; anything wider is not."""
    CameraConfig(focal_px=(50.0, 50.0), distance=(0.2, 10.0),
                 elevation_deg=(90.0, 90.0)).validate()
    with pytest.raises(ConfigError):
        CameraConfig(focal_px=(525.0, 5000.5)).validate()


def test_configs_saved_before_the_scene_spec_still_load():
    """A run folder's config.json from before per-axis footprints and ranges."""
    old = {"scene": {"container_inner_size": 1.0, "wall_height": 0.25,
                     "release_above_rim": 1.5, "release_offset": 0.6}}
    scene = dataset_config_from_dict(old).scene
    assert scene.inner_size_x == scene.inner_size_y == (1.0, 1.0)
    assert scene.wall_height == (0.25, 0.25) and scene.release_height == (1.5, 1.5)
    assert scene.release_margin == pytest.approx(0.1)


# ---- the CLI --------------------------------------------------------------------------------

def _cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "training", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_unknown_stage_exits_nonzero_and_lists_the_stages():
    result = _cli("bogus")
    assert result.returncode != 0
    assert "bogus" in result.stderr
    for stage in COMMANDS:
        assert stage in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("option,value", [("--episodes", "-5"), ("--episodes", "0"),
                                          ("--workers", "0"), ("--chunk-size", "0"),
                                          ("--seed", "-1"), ("--episodes", "ten")])
def test_bad_counts_are_refused_with_a_message(tmp_path, capsys, option, value):
    with pytest.raises(SystemExit) as exc:
        main(["dataset", "--out", str(tmp_path / "run"), option, value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert option in err and value in err, err
    assert not (tmp_path / "run").exists(), "a refused command must not create the run folder"


def test_discover_on_an_empty_folder_is_a_clear_error(tmp_path):
    result = _cli("discover", "--out", str(tmp_path))
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert "error:" in result.stderr
    assert "chunk_0000000.json" in result.stderr and "missing" in result.stderr
    assert "simulate" in result.stderr
    assert list(tmp_path.iterdir()) == [], "discover must not write into a folder it refused"


def test_render_without_discovery_is_a_clear_error(tmp_path, capsys):
    assert main(["render", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "outcomes.json" in err and "does not exist" in err


def test_bad_saved_config_is_reported_not_raised(tmp_path, capsys):
    """A run folder whose config.json is outside the envelope: exit 2 naming the field."""
    bad = to_dict(DatasetConfig(episodes=2))
    bad["camera"]["elevation_deg"] = [3.0, 65.0]
    save_json(tmp_path / "config.json", bad)
    assert main(["simulate", "--out", str(tmp_path), "--episodes", "2", "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "camera.elevation_deg[0]" in err and "[5.0, 90.0]" in err
    assert not (tmp_path / "simulate").exists()


def test_run_folder_refuses_a_different_config(tmp_path, capsys):
    """Resuming with other options would mix two datasets in one folder."""
    save_run_config(tmp_path, DatasetConfig(episodes=2, workers=1))
    # Another worker count is fine (results do not depend on it) ...
    save_run_config(tmp_path, DatasetConfig(episodes=2, workers=2))
    # ... another seed is not.
    assert main(["simulate", "--out", str(tmp_path), "--episodes", "2", "--seed", "5"]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and "different config" in err
    assert not (tmp_path / "simulate").exists()
