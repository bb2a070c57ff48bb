"""Scene specs: a task described in one YAML file (``training/scenes/NAME.yaml``).

A spec has the sections of the dataset config that describe the world: ``scene`` (fixture,
support, objects, release), ``camera`` (the envelope), ``noise`` (the sensor model) and
``discover`` (clustering), plus a ``name`` and a ``description``. Its fields are exactly those
of the frozen dataclasses in ``training/config.py``, which stay the one schema: the spec is
loaded into them and validated by them before anything runs, and every error names the file,
the field and the allowed range. ``python -m training <stage> --scene NAME|FILE`` selects one;
the resolved config is saved in the run folder and in every checkpoint.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

from training.config import ConfigError, DatasetConfig, _from_dict

SCENES_DIR = Path(__file__).resolve().parent / "scenes"
SECTIONS = ("scene", "camera", "noise", "tof", "stereo", "discover")
DEFAULT_SCENE = "default"


def bundled_scenes() -> list[str]:
    return sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))


def spec_path(name_or_path: str | Path) -> Path:
    """A bundled spec's name (``tote``) or a file path -> the YAML file."""
    text = str(name_or_path)
    if text in bundled_scenes():
        return SCENES_DIR / f"{text}.yaml"
    path = Path(text)
    if not path.is_file():
        raise ConfigError(f"scene spec {text!r}: no such file, and not a bundled spec "
                          f"(bundled: {', '.join(bundled_scenes())})")
    return path


def read_spec(name_or_path: str | Path) -> tuple[str, dict[str, Any]]:
    """(spec name, its sections as plain data); YAML and top-level errors name the file."""
    import yaml

    path = spec_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the scene spec: {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a scene spec is a mapping with sections {SECTIONS}")
    unknown = sorted(set(data) - {*SECTIONS, "name", "description"})
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; expected {SECTIONS}, "
                          "name, description")
    name = data.get("name", path.stem)
    # The name becomes the shipped model's file and model_path:=<name>: a plain word.
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_-]+", name):
        raise ConfigError(f"{path}: name must be a non-empty string of letters, digits, _ "
                          f"and -, got {name!r}")
    return name, {k: data[k] for k in SECTIONS if k in data}


def load_scene(name_or_path: str | Path, **dataset_fields: Any) -> DatasetConfig:
    """The validated dataset config of a spec; ``dataset_fields`` (episodes, seed, ...) on top.

    Fields a spec leaves out keep the dataclass defaults, which are the default task's."""
    path = spec_path(name_or_path)
    name, sections = read_spec(path)
    _require_words(path, sections)
    try:
        parts = {key: _from_dict(type(getattr(DatasetConfig(), key)), value or {})
                 for key, value in sections.items()}
        return dataclasses.replace(DatasetConfig(), task=name, **parts,
                                   **dataset_fields).validate()
    except (ConfigError, TypeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _require_words(path: Path, sections: dict[str, Any]) -> None:
    """A spec of another fixture than the default task's open box must say what its outcomes
    are called and how its yardstick judges "inside": the defaults are the default task's
    (success, fell_outside, stuck_on_rim; the top below the rim)."""
    fixture = (sections.get("scene") or {}).get("fixture", "open_box")
    given = sections.get("discover") or {}
    missing = [k for k in ("outcome_names", "fixture_name", "yardstick_inside") if k not in given]
    if fixture != "open_box" and missing:
        raise ConfigError(f"{path}: a {fixture} task needs discover.{', discover.'.join(missing)} "
                          "(the defaults are the default task's container words)")
